"""The ordered stage registry: ``pcrelight run`` walks it, the CLI lists its verbs in its order and
``evaluate --run-all`` runs its expansion stages once per method.

Like OpenSfM's command list and COLMAP's automatic reconstructor: one list in pipeline order;
each stage declares every path it reads and writes in one workspace (the paths are defined in
:mod:`pipeline.io.workspace`), so an executor knows what to ship; a stage is skipped when its outputs
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

from ..config import StageConfig, TomlFile, load_toml, resolve
from ..errors import ConfigError, InputError
from .own import OwnConfig
from ..runtime import get_logger, progress
from ..io.workspace import FaceFolder, Workspace, report_of

log = get_logger("run")


@dataclass
class RunConfig(OwnConfig):
    """``[run]`` table of a pipeline config (with :class:`pipeline.run.own.OwnConfig`'s: your scan, photo, placement,
    camera)."""

    inputs: str = field(default="data_samples", metadata={"help": "folder with photo.exr, cloud_ldr.ply, scene.json, object.glb"})
    workspace: str = field(default="out/demo", metadata={"help": "output folder of every stage"})
    object: str = field(default="", metadata={"help": "the object to relight: glTF/GLB, OBJ or PLY (default: <inputs>/object.glb)"})
    view: str = field(default="view1", metadata={"help": "camera view of scene.json"})
    previews: bool = field(default=True, metadata={"help": "write PNG previews"})
    plan: bool = field(default=True, metadata={
        "help": "follow the planner (pipeline/run/plan.py): skip the stages the inputs do not need (no overexposed point: "
                "no expansion; nothing invalid: no poisson) and hand relight its BRDF; false: every stage runs"})
    report: bool = field(default=True, metadata={
        "help": "end by writing <workspace>/report.html (pcrelight report: one self-contained page of the run)"})
    hdr_out: bool = field(default=False, metadata={
        "help": "also write relit.hdr and composite.hdr (Radiance RGBE) beside the EXRs ([relight] hdr_out = true: "
                "relit.hdr only)"})


def workspace_of(cfg: RunConfig) -> Workspace:
    """The workspace of a ``[run]`` table; with ``cloud`` (your scan) the inputs are the imported cloud and the
    scene.json that :mod:`pipeline.run.own` writes in the workspace, the photo and object as given."""
    root = Path(cfg.workspace)
    own = dict(cloud_file=root / "cloud_ldr.ply", scene_file=root / "scene.json") if cfg.cloud else {}
    from ..expansion.photo_set import expand_photos

    photos = expand_photos(cfg.photo) if cfg.photo else []
    return Workspace(root if cfg.cloud else cfg.inputs, cfg.workspace, Path(cfg.object) if cfg.object else None,
                     cfg.previews, cfg.view, photo_file=photos[0] if photos else None,
                     photo_files=tuple(photos) if len(photos) > 1 else (), **own)


def _face_folder(ff: FaceFolder, key: Path) -> list[Path]:
    """A face folder as declared: the folder (every face in it), its NPZ and its report."""
    return [ff.path, key, ff.report]


@dataclass(frozen=True)
class Param:
    """A path (or name) that the stage's verb takes when run by hand: a positional argument (``flag`` empty) or
    an option. ``kind``: file, dir or text; ``name``: the keyword the verb's ``by_hand`` call receives. The
    stage's other options are its config dataclass's fields (``cli.stage`` makes them)."""

    name: str
    flag: str = ""
    help: str = ""
    kind: str = "file"
    required: bool = False
    multiple: bool = False


def _arg(name: str, kind: str = "file", required: bool = True) -> Param:
    return Param(name, "", "", kind, required)


def _opt(flag: str, help: str, kind: str = "file", required: bool = False, name: str = "", multiple: bool = False) -> Param:
    return Param(name or flag.lstrip("-").replace("-", "_"), flag, help, kind, required, multiple)


@dataclass(frozen=True)
class Stage:
    """One pipeline stage: its verb, its options class, the workspace paths it reads and the ones it
    always writes (a folder means the folder and every file in it), the name of its optional preview
    ``<root>/<preview>.png`` (written when previews are on and there is something to show), how
    to call it: ``call(module, workspace, cfg, preview path or None)``, and the files it writes only when
    an option asks (``optional``: relight's relit.hdr)."""

    verb: str
    config: str                       # "module:Class"
    inputs: Callable[[Workspace], list[Path]]
    outputs: Callable[[Workspace], list[Path]]
    call: Callable[[Any, Workspace, StageConfig, Path | None], Any]
    preview: str | None = None
    short: str = ""                   # the verb's one-line help
    doc: str = ""                     # the verb's help
    params: tuple[Param, ...] = ()    # the paths the verb takes by hand, in their order on the command line
    by_hand: Callable[..., Any] | None = None   # (module, cfg, preview, **params): the verb's call
    optional: Callable[[Workspace], list[Path]] = lambda w: []   # files written only when an option asks

    def config_class(self) -> type[StageConfig]:
        mod, _, cls = self.config.partition(":")
        return getattr(importlib.import_module(mod), cls)

    def preview_path(self, ws: Workspace) -> Path | None:
        return ws.preview(self.preview) if self.preview else None

    def all_outputs(self, ws: Workspace) -> list[Path]:
        """What the stage may write: its outputs, its preview and its optional outputs."""
        pv = self.preview_path(ws)
        return self.outputs(ws) + ([pv] if pv is not None else []) + self.optional(ws)

    def run(self, ws: Workspace, cfg: StageConfig) -> Any:
        return self.call(importlib.import_module(self.config.partition(":")[0]), ws, cfg, self.preview_path(ws))


# The pipeline in order. `pcrelight run`, the CLI's verb order and `evaluate --run-all` are derived from it.
STAGES: list[Stage] = [
    Stage("expose-match", "pipeline.expansion.expose_match:ExposeMatchConfig",
          lambda w: [*w.photos, w.cloud_ldr],
          lambda w: [w.exposure, w.photo_ldr, w.exposure_report, w.exposure_fit],
          lambda m, w, c, pv: m.run_expose_match(list(w.photos), w.cloud_ldr, w.exposure, w.photo_ldr, c, preview=pv),
          "expose_match", "match the photo's exposure to the cloud (Eq. 1)",
          "Find α so that clamp(α·photo, 0, 1) has the cloud's luminance histogram (§4.1, Eq. 1); with several PHOTOs "
          "(or a folder of them) each is registered and α, with one scale per photo, is fitted jointly.",
          (Param("photo", "", "", "path", True, True), _arg("cloud"), _opt("--out", "output exposure.npz", required=True),
           _opt("--photo-ldr", "output photo_ldr.exr", required=True)),
          lambda m, c, pv, photo, cloud, out, photo_ldr: m.run_expose_match(list(photo), cloud, out, photo_ldr, c, preview=pv)),
    Stage("render-cubemaps", "pipeline.expansion.render_cubemaps:RenderCubemapsConfig",
          lambda w: [w.cloud_ldr],
          lambda w: _face_folder(w.cubemaps, w.cubemaps.cameras),
          lambda m, w, c, pv: m.run_render_cubemaps(w.cloud_ldr, w.cubemaps.path, c, preview=pv),
          "cubemaps", "render cube maps of the LDR cloud",
          "Render the LDR cloud as point splats into cube maps with depth (§4.1).",
          (_arg("cloud"), _opt("--out", "output folder (faces + cameras.npz)", "dir", required=True)),
          lambda m, c, pv, cloud, out: m.run_render_cubemaps(cloud, out, c, preview=pv)),
    Stage("patchmatch", "pipeline.expansion.patchmatch:PatchmatchConfig",
          lambda w: [w.cubemaps.path, *w.photos, w.photo_ldr, w.exposure],
          lambda w: _face_folder(w.hdr_faces, w.hdr_faces.renderings),
          lambda m, w, c, pv: m.run_patchmatch(w.cubemaps.path, list(w.photos), w.photo_ldr, w.exposure, w.hdr_faces.path,
                                               c, preview=pv),
          "hdr_faces", "expand the cube-map faces to HDR",
          "Generalized PatchMatch against the photo, or an inverse tone-mapping baseline (§4.1).",
          (_arg("cubemaps", "dir"), _opt("--photo", "photo.exr (HDR); several photos, or a folder: the set expose-match "
                                          "read (default: the set exposure.npz records)", "path", multiple=True),
           _opt("--photo-ldr", "photo_ldr.exr from expose-match"), _opt("--exposure", "exposure.npz from expose-match"),
           _opt("--out", "output folder (HDR faces)", "dir", required=True)),
          lambda m, c, pv, cubemaps, photo, photo_ldr, exposure, out:
              m.run_patchmatch(cubemaps, list(photo) or None, photo_ldr, exposure, out, c, preview=pv)),
    Stage("reproject", "pipeline.expansion.reproject:ReprojectConfig",  # photo + exposure: for --method landis-pc|banterle-pc
          lambda w: [w.cloud_ldr, *([w.cubemaps.path, w.hdr_faces.path] if w.faces else []), *w.photos, w.exposure],
          lambda w: [w.cloud_proj, report_of(w.cloud_proj)],
          lambda m, w, c, pv: m.run_reproject(w.cloud_ldr, *((None, None) if c.method in m.PC_METHODS or not w.faces
                                                              else (w.cubemaps.path, w.hdr_faces.path)),
                                              w.cloud_proj, c, preview=pv, photo=list(w.photos), exposure=w.exposure),
          "cloud_proj", "project HDR faces back onto the points",
          "Give overexposed points the HDR values of the renderings that see them (§4.1).",
          (_arg("cloud"), _arg("cubemaps", "dir", False), _arg("renderings", "dir", False),
           _opt("--out", "output cloud PLY", required=True),
           _opt("--photo", "photo.exr (may be repeated, or a folder: the set expose-match read): the -pc methods' peak, and the registered photo's direct transfer (pmatch, with "
                "an exposure.npz that holds its camera; default: the photo patchmatch read, recorded in "
                "RENDERINGS/renderings.npz)", "path", multiple=True),
           _opt("--exposure", "exposure.npz: α for the -pc methods; with a registered camera (expose-match --photo-fov) "
                "the pmatch direct transfer and --unseen (default: the one patchmatch read, recorded in renderings.npz)")),
          lambda m, c, pv, cloud, cubemaps, renderings, out, photo, exposure:
              m.run_reproject(cloud, cubemaps, renderings, out, c, preview=pv, photo=list(photo) or None, exposure=exposure)),
    Stage("poisson", "pipeline.expansion.poisson:PoissonConfig",
          lambda w: [w.cloud_proj, w.cloud_ldr],
          lambda w: [w.cloud_hdr, report_of(w.cloud_hdr)],
          lambda m, w, c, pv: m.run_poisson(w.cloud_proj, w.cloud_hdr, c, preview=pv, ldr=w.cloud_ldr),
          "cloud_hdr", "fill points without HDR colour (Eq. 2–3)",
          "Solve the Poisson equation on the kNN graph for the invalid points (§4.2).",
          (_arg("cloud"), _opt("--out", "output cloud PLY", required=True),
           _opt("--ldr", "cloud_ldr.ply: exact LDR colours for the guidance (optional)")),
          lambda m, c, pv, cloud, out, ldr: m.run_poisson(cloud, out, c, preview=pv, ldr=ldr)),
    Stage("build-bsh", "pipeline.bsh.build_bsh:BuildBshConfig",  # bsh_cloud: cloud_hdr, or what the plan says
          lambda w: [w.bsh_cloud],
          lambda w: [w.bsh, report_of(w.bsh)],
          lambda m, w, c, pv: m.run_build_bsh(w.bsh_cloud, w.bsh, c, preview=pv),
          "bsh", "build the bounding sphere hierarchy",
          "Morton codes, Karras LBVH, spheres, normal cones, pruning, 40-byte nodes (§5.1, §5.4).",
          (_arg("cloud"), _opt("--out", "output bsh.npz", required=True)),
          lambda m, c, pv, cloud, out: m.run_build_bsh(cloud, out, c, preview=pv)),
    Stage("relight", "pipeline.relight.relight:RelightConfig",  # relit.png is its picture; no separate preview
          lambda w: [w.bsh, w.scene, w.object],
          lambda w: [w.relit_exr, w.relit, w.relit_stats],
          lambda m, w, c, pv: m.run_relight(w.bsh, w.relit_dir, c, object_path=w.object, scene_path=w.scene,
                                            view=w.view),
          None, "render the object relit by the cloud (PBGI)",
          "Point-based global illumination of the object: classic, mipmapped or hybrid (§5.2–5.4).",
          (_opt("--bsh", "bsh.npz from build-bsh", required=True),
           _opt("--object", "OBJ, PLY or glTF object; give it twice for two objects (each shadows the other)",
                name="object_path", multiple=True),
           _opt("--scene", "scene.json (camera views, object placement)"),
           _opt("--view", "view name in scene.json (view1, view2)", "text"),
           _opt("--out", "output folder", "dir", required=True)),
          lambda m, c, pv, bsh, object_path, scene, view, out:
              m.run_relight(bsh, out, c, object_path=list(object_path) or None, scene_path=scene, view=view, preview=pv),
          optional=lambda w: [w.relit_hdr]),                  # --hdr-out
]
VERBS = [s.verb for s in STAGES]
STAGE = {s.verb: s for s in STAGES}


# ----------------------------------------------------------------------------- jobs and their execution
@dataclass(frozen=True)
class Job:
    """One stage to run: its verb, its resolved options and the workspace it reads and writes. Picklable (the
    stage is looked up by its verb), so an executor may run it in another process. ``key``: its name in
    timings (the verb, unless a plan runs one stage several times, as ``evaluate --run-all`` does)."""

    verb: str
    cfg: StageConfig
    ws: Workspace
    key: str = ""

    @property
    def stage(self) -> Stage:
        return STAGE[self.verb]

    @property
    def name(self) -> str:
        return self.key or self.verb

    def inputs(self) -> list[Path]:
        return self.stage.inputs(self.ws)

    def outputs(self) -> list[Path]:
        return self.stage.outputs(self.ws)


def run_job(job: Job) -> float:
    """Run one job in this process (what an executor's worker calls); its wall seconds."""
    t0 = time.perf_counter()
    job.stage.run(job.ws, job.cfg)
    return time.perf_counter() - t0


def execute(job: Job, executor: Any = None) -> float:
    """Run ``job`` and wait for it: in this process (``executor`` None, what ``pcrelight run`` does) or on an
    :class:`pipeline.run.executor.Executor` (its ``map`` on this one job: a worker process, a Ray task). The job's
    error is raised here; the wall seconds of the stage are returned."""
    if executor is None:
        return run_job(job)
    for _, outcome in executor.map(run_job, [job]):
        if isinstance(outcome, BaseException):
            raise outcome
        return float(outcome)
    raise RuntimeError(f"executor {executor.describe()} returned nothing for {job.name}")


def execute_all(jobs: list[Job], executor: Any = None) -> dict[str, float]:
    """Run ``jobs`` in order (each may read what an earlier one wrote); seconds per job name."""
    secs: dict[str, float] = {}
    for job in progress(jobs, total=len(jobs), desc="jobs"):
        log.info("%s: running", job.name)
        secs[job.name] = round(execute(job, executor), 3)
        log.info("%s: done in %.1f s", job.name, secs[job.name])
    return secs


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


@dataclass
class RunPlan:
    """What ``pcrelight run`` does: its ``[run]`` options, the workspace, one job per stage from ``--from`` to
    ``--to`` (options resolved once, from the TOML file read once) and the planner's decisions
    (:class:`pipeline.run.plan.Plan`: the stages the inputs do not need, build-bsh's cloud, relight's BRDF; the
    decisions an earlier stage's output makes are taken when it has run)."""

    config: TomlFile | None
    run: RunConfig
    ws: Workspace
    jobs: list[Job]
    decisions: Any                              # pipeline.run.plan.Plan

    @property
    def cfgs(self) -> dict[str, StageConfig]:
        return {j.verb: j.cfg for j in self.jobs}


def _toml(config_toml: str | TomlFile | None) -> TomlFile | None:
    return config_toml if config_toml is None or isinstance(config_toml, TomlFile) else TomlFile(config_toml)


def plan(config_toml: str | TomlFile | None, from_stage: str | None = None, to_stage: str | None = None,
         seed: int | None = None, overrides: dict[str, Any] | None = None) -> RunPlan:
    """The run's plan: the stages from ``from_stage`` to ``to_stage`` as jobs with their resolved options (the TOML
    read once) and the planner's decisions (:mod:`pipeline.run.plan`). Reads the inputs the decisions need; writes
    nothing."""
    from . import plan as planner

    toml = _toml(config_toml)
    data = load_toml(toml) if toml is not None else {}
    unknown = sorted(k for k, v in data.items() if isinstance(v, dict) and k not in set(VERBS) | {"run"})
    if unknown:
        raise ConfigError(f"{toml}: unknown table [{unknown[0]}] (known: run, {', '.join(VERBS)})")
    if isinstance(data.get("run"), dict) and "seed" in data["run"]:
        raise ConfigError(f"{toml}: put 'seed' at the top of the file (it applies to every stage), not in [run]")
    rcfg = resolve(RunConfig, toml, "run", {**(overrides or {}), "seed": seed})
    for name in (from_stage, to_stage):
        if name is not None and name not in VERBS:
            raise ConfigError(f"--from/--to must be one of {', '.join(VERBS)}, got {name!r}")
    i0 = VERBS.index(from_stage) if from_stage else 0
    i1 = VERBS.index(to_stage) if to_stage else len(VERBS) - 1
    todo = STAGES[i0:i1 + 1]
    ws = workspace_of(rcfg)
    if i0 == 0 and not ws.cloud_ldr.exists():
        raise InputError(ws.cloud_ldr, "no such file (the [run] inputs folder must hold photo.exr and cloud_ldr.ply)")
    cfgs = {st.verb: resolve(st.config_class(), toml, st.verb, {"seed": seed}) for st in todo}
    if rcfg.hdr_out and "relight" in cfgs:
        cfgs["relight"] = dataclasses.replace(cfgs["relight"], hdr_out=True)
    known = dict(cfgs)                 # the planner also reads reproject's t_l and unseen when reproject is not run
    if "reproject" not in known and any(st.verb in planner.EXPANSION or st.verb == "build-bsh" for st in todo):
        known["reproject"] = resolve(STAGE["reproject"].config_class(), toml, "reproject", {"seed": seed})
    given = {v: set(t) for v, t in data.items() if isinstance(t, dict)}   # options the file sets: not decided again
    pl = planner.make_plan(ws, known, [st.verb for st in todo], follow=rcfg.plan, given=given)
    missing = [p for p in ws.photos if not p.exists()]
    if i0 == 0 and missing and not pl.skip_reason("expose-match"):
        raise InputError(missing[0], "no such file (the [run] inputs folder must hold photo.exr and cloud_ldr.ply; "
                                   "a cloud with overexposed points needs the photo)")
    return RunPlan(toml, rcfg, ws, [Job(st.verb, cfgs[st.verb], ws) for st in todo], pl)


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

    toml = _toml(config_toml)
    rc = resolve(RunConfig, toml, "run", {**(overrides or {}), "seed": seed})
    if rc.cloud and not workspace_of(rc).cloud_ldr.exists():
        raise NotYet("run --explain --cloud before the scan is imported: not implemented yet (run it once first)")
    rp = plan(toml, from_stage, to_stage, seed, overrides)
    pl, ws = rp.decisions, rp.ws
    lines = [f"plan of {toml} (inputs {ws.inputs}, workspace {ws.root}, {rp.jobs[0].verb} … "
             f"{rp.jobs[-1].verb}{'' if rp.run.plan else '; plan = false: every stage runs'}):"]
    stale = False                      # an earlier stage will (re)run: later outputs on disk are not this run's
    for job in rp.jobs:
        ws = _decide_before(pl, job.verb, ws, fresh=not stale)
        st = job.stage
        skip = pl.skip_reason(st.verb)
        kept = not skip and not force and not stale and _up_to_date(st.inputs(ws), st.outputs(ws))
        if kept and st.verb == "build-bsh":
            planner.emitters_from_file(pl, report_of(ws.bsh))
        stale = stale or not (skip or kept)
        lines.append(pl.stage_line(st.verb, str(ws.bsh_cloud), kept=kept))
    return lines


def _own_inputs(config_toml: str | TomlFile | None, seed: int | None, overrides: dict[str, Any] | None,
                force: bool) -> dict[str, Any] | None:
    """``run --cloud``: import the scan, place the object, choose the camera, write scene.json
    (:func:`pipeline.run.own.prepare`); the decisions, or None for a run on an inputs folder."""
    from . import own

    rcfg = resolve(RunConfig, config_toml, "run", {**(overrides or {}), "seed": seed})
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


def run_pipeline(config_toml: str | TomlFile | None, from_stage: str | None = None, to_stage: str | None = None,
                 force: bool = False, seed: int | None = None,
                 overrides: dict[str, Any] | None = None, executor: Any = None) -> dict[str, Any]:
    """Run the stages from ``from_stage`` to ``to_stage`` with the options of ``config_toml``
    (its ``[run]`` table and one table per verb): :func:`plan`, then each job in order — the decisions an
    earlier stage's output makes, skipped when the plan says so (``[run] plan = false``: every stage runs) or
    when its outputs are up to date (unless ``force``), else run by :func:`execute` (in this process, or on
    ``executor``, a :class:`pipeline.run.executor.Executor`) — and report: ``<workspace>/run.json`` with the plan,
    the resolved config of every stage, what ran, what was skipped and why, and the timings.

    Seeds: the file's top-level ``seed`` < a ``[verb]`` table's ``seed`` < ``seed`` (``--seed``;
    None = not given). ``overrides``: ``[run]`` options given on the command line (None = not given).
    """
    from .. import io
    from . import plan as planner

    toml = _toml(config_toml)
    own_report = _own_inputs(toml, seed, overrides, force)
    rp = plan(toml, from_stage, to_stage, seed, overrides)
    pl, ws = rp.decisions, rp.ws
    if own_report and own_report["photo_fov"] > 0:
        rp.jobs = [dataclasses.replace(j, cfg=dataclasses.replace(j.cfg, photo_fov=own_report["photo_fov"]))
                   if j.verb == "expose-match" else j for j in rp.jobs]
    ws.root.mkdir(parents=True, exist_ok=True)
    try:
        last = io.read_json(ws.run_report) if ws.run_report.exists() else {}
    except InputError:
        last = {}
    report: dict[str, Any] = {"config": str(toml), "run": rp.run.as_dict(), "plan": pl.as_dict(), "stages": {}}
    if own_report is not None:
        report["own"] = own_report
    for job in progress(rp.jobs, total=len(rp.jobs), desc="pipeline"):
        ws = _decide_before(pl, job.verb, ws)
        job = dataclasses.replace(job, ws=ws)
        entry: dict[str, Any] = {"config": job.cfg.as_dict(), "inputs": [str(p) for p in job.inputs()]}
        why = pl.skip_reason(job.verb)
        if why:
            log.info("%s: skipped by the plan: %s", job.verb, why)
            entry.update(skipped=True, plan=why)
        elif not force and _up_to_date(job.inputs(), job.outputs()) and _same_as_last(last, job.verb, entry["config"],
                                                                                      job.inputs()):
            log.info("%s: outputs up to date, skipped (use --force to rerun)", job.verb)
            entry["skipped"] = True
        else:
            given = pl.overrides(job.verb, job.cfg)
            if given:
                entry["from_plan"] = given
                job = dataclasses.replace(job, cfg=dataclasses.replace(job.cfg, **given))
            log.info("%s: running%s", job.verb, "".join(f" ({k} = {v} from the plan)" for k, v in given.items()))
            c0 = time.process_time()
            entry["seconds"] = round(execute(job, executor), 3)
            if executor is None:       # in this process: its CPU seconds (every thread; a worker's are not here)
                entry["cpu_s"] = round(time.process_time() - c0, 3)
            log.info("%s: done in %.1f s", job.verb, entry["seconds"])
        if job.verb == "build-bsh":
            entry["input"] = str(ws.bsh_cloud)
            planner.emitters_from_file(pl, report_of(ws.bsh))
        report["stages"][job.verb] = entry
        report.setdefault("order", []).append(job.verb)
        report["plan"] = pl.as_dict()
        io.write_json(ws.run_report, report)
    if rp.jobs[-1].verb == "relight" and ws.relit_exr.exists():
        report["composite"] = _composite(ws, force, rp.run.hdr_out)
        io.write_json(ws.run_report, report)
    log.info("pipeline finished: %s", ws.relit if rp.jobs[-1].verb == VERBS[-1] else ws.root)
    if rp.run.report:
        from .report import write_report

        write_report(ws.root, ws.report, inputs=ws.inputs)
    return report


def _composite(ws: Workspace, force: bool, hdr_out: bool = False) -> dict[str, Any]:
    """composite.exr/.png: relit.exr over the room's HDR cloud from the same camera (:func:`pipeline.run.own.composite`),
    redone when relit.exr or that cloud is newer; with ``hdr_out`` also composite.hdr (Radiance RGBE, its RGB)."""
    from .. import io
    from . import own

    outs = [ws.composite, ws.composite_exr] + ([ws.composite_hdr] if hdr_out else [])
    if not force and _up_to_date([ws.relit_exr, ws.bsh_cloud], outs):
        log.info("composite: up to date, kept (%s)", ws.composite)
        return {"skipped": True, "cloud": str(ws.bsh_cloud)}
    info = own.composite(ws.relit_exr, ws.bsh_cloud, ws.scene, ws.view, ws.relit_dir)
    if hdr_out:
        io.write_image(ws.composite_hdr, io.read_image(ws.composite_exr)[..., :3])
        log.info("wrote %s (Radiance RGBE) beside composite.exr", ws.composite_hdr)
    return info
