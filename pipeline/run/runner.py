"""The runner: ``pcrelight run`` as one plan (the TOML read once, a :class:`Job` a stage, the planner's decisions)
and its execution here or on an executor (:mod:`pipeline.run.executor`), skipping stages whose outputs are up to
date, honouring a stop request between stages, writing run.json and ending with the report. The stages themselves
are :data:`pipeline.run.stages.STAGES`."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..config import StageConfig, TomlFile, check_file, load_toml, resolve
from ..errors import ConfigError, InputError
from ..io.workspace import Workspace, report_of
from ..runtime import get_logger, progress
from .own import OwnConfig
from .stages import STAGE, STAGES, VERBS, RunConfig, Stage, workspace_of

log = get_logger("run")


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
    if toml is not None:
        check_file(data, toml)          # the one check every verb makes (an [evaluate] table is a verb's too)
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
    photo_view = ws.photo_view
    if verb == "relight" and ws.cloud_file is not None and ws.exposure.exists():
        photo_view = _registered_photo(ws)
    return dataclasses.replace(ws, hdr_cloud=pl.hdr_cloud(), faces=not pl.skip_reason("render-cubemaps"),
                               photo_view=photo_view)


def _registered_photo(ws: Workspace) -> bool:
    """Whether an own-room run's relight renders from the photo's camera and composites into it: exposure.npz holds
    one registered pinhole photo. Else one line says why the composite is over the cloud from the automatic camera."""
    from .. import io
    from ..relight.composite import registered

    ex = io.read_npz(ws.exposure, "pcrelight.exposure/1")
    if "photos" in ex:
        log.warning("composite: several photos: over the room's cloud from the automatic camera (composite into one "
                    "photo of a set is not built yet)")
        return False
    if not registered(ex):
        log.warning("composite: %s is not registered to the scan (no field of view: --photo-fov or EXIF, or the "
                    "registration was not confident; %s): over the room's cloud from the automatic camera", ws.photo,
                    ws.exposure_report)
        return False
    log.info("composite: the photo is registered: relight renders from its camera and composites into it")
    return True


def explain_pipeline(config_toml: str, from_stage: str | None = None, to_stage: str | None = None,
                     force: bool = False, seed: int | None = None,
                     overrides: dict[str, Any] | None = None) -> list[str]:
    """The plan of ``pcrelight run`` as lines (a header, then one line per stage: run / skipped, why, with the
    numbers), without running or writing anything. A decision that an earlier stage's output makes is taken
    from that output when it is up to date, else said to be made when the stage has run."""
    from . import own, plan as planner

    toml = _toml(config_toml)
    rc = resolve(RunConfig, toml, "run", {**(overrides or {}), "seed": seed})
    if rc.cloud and not workspace_of(rc).cloud_ldr.exists():          # the plan from the inputs' headers
        cfg = {v: resolve(STAGE[v].config_class(), toml, v, {"seed": seed}) for v in ("expose-match", "reproject",
                                                                                     "relight")}
        return own.explain_before_import(rc, cfg["expose-match"].photo_fov, cfg["reproject"].t_l, cfg["relight"])
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
    if rp.jobs[-1].verb == "relight" and ws.photo_view and ws.composite_exr.exists():
        from .. import io

        report["composite"] = io.read_json(ws.relit_stats).get("composite", {})     # relight wrote it, in the photo
    elif rp.jobs[-1].verb == "relight" and ws.relit_exr.exists():
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
