"""pcrelight command line: one verb per stage, each a thin wrapper over one library call.

Every stage verb takes explicit file paths, ``--config FILE.toml`` (its ``[<verb>]`` table;
command-line options win; unknown keys are an error), ``--seed``, ``--preview PNG``, ``-q/-v``.
Errors print one line ``pcrelight: <file>: <problem>`` and exit 1 (2 for usage, bad options and
stages not built yet, 128+N on signal N).
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import os
import signal
import sys
import traceback
import typing
from typing import Any, Callable

import click

from pipeline import __version__
from pipeline.config import StageConfig, describe, resolve
from pipeline.errors import ConfigError, Interrupted, PcrelightError
from pipeline.run.executor import EXECUTORS
from pipeline.runtime import install_signal_handlers, setup_logging, stop_signal
from pipeline.run.stages import STAGES, RunConfig, call_stage
from pipeline.verbs import VERB, VERBS as REGISTRY, verb_list

# The verbs in the registry's order (pipeline/verbs.py: every verb declared there once).
VERBS = [v.name for v in REGISTRY]


def _config_class(spec: str | None) -> type[StageConfig]:
    """``"pipeline.bsh.build_bsh:BuildBshConfig"`` → the class; the base config for a verb without options."""
    if spec is None:
        return StageConfig
    mod, _, name = spec.partition(":")
    return getattr(importlib.import_module(mod), name)


def _field_option(name: str, default: Any, help_: str, choices: tuple | None, tp: Any,
                  multiple: bool = False) -> Callable:
    flag = "--" + name.replace("_", "-")
    if multiple:  # a field whose metadata says "multiple": the option may be given several times
        return click.option(flag, name, type=str, multiple=True, default=None, help=help_ + " (may be repeated)")
    shown = ",".join(map(str, default)) if isinstance(default, (tuple, list)) else default
    text = f"{help_} [default: {shown}]" if help_ else f"[default: {shown}]"
    if tp is bool:
        return click.option(f"{flag}/--no-{name.replace('_', '-')}", name, default=None, help=text)
    ctype: Any = click.Choice([str(c) for c in choices]) if choices else (
        int if tp is int else float if tp is float else str)
    return click.option(flag, name, type=ctype, default=None, help=text,
                        metavar="X,Y,Z" if typing.get_origin(tp) in (tuple, list) else None)


def stage(verb: str) -> Callable:
    """Declare a verb with options (its :data:`pipeline.verbs.VERBS` row: options class, one-line help): common
    options, config-field options, error handling.

    The decorated function receives ``(cfg, preview, **its own click params)``. The verb is built when it is
    first looked up (``main.get_command``), so ``pcrelight relight`` imports the relight stage's module for its
    options and no other stage's (numba, trimesh, Open3D, SciPy: issue 23 item 3); the decorator returns ``fn``.
    """

    def deco(fn: Callable) -> Callable:
        main.commands.builders[verb] = lambda: _build_verb(verb, VERB[verb].config, VERB[verb].short, fn)
        return fn

    return deco


def tool(verb: str) -> Callable:
    """Declare a verb without an options class (report, batch, info: its own click options, no TOML table); its
    one-line help is the registry's. Built on first lookup, as :func:`stage`'s verbs."""

    def deco(fn: Callable) -> Callable:
        main.commands.builders[verb] = lambda: main.command(verb, short_help=VERB[verb].short)(fn)
        return fn

    return deco


def _build_verb(verb: str, config: str | None, short: str, fn: Callable) -> click.Command:
    """The click command of :func:`stage` (its config class imported now), registered in ``main``."""
    cls = _config_class(config)
    multi = {f.name for f in dataclasses.fields(cls) if f.metadata.get("multiple")}

    @functools.wraps(fn)
    def body(config_file, preview, quiet, verbose, **kw):
        fields = set(cls.field_names())
        own = {k: v for k, v in kw.items() if k not in fields}
        overrides = {k: (None if k in multi and not v else v) for k, v in kw.items() if k in fields}
        return _guard(verbose - quiet, lambda: fn(resolve(cls, config_file, verb, overrides), preview, **own))

    cmd = body
    for name, default, help_, choices, tp in reversed(describe(cls)):
        cmd = _field_option(name, default, help_, choices, tp, name in multi)(cmd)
    cmd = click.option("-v", "--verbose", count=True, help="more logging; tracebacks on errors")(cmd)
    cmd = click.option("-q", "--quiet", count=True, help="warnings and errors only")(cmd)
    cmd = click.option("--preview", type=click.Path(dir_okay=False), default=None,
                       help="also write a PNG preview to this path")(cmd)
    cmd = click.option("--config", "config_file", type=click.Path(dir_okay=False), default=None,
                       help=f"TOML file; its [{verb}] table sets options (command line wins)")(cmd)
    expert = {f.name for f in dataclasses.fields(cls) if f.metadata.get("expert")}
    if expert:
        cmd = click.option("--help-all", is_flag=True, expose_value=False, is_eager=True, callback=_help_all,
                           help="show the expert options too and exit")(cmd)
    built = main.command(verb, cls=_Grouped, help=(fn.__doc__ or short), short_help=short)(cmd)
    built.expert, built.fields = expert, set(cls.field_names())
    return built


def _help_all(ctx: click.Context, param: click.Parameter, value: bool) -> None:
    """``--help-all``: the verb's help with its expert options."""
    if value and not ctx.resilient_parsing:
        ctx.meta["pcrelight.help_all"] = True
        click.echo(ctx.get_help(), color=ctx.color)
        ctx.exit()


class _Grouped(click.Command):
    """A verb whose help lists the everyday options first and the expert knobs (config fields marked ``expert``)
    in their own section, shown by ``--help-all`` (``--help`` names how many there are)."""

    expert: set[str] = set()
    fields: set[str] = set()

    def format_options(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        every, expert = [], []
        common = {"config_file", "preview", "quiet", "verbose", "help", "help_all"}
        helps = {id(self.get_help_option(ctx))}
        order = sorted(self.get_params(ctx), key=lambda p: 2 if p.name in common or id(p) in helps
                       else 1 if p.name in self.fields else 0)
        for p in order:
            rv = p.get_help_record(ctx)
            if rv is not None:
                (expert if p.name in self.expert else every).append(rv)
        with formatter.section("Options"):
            formatter.write_dl(every)
        if expert and ctx.meta.get("pcrelight.help_all"):
            with formatter.section("Expert options (the trade of each: docs/relight.md, bench/)"):
                formatter.write_dl(expert)
        elif expert:
            formatter.write_paragraph()
            formatter.write_text(f"{len(expert)} expert options (the gather's knobs, each measured in docs/): "
                                 f"pcrelight {ctx.info_name} --help-all")


class _LazyCommands(dict):
    """``main.commands``: the verbs declared by :func:`stage` are built on first lookup (``builders``: verb → the
    function that builds and registers it); ``in``, ``[]`` and ``get`` see them all, iteration only the built ones."""

    def __init__(self) -> None:
        super().__init__()
        self.builders: dict[str, Callable[[], click.Command]] = {}

    def __missing__(self, name: str) -> click.Command:
        build = self.builders.pop(name, None)
        if build is None:
            raise KeyError(name)
        build()                            # registers itself (main.command)
        return dict.__getitem__(self, name)

    def get(self, name: str, default: Any = None) -> Any:  # type: ignore[override]
        try:
            return self[name]
        except KeyError:
            return default

    def __contains__(self, name: object) -> bool:
        return dict.__contains__(self, name) or name in self.builders

    def names(self) -> list[str]:
        """Every verb, built or not."""
        return [*dict.keys(self), *(v for v in self.builders if not dict.__contains__(self, v))]


class _LazyChoice(click.Choice):
    """A :class:`click.Choice` whose choices are computed when first needed (``make-scene --preset``: the preset
    files, read by the make-scene module, which ``pcrelight relight`` does not import)."""

    def __init__(self, get: Callable[[], Any]) -> None:
        self._get, self._choices = get, None
        super().__init__((), case_sensitive=True)

    @property
    def choices(self) -> tuple:  # type: ignore[override]
        if self._choices is None:
            self._choices = tuple(self._get())
        return self._choices

    @choices.setter
    def choices(self, value: Any) -> None:
        pass


def _exit_now(code: int) -> None:
    """Leave at once after a stop request, the clean-up done (temp files removed while the exception unwound):
    a native library's threads (Open3D, numba, Mesa) tearing down in the middle of their work crashed the
    interpreter's own shutdown (SIGSEGV/SIGABRT after the line was printed, make fuzz's signal trials)."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:  # a closed pipe: nothing more to say
            pass
    os._exit(code)


def _stopped(verbosity: int) -> None:
    """If a stop request arrived, whatever error it turned into (a C extension's import interrupted reads
    "ImportError: initialization failed"), answer the stop: its line, exit 128 + N."""
    sig = stop_signal()
    if sig is not None:
        if verbosity > 0:
            traceback.print_exc()
        click.echo(f"pcrelight: {Interrupted(sig)}", err=True)
        _exit_now(128 + sig)


def _guard(verbosity: int, call: Callable[[], Any]) -> Any:
    """Run a stage: logging, signal handling, one-line errors with the right exit status."""
    setup_logging(verbosity)
    install_signal_handlers()
    try:
        return call()
    except Interrupted as e:  # SIGINT/SIGTERM (a BaseException: no catch-all swallows it)
        if verbosity > 0:
            traceback.print_exc()
        click.echo(f"pcrelight: {e}", err=True)
        _exit_now(e.exit_code)
    except PcrelightError as e:
        _stopped(verbosity)
        if verbosity > 0:
            traceback.print_exc()
        click.echo(f"pcrelight: {e}", err=True)
        sys.exit(e.exit_code)
    except KeyboardInterrupt:
        click.echo("pcrelight: interrupted; outputs left as they were", err=True)
        sys.exit(130)
    except (click.exceptions.Exit, click.ClickException, SystemExit):
        raise
    except OSError as e:  # a folder or file the stage could not make or open (read-only, disk full, no permission)
        _stopped(verbosity)
        if verbosity > 0:
            traceback.print_exc()
        where = f"{e.filename}: " if e.filename else ""
        problem = e.strerror or (str(e).strip().splitlines() or [type(e).__name__])[0]
        click.echo(f"pcrelight: {where}{problem}", err=True)
        sys.exit(1)
    except MemoryError:
        click.echo("pcrelight: out of memory (lower --memory-budget or the sizes)", err=True)
        sys.exit(1)
    except Exception as e:  # a bug, not bad input: one line, the traceback with -v
        _stopped(verbosity)
        if verbosity > 0:
            traceback.print_exc()
        first = str(e).strip().splitlines()[0] if str(e).strip() else ""
        click.echo(f"pcrelight: internal error ({type(e).__name__}: {first}); rerun with -v for the traceback", err=True)
        sys.exit(1)


class _Ordered(click.Group):
    """Lists the verbs in pipeline order, as COLMAP's verb table does; a usage error (an option outside its
    choices or range, an unknown option, a missing argument) is one line ``pcrelight: <option>: <problem>``,
    exit 2, not click's three-line usage message (README "Exit status")."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.commands = _LazyCommands()

    def list_commands(self, ctx: click.Context) -> list[str]:
        names = self.commands.names() if isinstance(self.commands, _LazyCommands) else list(self.commands)
        return [v for v in VERBS if v in names] + sorted(set(names) - set(VERBS))

    def get_command(self, ctx: click.Context | None, cmd_name: str) -> click.Command | None:  # type: ignore[override]
        return self.commands.get(cmd_name)

    def main(self, *args: Any, standalone_mode: bool = True, **kwargs: Any) -> Any:
        if not standalone_mode:
            return super().main(*args, standalone_mode=False, **kwargs)
        program = not args and kwargs.get("args") is None          # the process's own command line (not a test's)
        try:
            self._main(*args, **kwargs)
        finally:
            # the work is done or refused: a stop from here on is ignored. The interpreter's shutdown puts the
            # default action back on every signal that has a Python handler, and a SIGINT/SIGTERM landing during
            # it killed the process (returncode -2/-15: make fuzz's import trials, ~1 in 16)
            if program:
                for sig in (signal.SIGINT, signal.SIGTERM):
                    signal.signal(sig, signal.SIG_IGN)

    def _main(self, *args: Any, **kwargs: Any) -> None:
        try:
            rv = super().main(*args, standalone_mode=False, **kwargs)
        except click.exceptions.UsageError as e:
            param = getattr(e, "param", None)
            opts = getattr(param, "opts", None) or []
            where = (max(opts, key=len) if opts else getattr(param, "name", None)) if param is not None else None
            msg = e.format_message().strip().splitlines()[0] if e.format_message().strip() else type(e).__name__
            if where and isinstance(e, click.exceptions.BadParameter):
                msg = msg.split(": ", 1)[1] if msg.startswith("Invalid value for ") and ": " in msg else msg
            cmd = f"pcrelight {e.ctx.info_name}" if e.ctx is not None and e.ctx.parent is not None else "pcrelight"
            prefix = f"{where}: " if where and where not in msg else ""
            click.echo(f"pcrelight: {prefix}{msg} (see `{cmd} --help`)", err=True)
            sys.exit(2)
        except click.exceptions.Abort:
            click.echo("pcrelight: interrupted; outputs left as they were", err=True)
            sys.exit(130)
        except click.ClickException as e:
            click.echo(f"pcrelight: {e.format_message()}", err=True)
            sys.exit(e.exit_code)
        except (Interrupted, KeyboardInterrupt) as e:   # a stop outside a stage's guard (before it, or after it returned)
            sig = e.signum if isinstance(e, Interrupted) else (stop_signal() or signal.SIGINT)
            click.echo(f"pcrelight: {Interrupted(sig)}", err=True)
            _exit_now(128 + int(sig))
        if stop_signal() is not None:                    # a stop that arrived as the stage returned: still a stop
            _stopped(0)
        sys.exit(rv if isinstance(rv, int) else 0)


@click.group(cls=_Ordered, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="pcrelight")
def main() -> None:
    """pcrelight — relight a 3D object by a scanned LDR point cloud.

    \b
    Verbs (each reads and writes files; `pcrelight run` chains the stages):
    {verbs}
    \b
    Worked example (the shipped sample, as `make demo` runs it):
      pcrelight expose-match data_samples/photo.exr data_samples/cloud_ldr.ply --photo-fov 70 \\
          --out out/demo/exposure.npz --photo-ldr out/demo/photo_ldr.exr
      pcrelight render-cubemaps data_samples/cloud_ldr.ply --size 256 --out out/demo/cubemaps
      pcrelight patchmatch out/demo/cubemaps --photo data_samples/photo.exr \\
          --exposure out/demo/exposure.npz --photo-ldr out/demo/photo_ldr.exr --out out/demo/hdr_faces
      pcrelight reproject data_samples/cloud_ldr.ply out/demo/cubemaps out/demo/hdr_faces --out out/demo/cloud_proj.ply
      pcrelight poisson out/demo/cloud_proj.ply --ldr data_samples/cloud_ldr.ply --out out/demo/cloud_hdr.ply
      pcrelight build-bsh out/demo/cloud_hdr.ply --out out/demo/bsh.npz
      pcrelight relight --bsh out/demo/bsh.npz \\
          --object data_samples/object.glb --scene data_samples/scene.json --view view1 --method hybrid --out out/demo
    or all at once: pcrelight run configs/demo.toml
    """


main.help = main.help.replace("{verbs}", "\n    ".join(verb_list("  ")))


# --------------------------------------------------------------------------- stage verbs
@stage("make-scene")
@click.option("--out", required=True, type=click.Path(file_okay=False), help="output folder")
@click.option("--preset", type=_LazyChoice(lambda: _config_class("pipeline.scene.make_scene:MakeSceneConfig").presets()),
              default=None,
              help="configs/scene/<preset>.toml: tiny (~20k points, tests), small (~200k, data_samples/), full (~3M), "
                   "lamps (a box room lit by small very bright lamps, tiny-sized)")
@click.option("--object", "object_path", type=click.Path(dir_okay=False), default=None,
              help="place this OBJ/PLY/glTF as object.* instead of the default knot")
@click.option("--only", type=click.Choice(["panorama"]), default=None,
              help="panorama: render only pano.exr (+ truth/truth_pano.npz, scene.json's \"panorama\") into the existing "
                   "make-scene folder OUT, from its scene.json, truth/truth.npz and cloud_gt.ply (what a full run writes)")
def make_scene(cfg, preview, out, preset, object_path, only):
    """Build the Sponza-style ground truth with Mitsuba 3: scene.json/xml + meshes, cloud_gt.ply,
    cloud_ldr.ply, photo.exr, the HDR panorama pano.exr, object.*, truth/ (references gather_*/full_*), previews/."""
    from pipeline.scene.make_scene import apply_preset, run_make_scene, run_panorama

    if preset is not None:
        cfg = apply_preset(preset, click.get_current_context().params)
    if only == "panorama":
        if object_path is not None:
            raise ConfigError("--only panorama renders the existing folder's room: --object does not apply")
        run_panorama(out, cfg, preview=preview if preview else True)
        return
    run_make_scene(out, cfg, object_path=object_path, preview=preview if preview else True)


@stage("import")
@click.argument("scan", type=click.Path(dir_okay=False))
@click.option("--out", required=True, type=click.Path(dir_okay=False), help="output cloud PLY (+ <stem>.json report)")
def import_(cfg, preview, scan, out):
    """Read a scan (PLY, PCD, XYZ/XYZN/XYZRGB/PTS, E57, LAS/LAZ) and write the pipeline's cloud: outliers
    removed, units and up axis detected (or --units, --up), metres, +Y up, linear colours, normals
    (estimated when missing), optionally voxel down-sampled; every decision logged and in <stem>.json."""
    from pipeline.ingest.import_scan import run_import

    run_import(scan, out, cfg, preview=preview)


@stage("merge-brackets")
@click.argument("photos", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("--out", required=True, type=click.Path(dir_okay=False), help="output HDR photo (EXR) + <stem>.json report")
def merge_brackets(cfg, preview, photos, out):
    """Merge JPEG/PNG/TIFF shots of one view at several exposure times (EXIF ExposureTime, or --times) into
    one HDR EXR: the camera's response recovered and the radiance merged by OpenCV (Debevec & Malik, or
    Robertson); the EXR is what expose-match, patchmatch and reproject read as the photo."""
    from pipeline.ingest.merge_brackets import run_merge_brackets

    run_merge_brackets(list(photos), out, cfg, preview=preview)


# The pipeline's stage verbs: generated from their STAGES rows (pipeline/run/stages.py: the paths each takes by hand,
# its help, its call); their options are their config dataclasses' fields (`stage`).
def _path_type(kind: str) -> Any:
    return {"file": click.Path(dir_okay=False), "dir": click.Path(file_okay=False)}.get(kind, str)


def _stage_verb(st: Any) -> None:
    """Declare the verb of one STAGES row: its path arguments and options (``st.params``), then :func:`stage`."""

    def call(cfg, preview, **paths):
        return call_stage(st.verb, cfg, preview, **paths)

    call.__doc__ = st.doc
    cmd: Callable = call
    for p in reversed(st.params):
        if not p.flag:
            cmd = click.argument(p.name, type=_path_type(p.kind), required=p.required, nargs=-1 if p.multiple else 1)(cmd)
        else:
            cmd = click.option(p.flag, p.name, type=_path_type(p.kind), required=p.required, multiple=p.multiple,
                               default=None, help=p.help)(cmd)
    stage(st.verb)(cmd)


for _st in STAGES:
    _stage_verb(_st)


class _StageVerbs(typing.Mapping[str, click.Command]):
    """The STAGES rows' verbs → their click commands, each built on first lookup (:class:`_LazyCommands`)."""

    def __getitem__(self, verb: str) -> click.Command:
        if verb not in {st.verb for st in STAGES}:
            raise KeyError(verb)
        return main.commands[verb]

    def __iter__(self) -> typing.Iterator[str]:
        return iter([st.verb for st in STAGES])

    def __len__(self) -> int:
        return len(STAGES)


STAGE_VERBS = _StageVerbs()


@stage("evaluate")
@click.option("--truth", required=True, type=click.Path(file_okay=False), help="ground-truth folder (make-scene)")
@click.argument("clouds", nargs=-1, type=click.Path(dir_okay=False))
@click.option("--json", "json_out", type=click.Path(dir_okay=False), help="output table.json")
@click.option("--md", "md_out", type=click.Path(dir_okay=False), help="output table.md")
@click.option("--exposure", type=click.Path(dir_okay=False), help="exposure.npz (for the α error)")
@click.option("--run-all", "run_all", type=click.Path(file_okay=False), default=None,
              help="first expand TRUTH's cloud_ldr.ply with every method into this folder, then evaluate them all")
def evaluate(cfg, preview, truth, clouds, json_out, md_out, exposure, run_all):
    """Cloud RMS (all / overexposed points), log-luminance RMS, α error; rendering RMS/SSIM.

    Each CLOUD is named by its file stem (cloud_<method>.ply → row <METHOD>)."""
    from pipeline.measure import evaluate as ev

    if run_all:
        return ev.run_all_photos(truth, run_all, click.get_current_context().params.get("config_file"), cfg, preview=preview)
    if len(cfg.photo_sets) > 1:
        raise ConfigError("--photo-sets: one set without --run-all (the photos the CLOUDS were expanded with)")
    photos = ev.photo_set(truth, cfg.photo_sets[0]) if cfg.photo_sets else None
    return ev.run_evaluate(truth, list(clouds), json_out, md_out, cfg, exposure=exposure, preview=preview, photos=photos)


@stage("trade")
@click.option("--scene", "scene_dir", required=True, type=click.Path(file_okay=False),
              help="make-scene folder (scene.json, cloud_ldr.ply, photo.exr, object, truth/full_<view>_<material>.exr)")
@click.option("--out", default=None, type=click.Path(file_okay=False),
              help="folder of trade.csv, trade.png, trade.json and fast/balanced/exact.toml [default: out/trade/<scene>]")
@click.option("--work", default=None, type=click.Path(file_okay=False),
              help="folder of the sweep's workspaces (kept for a resumed sweep) [default: <out>/work]")
def trade(cfg, preview, scene_dir, out, work):
    """Sweep the knobs that cost time (expansion, build-bsh, relight: every gatherer), measure each row's
    error against the path-traced references (4×4 block RMS, their noise removed) and its wall time; write
    trade.csv (a rerun resumes it), the Pareto front (trade.png) and the presets fast/balanced/exact picked from
    it by the rule of pipeline/measure/trade.py. --config's stage tables are the base configuration."""
    from pathlib import Path

    from pipeline.measure.trade import run_trade

    out = Path(out) if out else Path("out") / "trade" / Path(scene_dir).resolve().name
    run_trade(scene_dir, out, Path(work) if work else out / "work", cfg,
              config_toml=click.get_current_context().params.get("config_file"), preview=preview)


@stage("run")
@click.argument("config_toml", type=click.Path(dir_okay=False), required=False)
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default=None,
              help="the workspace folder (same as --workspace)")
@click.option("--from", "from_stage", default=None, help="first stage to run")
@click.option("--to", "to_stage", default=None, help="last stage to run")
@click.option("--force", is_flag=True, help="rerun stages whose outputs are up to date")
@click.option("--explain", is_flag=True, help="print the plan (what each stage would do and why, with the numbers) "
                                               "and exit without running or writing anything")
def run(cfg, preview, config_toml, from_stage, to_stage, force, explain, out_dir):
    """Run every stage in order on one workspace, following the plan (pipeline/run/plan.py: no overexposed
    point → no expansion, nothing invalid after reproject → no poisson, the object's BRDF; each decision
    logged with its number and written into run.json; --no-plan runs every stage). Skips stages whose outputs
    are newer than their inputs unless --force; stops cleanly between stages on SIGINT/SIGTERM. Options come
    from CONFIG_TOML (its top-level seed, [run] and one table per verb); --seed and the [run] options given
    here win. --explain prints the plan and runs nothing.

    \b
    Your object in your room, no config needed (README "Relight your own object in your own room"):
      pcrelight run --cloud office.ply --photo office.hdr --object helmet.glb --out out/office
    imports the scan, places the object on the floor, frames it and writes relit.png and composite.png."""
    from pipeline.run.runner import explain_pipeline, run_pipeline

    given = click.get_current_context().params
    if given.get("config_file"):
        raise ConfigError("run reads its options from CONFIG_TOML; --config is not used here")
    overrides = {k: given[k] for k in RunConfig.field_names() if k != "seed" and given.get(k) not in (None, ())}
    if out_dir is not None:
        overrides["workspace"] = out_dir
    if config_toml is None and not overrides.get("cloud"):
        raise ConfigError("run needs CONFIG_TOML, or --cloud SCAN --photo PHOTO --object ASSET --out DIR")
    if explain:
        click.echo("\n".join(explain_pipeline(config_toml, from_stage=from_stage, to_stage=to_stage, force=force,
                                              seed=given.get("seed"), overrides=overrides)))
        return None
    return run_pipeline(config_toml, from_stage=from_stage, to_stage=to_stage, force=force, seed=given.get("seed"),
                        overrides=overrides)


@tool("report")
@click.argument("workspace", type=click.Path(file_okay=False))
@click.option("--out", type=click.Path(dir_okay=False), default=None, help="output HTML [default: WORKSPACE/report.html]")
@click.option("--inputs", type=click.Path(file_okay=False), default=None,
              help="the run's inputs folder (photo.exr, cloud_ldr.ply…) [default: run.json's]")
@click.option("--table", type=click.Path(dir_okay=False), default=None,
              help="evaluate's table.json (table.png beside it) [default: WORKSPACE/table.json, when present]")
@click.option("--trade", type=click.Path(dir_okay=False), default=None,
              help="pcrelight trade's trade.csv (its Pareto PNG beside it) [default: WORKSPACE/trade.csv, when present]")
@click.option("--max-px", type=click.IntRange(64, 16384), default=1600, show_default=True,
              help="embedded images: longest side [px]; larger previews are downscaled")
@click.option("-q", "--quiet", count=True, help="warnings and errors only")
@click.option("-v", "--verbose", count=True, help="more logging; tracebacks on errors")
def report(workspace, out, inputs, table, trade, max_px, quiet, verbose):
    """One self-contained HTML page of a run's WORKSPACE (images embedded, no network): the inputs, the plan,
    every stage's status, decisions, numbers and previews, the timings, the relit image and the composite,
    Table 2 and the speed/accuracy trade when present. `pcrelight run` ends by writing it (--no-report: not)."""
    from pipeline.run.report import write_report

    _guard(verbose - quiet, lambda: write_report(workspace, out, inputs=inputs, table=table, trade=trade, max_px=max_px))


@tool("batch")
@click.argument("jobs_toml", type=click.Path(dir_okay=False))
@click.option("--executor", type=click.Choice(list(EXECUTORS)), default="local", show_default=True,
              help="where the jobs run: local = a process pool on this machine (spawn), ray = Ray (local or --address)")
@click.option("--address", default=None, help="Ray cluster to join (ray://HEAD:10001, HEAD:6379 or auto); "
                                              "default: start a Ray on this machine")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="jobs at once [default: this machine's CPUs; with --address the cluster's]")
@click.option("--gpus-per-job", type=click.FloatRange(min=0), default=0.0,
              help="ray: GPUs each job asks for; its worker's GL uses that GPU's EGL device [default: 0, CPU]")
@click.option("--force", is_flag=True, help="rerun jobs whose outputs are up to date")
@click.option("--seed", type=click.IntRange(min=0), default=None, help="every stage's seed (default: JOBS.toml's)")
@click.option("-q", "--quiet", count=True, help="warnings and errors only")
@click.option("-v", "--verbose", count=True, help="more logging (the workers' too); tracebacks on errors")
def batch(jobs_toml, executor, address, workers, gpus_per_job, force, seed, quiet, verbose):
    """Relight many jobs against one room: objects × views × materials × presets, or a turntable (JOBS.toml,
    see pipeline/run/batch.py). The expansion and the BSH are built once (skipped when up to date); each job
    writes <out>/<job>/ atomically and is skipped when done, so a killed batch resumes; then
    <out>/summary.csv, contact_sheet.png and batch.json. GL runs only in the workers."""
    from pipeline.run.batch import run_batch

    return _guard(verbose - quiet, lambda: run_batch(jobs_toml, executor, workers, address, force, seed,
                                                     verbosity=-1 if verbose == 0 else verbose,
                                                     gpus_per_job=gpus_per_job))


@tool("info")
@click.option("--json", "as_json", is_flag=True, help="print JSON")
def info(as_json):
    """Versions, the GL context (vendor/renderer/version) and whether GS + transform feedback work."""
    from pipeline.run.info import collect, format_info

    setup_logging(-1)
    data = collect()
    click.echo(format_info(data, as_json))
    sys.exit(0 if data["gl"].get("ok") else 1)


if __name__ == "__main__":
    main()
