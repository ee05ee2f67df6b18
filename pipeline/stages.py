"""The ordered stage registry: ``pcrelight run`` walks it, the CLI lists its verbs in its order and
``evaluate --run-all`` runs its expansion stages once per method.

Like OpenSfM's command list and COLMAP's automatic reconstructor: one list in pipeline order;
each stage declares every path it reads and writes in one workspace (the paths are defined in
:mod:`pipeline.workspace`), so an executor knows what to ship; a stage is skipped when its outputs
are newer than its inputs (unless ``--force``), and a stop request (SIGINT/SIGTERM) is honoured
between stages.
"""

from __future__ import annotations

import dataclasses
import importlib
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from .config import StageConfig, load_toml, resolve
from .errors import ConfigError, InputError
from .own import OwnConfig
from .runtime import get_logger, progress
from .workspace import FaceFolder, Workspace, report_of

log = get_logger("run")


@dataclass
class RunConfig(OwnConfig):
    """``[run]`` table of a pipeline config (with :class:`pipeline.own.OwnConfig`'s: your scan, photo, placement,
    camera)."""

    inputs: str = field(default="data_samples", metadata={"help": "folder with photo.exr, cloud_ldr.ply, scene.json, object.glb"})
    workspace: str = field(default="out/demo", metadata={"help": "output folder of every stage"})
    object: str = field(default="", metadata={"help": "the object to relight: glTF/GLB, OBJ or PLY (default: <inputs>/object.glb)"})
    view: str = field(default="view1", metadata={"help": "camera view of scene.json"})
    previews: bool = field(default=True, metadata={"help": "write PNG previews"})
    plan: bool = field(default=True, metadata={
        "help": "follow the planner (pipeline/plan.py): skip the stages the inputs do not need (no overexposed point: "
                "no expansion; nothing invalid: no poisson) and hand relight its BRDF; false: every stage runs"})
    report: bool = field(default=True, metadata={
        "help": "end by writing <workspace>/report.html (pcrelight report: one self-contained page of the run)"})


def workspace_of(cfg: RunConfig) -> Workspace:
    """The workspace of a ``[run]`` table; with ``cloud`` (your scan) the inputs are the imported cloud and the
    scene.json that :mod:`pipeline.own` writes in the workspace, the photo and object as given."""
    root = Path(cfg.workspace)
    own = dict(cloud_file=root / "cloud_ldr.ply", scene_file=root / "scene.json") if cfg.cloud else {}
    return Workspace(root if cfg.cloud else cfg.inputs, cfg.workspace, Path(cfg.object) if cfg.object else None,
                     cfg.previews, cfg.view, photo_file=Path(cfg.photo[0]) if cfg.photo else None, **own)


def _face_folder(ff: FaceFolder, key: Path) -> list[Path]:
    """A face folder as declared: the folder (every face in it), its NPZ and its report."""
    return [ff.path, key, ff.report]


@dataclass(frozen=True)
class Stage:
    """One pipeline stage: its verb, its options class, the workspace paths it reads and the ones it
    always writes (a folder means the folder and every file in it), the name of its optional preview
    ``<root>/<preview>.png`` (written when previews are on and there is something to show), and how
    to call it: ``call(module, workspace, cfg, preview path or None)``."""

    verb: str
    config: str                       # "module:Class"
    inputs: Callable[[Workspace], list[Path]]
    outputs: Callable[[Workspace], list[Path]]
    call: Callable[[Any, Workspace, StageConfig, Path | None], Any]
    preview: str | None = None

    def config_class(self) -> type[StageConfig]:
        mod, _, cls = self.config.partition(":")
        return getattr(importlib.import_module(mod), cls)

    def preview_path(self, ws: Workspace) -> Path | None:
        return ws.preview(self.preview) if self.preview else None

    def all_outputs(self, ws: Workspace) -> list[Path]:
        """What the stage may write: its outputs and its preview."""
        pv = self.preview_path(ws)
        return self.outputs(ws) + ([pv] if pv is not None else [])

    def run(self, ws: Workspace, cfg: StageConfig) -> Any:
        return self.call(importlib.import_module(self.config.partition(":")[0]), ws, cfg, self.preview_path(ws))


# The pipeline in order. `pcrelight run`, the CLI's verb order and `evaluate --run-all` are derived from it.
STAGES: list[Stage] = [
    Stage("expose-match", "pipeline.expose_match:ExposeMatchConfig",
          lambda w: [w.photo, w.cloud_ldr],
          lambda w: [w.exposure, w.photo_ldr, w.exposure_report, w.exposure_fit],
          lambda m, w, c, pv: m.run_expose_match(w.photo, w.cloud_ldr, w.exposure, w.photo_ldr, c, preview=pv),
          "expose_match"),
    Stage("render-cubemaps", "pipeline.render_cubemaps:RenderCubemapsConfig",
          lambda w: [w.cloud_ldr],
          lambda w: _face_folder(w.cubemaps, w.cubemaps.cameras),
          lambda m, w, c, pv: m.run_render_cubemaps(w.cloud_ldr, w.cubemaps.path, c, preview=pv),
          "cubemaps"),
    Stage("patchmatch", "pipeline.patchmatch:PatchmatchConfig",
          lambda w: [w.cubemaps.path, w.photo, w.photo_ldr, w.exposure],
          lambda w: _face_folder(w.hdr_faces, w.hdr_faces.renderings),
          lambda m, w, c, pv: m.run_patchmatch(w.cubemaps.path, w.photo, w.photo_ldr, w.exposure, w.hdr_faces.path,
                                               c, preview=pv),
          "hdr_faces"),
    Stage("reproject", "pipeline.reproject:ReprojectConfig",  # photo + exposure: for --method landis-pc|banterle-pc
          lambda w: [w.cloud_ldr, *([w.cubemaps.path, w.hdr_faces.path] if w.faces else []), w.photo, w.exposure],
          lambda w: [w.cloud_proj, report_of(w.cloud_proj)],
          lambda m, w, c, pv: m.run_reproject(w.cloud_ldr, *((None, None) if c.method in m.PC_METHODS or not w.faces
                                                              else (w.cubemaps.path, w.hdr_faces.path)),
                                              w.cloud_proj, c, preview=pv, photo=w.photo, exposure=w.exposure),
          "cloud_proj"),
    Stage("poisson", "pipeline.poisson:PoissonConfig",
          lambda w: [w.cloud_proj, w.cloud_ldr],
          lambda w: [w.cloud_hdr, report_of(w.cloud_hdr)],
          lambda m, w, c, pv: m.run_poisson(w.cloud_proj, w.cloud_hdr, c, preview=pv, ldr=w.cloud_ldr),
          "cloud_hdr"),
    Stage("build-bsh", "pipeline.build_bsh:BuildBshConfig",  # bsh_cloud: cloud_hdr, or what the plan says
          lambda w: [w.bsh_cloud],
          lambda w: [w.bsh, report_of(w.bsh)],
          lambda m, w, c, pv: m.run_build_bsh(w.bsh_cloud, w.bsh, c, preview=pv),
          "bsh"),
    Stage("relight", "pipeline.relight:RelightConfig",  # relit.png is its picture; no separate preview
          lambda w: [w.bsh, w.scene, w.object],
          lambda w: [w.relit_exr, w.relit, w.relit_stats],
          lambda m, w, c, pv: m.run_relight(w.bsh, w.relit_dir, c, object_path=w.object, scene_path=w.scene,
                                            view=w.view)),
]
VERBS = [s.verb for s in STAGES]
STAGE = {s.verb: s for s in STAGES}


def files_of(paths: list[Path]) -> list[Path]:
    """The files a declaration names: a file itself, every file under a folder (none if absent)."""
    out: list[Path] = []
    for p in paths:
        if p.is_dir():
            out += sorted(f for f in p.rglob("*") if f.is_file() and not f.name.startswith("."))
        elif p.exists():
            out.append(p)
    return out


def _up_to_date(ins: list[Path], outs: list[Path]) -> bool:
    if not all(o.exists() for o in outs):
        return False
    newest_in = max((p.stat().st_mtime for p in files_of(ins)), default=0.0)
    return min(o.stat().st_mtime for o in files_of(outs)) >= newest_in


def up_to_date(ins: list[Path], outs: list[Path]) -> bool:
    """Every output exists and none is older than the newest input (a folder: its files), as ``run`` decides."""
    return _up_to_date(ins, outs)


def _prepare(config_toml: str, from_stage: str | None, to_stage: str | None, seed: int | None,
             overrides: dict[str, Any] | None) -> tuple[RunConfig, Workspace, list[Stage], dict[str, StageConfig], Any]:
    """The ``[run]`` options, the workspace, the stages from ``from_stage`` to ``to_stage``, their resolved
    options (and reproject's, whose ``t_l`` the planner uses) and the plan (:mod:`pipeline.plan`)."""
    from . import plan as planner

    data = load_toml(config_toml) if config_toml is not None else {}
    unknown = sorted(k for k, v in data.items() if isinstance(v, dict) and k not in set(VERBS) | {"run"})
    if unknown:
        raise ConfigError(f"{config_toml}: unknown table [{unknown[0]}] (known: run, {', '.join(VERBS)})")
    if isinstance(data.get("run"), dict) and "seed" in data["run"]:
        raise ConfigError(f"{config_toml}: put 'seed' at the top of the file (it applies to every stage), not in [run]")
    rcfg = resolve(RunConfig, config_toml, "run", {**(overrides or {}), "seed": seed})
    for name in (from_stage, to_stage):
        if name is not None and name not in VERBS:
            raise ConfigError(f"--from/--to must be one of {', '.join(VERBS)}, got {name!r}")
    i0 = VERBS.index(from_stage) if from_stage else 0
    i1 = VERBS.index(to_stage) if to_stage else len(VERBS) - 1
    todo = STAGES[i0:i1 + 1]
    ws = workspace_of(rcfg)
    if i0 == 0 and not ws.cloud_ldr.exists():
        raise InputError(ws.cloud_ldr, "no such file (the [run] inputs folder must hold photo.exr and cloud_ldr.ply)")
    cfgs = {st.verb: resolve(st.config_class(), config_toml, st.verb, {"seed": seed}) for st in todo}
    if "reproject" not in cfgs and any(st.verb in planner.EXPANSION or st.verb == "build-bsh" for st in todo):
        cfgs["reproject"] = resolve(STAGE["reproject"].config_class(), config_toml, "reproject", {"seed": seed})
    pl = planner.make_plan(ws, cfgs, [st.verb for st in todo], follow=rcfg.plan)
    if i0 == 0 and not ws.photo.exists() and not pl.skip_reason("expose-match"):
        raise InputError(ws.photo, "no such file (the [run] inputs folder must hold photo.exr and cloud_ldr.ply; "
                                   "a cloud with overexposed points needs the photo)")
    return rcfg, ws, todo, cfgs, pl


def _decide_before(pl: Any, verb: str, ws: Workspace, fresh: bool = True) -> Workspace:
    """Make the decisions an earlier stage's output makes before ``verb`` runs (the faces: from exposure.npz; poisson:
    from cloud_proj.ply; when ``fresh`` — the earlier stage's outputs are what this run will use); the workspace with
    the cloud build-bsh reads and whether reproject reads the faces."""
    from . import plan as planner

    fa, po = pl.get("faces"), pl.get("poisson")
    if verb in planner.FACES + ("reproject",) and fa is not None and fa.needed is None and fresh:
        planner.faces_from_file(pl, ws.exposure)
    if verb in ("poisson", "build-bsh") and po is not None and po.needed is None and fresh:
        planner.poisson_from_file(pl, ws.cloud_proj)
    return dataclasses.replace(ws, hdr_cloud=pl.hdr_cloud(), faces=not pl.skip_reason("render-cubemaps"))


def explain_pipeline(config_toml: str, from_stage: str | None = None, to_stage: str | None = None,
                     force: bool = False, seed: int | None = None,
                     overrides: dict[str, Any] | None = None) -> list[str]:
    """The plan of ``pcrelight run`` as lines (a header, then one line per stage: run / skipped, why, with the
    numbers), without running or writing anything. A decision that an earlier stage's output makes is taken
    from that output when it is up to date, else said to be made when the stage has run."""
    from . import plan as planner
    from .own import NotYet

    rc = resolve(RunConfig, config_toml, "run", {**(overrides or {}), "seed": seed})
    if len(rc.photo) > 1:
        raise NotYet("several photos: not implemented yet (issue 25)")
    if rc.cloud and not workspace_of(rc).cloud_ldr.exists():
        raise NotYet("run --explain --cloud before the scan is imported: not implemented yet (run it once first)")
    rcfg, ws, todo, cfgs, pl = _prepare(config_toml, from_stage, to_stage, seed, overrides)
    lines = [f"plan of {config_toml} (inputs {ws.inputs}, workspace {ws.root}, "
             f"{todo[0].verb} … {todo[-1].verb}{'' if rcfg.plan else '; plan = false: every stage runs'}):"]
    stale = False                      # an earlier stage will (re)run: later outputs on disk are not this run's
    for st in todo:
        ws = _decide_before(pl, st.verb, ws, fresh=not stale)
        skip = pl.skip_reason(st.verb)
        kept = not skip and not force and not stale and _up_to_date(st.inputs(ws), st.outputs(ws))
        if kept and st.verb == "build-bsh":
            planner.emitters_from_file(pl, report_of(ws.bsh))
        stale = stale or not (skip or kept)
        lines.append(pl.stage_line(st.verb, str(ws.bsh_cloud), kept=kept))
    return lines


def _own_inputs(config_toml: str | None, seed: int | None, overrides: dict[str, Any] | None,
                force: bool) -> dict[str, Any] | None:
    """``run --cloud``: import the scan, place the object, choose the camera, write scene.json
    (:func:`pipeline.own.prepare`); the decisions, or None for a run on an inputs folder."""
    from . import own

    rcfg = resolve(RunConfig, config_toml, "run", {**(overrides or {}), "seed": seed})
    if len(rcfg.photo) > 1:
        raise own.NotYet("several photos: not implemented yet (issue 25)")
    if not rcfg.cloud:
        setup = [f.name for f in dataclasses.fields(OwnConfig) if f.name not in ("seed", "cloud", "photo")
                 and getattr(rcfg, f.name) != f.default]
        if setup:
            raise ConfigError(f"--{setup[0].replace('_', '-')} applies to your own scan: give --cloud (an inputs folder's "
                              "scene.json places the object and holds the views)")
        return None
    em = resolve(STAGE["expose-match"].config_class(), config_toml, "expose-match", {"seed": seed})
    return own.prepare(rcfg, Path(rcfg.workspace), rcfg.view, em.photo_fov, force=force)


def _same_as_last(last: dict[str, Any], verb: str, config: dict[str, Any], inputs: list[Path]) -> bool:
    """Whether the previous run.json ran ``verb`` with the same options and input paths (no previous record:
    True, the file times decide alone)."""
    import json

    prev = (last.get("stages") or {}).get(verb)
    if not isinstance(prev, dict) or "inputs" not in prev:
        return True
    now = json.loads(json.dumps({"config": config, "inputs": [str(p) for p in inputs]}, default=str))
    return prev.get("config") == now["config"] and prev.get("inputs") == now["inputs"]


def run_pipeline(config_toml: str | None, from_stage: str | None = None, to_stage: str | None = None,
                 force: bool = False, seed: int | None = None,
                 overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """Run the stages from ``from_stage`` to ``to_stage`` with the options of ``config_toml``
    (its ``[run]`` table and one table per verb), following the plan (:mod:`pipeline.plan`: the stages the
    inputs do not need are skipped, relight takes the planned BRDF; ``[run] plan = false`` runs every
    stage); writes ``<workspace>/run.json`` with the plan, the resolved config of every stage, what ran,
    what was skipped and why, and the timings.

    Seeds: the file's top-level ``seed`` < a ``[verb]`` table's ``seed`` < ``seed`` (``--seed``;
    None = not given). ``overrides``: ``[run]`` options given on the command line (None = not given).
    """
    from . import io
    from . import plan as planner

    own_report = _own_inputs(config_toml, seed, overrides, force)
    rcfg, ws, todo, cfgs, pl = _prepare(config_toml, from_stage, to_stage, seed, overrides)
    if own_report and own_report["photo_fov"] > 0 and "expose-match" in cfgs:
        cfgs["expose-match"] = dataclasses.replace(cfgs["expose-match"], photo_fov=own_report["photo_fov"])
    ws.root.mkdir(parents=True, exist_ok=True)
    try:
        last = io.read_json(ws.run_report) if ws.run_report.exists() else {}
    except InputError:
        last = {}
    report: dict[str, Any] = {"config": str(config_toml), "run": rcfg.as_dict(), "plan": pl.as_dict(), "stages": {}}
    if own_report is not None:
        report["own"] = own_report
    for st in progress(todo, total=len(todo), desc="pipeline"):
        ws = _decide_before(pl, st.verb, ws)
        cfg = cfgs[st.verb]
        entry: dict[str, Any] = {"config": cfg.as_dict(), "inputs": [str(p) for p in st.inputs(ws)]}
        why = pl.skip_reason(st.verb)
        if why:
            log.info("%s: skipped by the plan: %s", st.verb, why)
            entry.update(skipped=True, plan=why)
        elif not force and _up_to_date(st.inputs(ws), st.outputs(ws)) and _same_as_last(last, st.verb, entry["config"],
                                                                                       st.inputs(ws)):
            log.info("%s: outputs up to date, skipped (use --force to rerun)", st.verb)
            entry["skipped"] = True
        else:
            given = pl.overrides(st.verb, cfg)
            if given:
                entry["from_plan"] = given
                cfg = dataclasses.replace(cfg, **given)
            log.info("%s: running%s", st.verb, "".join(f" ({k} = {v} from the plan)" for k, v in given.items()))
            t0 = time.perf_counter()
            st.run(ws, cfg)
            entry["seconds"] = round(time.perf_counter() - t0, 3)
            log.info("%s: done in %.1f s", st.verb, entry["seconds"])
        if st.verb == "build-bsh":
            entry["input"] = str(ws.bsh_cloud)
            planner.emitters_from_file(pl, report_of(ws.bsh))
        report["stages"][st.verb] = entry
        report.setdefault("order", []).append(st.verb)
        report["plan"] = pl.as_dict()
        io.write_json(ws.run_report, report)
    if todo[-1].verb == "relight" and ws.relit_exr.exists():
        report["composite"] = _composite(ws, force)
        io.write_json(ws.run_report, report)
    log.info("pipeline finished: %s", ws.relit if todo[-1].verb == VERBS[-1] else ws.root)
    if rcfg.report:
        from .report import write_report

        write_report(ws.root, ws.report, inputs=ws.inputs)
    return report


def _composite(ws: Workspace, force: bool) -> dict[str, Any]:
    """composite.exr/.png: relit.exr over the room's HDR cloud from the same camera (:func:`pipeline.own.composite`),
    redone when relit.exr or that cloud is newer."""
    from . import own

    if not force and _up_to_date([ws.relit_exr, ws.bsh_cloud], [ws.composite, ws.composite_exr]):
        log.info("composite: up to date, kept (%s)", ws.composite)
        return {"skipped": True, "cloud": str(ws.bsh_cloud)}
    return own.composite(ws.relit_exr, ws.bsh_cloud, ws.scene, ws.view, ws.relit_dir)
