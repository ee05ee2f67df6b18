"""``pcrelight batch JOBS.toml``: relight many objects, views, materials and presets — or a turntable — against
one captured room, on an executor (:mod:`pipeline.run.executor`: ``local`` process pool, ``ray``).

JOBS.toml (paths relative to the current folder, as in every pcrelight config)::

    seed = 0                          # optional: every stage's seed (--seed wins)
    [batch]
    config = "configs/demo.toml"      # the pipeline config: its [run] inputs and workspace, its stage tables
    out = "out/batch"                 # job folders <out>/<job>/, summary.csv, contact_sheet.png, batch.json
    size = "128x128"                  # optional: relight --size of every job (default: each view's)
    [grid]                            # every combination (each key optional)
    objects = ["data_samples/object.glb"]   # default: the run's object
    views = ["view1", "view2"]        # scene.json views; default: all of them
    materials = ["lambert", "ggx0.25"]      # scene.json materials; "" = the object's own (default)
    presets = ["", "fast"]            # relight presets; "" = the config's [relight] (default)
    [turntable]                       # N views of one object, the camera turned about an axis
    object = "data_samples/object.glb"
    view = "view1"                    # the first camera (its size and field of view for all)
    axis = [0.0, 1.0, 0.0]            # through the view's target, right-handed: angle k·2π/N [rad]
    views = 36
    material = ""
    preset = ""

What runs where: the cloud's expansion and BSH (``pcrelight run --to build-bsh`` on the config: stages whose
outputs are up to date are skipped) run **once**, as one task on a worker; every job then reads that BSH from
the workspace (a shared path: on a cluster, a file system every node mounts at the same place). Each job
writes ``<out>/<job>/`` (relit.exr, relit.png, stats.json: each file atomically) and last ``done.json``
(the job, its resolved options, its seconds and worker, its error against the reference when the scene has
one); a worker reads the BSH from a copy on its node's disk, made once a node (:func:`node_local`). A job is
skipped when its done.json holds the same job and options and is newer than its inputs (the BSH, scene.json,
the object), so a killed batch resumes where it stopped. A job whose worker died runs again
(Ray reruns it itself; the local pool is restarted), up to ``retries`` times.

GL: the driver (this process) never creates a GL context — a context made in a parent makes forked children
hang. Each worker creates one on its first job (:func:`worker_context`) and keeps it for its later jobs; the
local executor starts workers by spawn, Ray's are processes of their own.
"""

from __future__ import annotations

import csv
import dataclasses
import itertools
import math
import os
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..config import load_toml, resolve
from ..errors import ConfigError, InputError, PcrelightError
from .executor import Executor, WorkerLost, make_executor
from ..runtime import check_interrupt, get_logger, progress_enabled

log = get_logger("batch")
OUTPUTS = ("relit.exr", "relit.png", "stats.json")      # what run_relight writes into a job folder
DONE = "done.json"                                      # written last: the job is complete
RUNNING = "running.json"                                # the worker running the job (host:pid), while it runs
SHEET_MAX = 100                                         # tiles of the contact sheet (evenly spaced jobs beyond)


# --------------------------------------------------------------------------- the job list
@dataclass(frozen=True)
class BatchJob:
    """One relit image: an object seen from a scene.json view (or a turntable angle of it), one material
    (scene.json's ``materials``; "" = the object's own) and one relight preset ("" = the config's)."""

    name: str
    object: str                     # absolute path
    view: str
    material: str = ""
    preset: str = ""
    turntable: tuple[float, ...] = ()   # (axis x, y, z, angle [rad]) for a turntable view, else ()


@dataclass
class Batch:
    """A parsed JOBS.toml: the pipeline config, the output folder, the seed and the jobs."""

    jobs_toml: Path
    config: Path
    out: Path
    seed: int | None
    size: str
    retries: int
    jobs: list[BatchJob] = field(default_factory=list)


def _strings(v: Any, where: str, key: str) -> list[str]:
    if isinstance(v, str):
        return [v]
    if not isinstance(v, list) or not all(isinstance(x, str) for x in v) or not v:
        raise ConfigError(f"{where}: '{key}' must be a string or a non-empty list of strings, got {v!r}")
    return list(v)


def _stem(p: str) -> str:
    return Path(p).stem


def read_batch(jobs_toml: str | os.PathLike, seed: int | None = None) -> Batch:
    """Parse JOBS.toml (module docstring) into a :class:`Batch`; every job checked against scene.json (objects
    exist, views and materials are the scene's). ``seed``: --seed (None: the file's)."""
    from .. import io
    from .stages import RunConfig, workspace_of

    path = Path(jobs_toml)
    data = load_toml(path)
    unknown = sorted(set(data) - {"seed", "batch", "grid", "turntable"})
    if unknown:
        raise ConfigError(f"{path}: unknown key or table '{unknown[0]}' (known: seed, [batch], [grid], [turntable])")
    b = data.get("batch", {})
    bad = sorted(set(b) - {"config", "out", "size", "retries"}) if isinstance(b, dict) else ["(not a table)"]
    if bad:
        raise ConfigError(f"{path}: unknown key '{bad[0]}' in [batch] (known: config, out, retries, size)")
    if "config" not in b:
        raise ConfigError(f"{path}: [batch] needs config = \"<pipeline config>.toml\"")
    config = Path(b["config"]).resolve()
    if not config.exists():
        raise InputError(config, f"no such file ([batch] config of {path})")
    seed = seed if seed is not None else data.get("seed")
    if seed is not None and (not isinstance(seed, int) or seed < 0):
        raise ConfigError(f"{path}: seed must be an integer ≥ 0, got {seed!r}")
    retries = b.get("retries", 2)
    if not isinstance(retries, int) or not 0 <= retries <= 100:
        raise ConfigError(f"{path}: [batch] retries must be an integer in [0, 100], got {retries!r}")
    batch = Batch(path, config, Path(b.get("out", "out/batch")).resolve(), seed, str(b.get("size", "")), retries)
    if batch.size:
        from ..camera import parse_size

        parse_size(batch.size)
    ws = workspace_of(resolve(RunConfig, config, "run", {}))
    scene = io.read_json(ws.scene)
    views = scene.get("views", {}) if isinstance(scene, dict) else {}
    mats = scene.get("materials", {}) if isinstance(scene, dict) else {}
    default_obj = str(ws.object.resolve())

    def check(obj: str, view: str, mat: str, where: str) -> str:
        p = Path(obj).resolve()
        if not p.is_file():
            raise InputError(p, f"no such object file ({where})")
        if view not in views:
            raise ConfigError(f"{path}: {where}: no view '{view}' in {ws.scene} (have: {', '.join(views) or 'none'})")
        if mat and mat not in mats:
            raise ConfigError(f"{path}: {where}: no material '{mat}' in {ws.scene} (have: {', '.join(mats) or 'none'})")
        return str(p)

    g = data.get("grid")
    if g is not None:
        if not isinstance(g, dict) or set(g) - {"objects", "views", "materials", "presets"}:
            raise ConfigError(f"{path}: [grid] takes objects, views, materials, presets")
        objs = _strings(g.get("objects", [default_obj]), str(path), "objects")
        for o, v, m, pr in itertools.product(objs, _strings(g.get("views", list(views)), str(path), "views"),
                                             _strings(g.get("materials", [""]), str(path), "materials"),
                                             _strings(g.get("presets", [""]), str(path), "presets")):
            name = "_".join(x for x in (_stem(o), v, m, pr) if x)
            batch.jobs.append(BatchJob(name, check(o, v, m, "[grid]"), v, m, pr))
    t = data.get("turntable")
    if t is not None:
        known = {"object", "view", "axis", "views", "material", "preset"}
        if not isinstance(t, dict) or set(t) - known:
            raise ConfigError(f"{path}: [turntable] takes {', '.join(sorted(known))}")
        n = t.get("views", 36)
        if not isinstance(n, int) or not 1 <= n <= 100000:
            raise ConfigError(f"{path}: [turntable] views must be an integer in [1, 100000], got {n!r}")
        axis = np.asarray(t.get("axis", [0.0, 1.0, 0.0]), np.float64).reshape(-1)
        if axis.shape != (3,) or not np.all(np.isfinite(axis)) or np.linalg.norm(axis) == 0:
            raise ConfigError(f"{path}: [turntable] axis must be three finite numbers, not all 0")
        axis = axis / np.linalg.norm(axis)
        obj = str(t.get("object", default_obj))
        v, m, pr = str(t.get("view", next(iter(views), "view1"))), str(t.get("material", "")), str(t.get("preset", ""))
        o = check(obj, v, m, "[turntable]")
        for k in range(n):
            batch.jobs.append(BatchJob(f"turntable_{_stem(obj)}_{k:04d}", o, v, m, pr,
                                  (*axis.tolist(), 2 * math.pi * k / n)))
    if not batch.jobs:
        raise ConfigError(f"{path}: no jobs (give a [grid] or a [turntable] table)")
    names = [j.name for j in batch.jobs]
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise ConfigError(f"{path}: two jobs are named {dup!r} (objects of the same file name?)")
    return batch


def material_options(scene: dict, name: str) -> dict[str, Any]:
    """relight options of a scene.json material (make-scene's ``materials`` table): ``lambert`` (albedo) →
    Lambert; ``ggx`` (roughness, Smith masking) → a white GGX metal (F = 1, Mitsuba's roughconductor)."""
    if not name:
        return {}
    m = scene["materials"][name]
    if m.get("type") == "lambert":
        a = np.broadcast_to(np.asarray(m.get("albedo", 0.8), np.float64), 3)
        return {"brdf": "lambert", "albedo": tuple(float(x) for x in a)}
    if m.get("type") == "ggx":
        return {"brdf": "ggx", "albedo": (1.0, 1.0, 1.0), "metallic": 1.0, "roughness": float(m["roughness"]),
                "masking": "separable" if "separable" in str(m.get("masking", "")) else "height-correlated"}
    raise InputError(None, f"material '{name}': type {m.get('type')!r} is not lambert or ggx")


def turntable_camera(view: dict, axis_angle: tuple[float, ...]) -> dict[str, Any]:
    """relight's eye/target/up of a scene.json view turned by ``angle`` [rad] about ``axis`` through its target
    (right-handed: counter-clockwise seen from the axis' tip); the view's field of view."""
    from scipy.spatial.transform import Rotation

    ax, ang = np.asarray(axis_angle[:3], np.float64), float(axis_angle[3])
    eye, target, up = (np.asarray(view[k], np.float64).reshape(3) for k in ("eye", "target", "up"))
    R = Rotation.from_rotvec(ax * ang)
    return {"eye": tuple(float(x) for x in target + R.apply(eye - target)), "target": tuple(float(x) for x in target),
            "up": tuple(float(x) for x in R.apply(up)), "fov": float(view.get("fov_deg", 45.0))}


def job_config(batch: Batch, job: BatchJob, scene: dict) -> Any:
    """The job's resolved relight options: the config's [relight] table, the job's preset, material and
    turntable camera, [batch] size, the seed."""
    from ..relight.relight import RelightConfig

    over: dict[str, Any] = {"seed": batch.seed, "preset": job.preset or None, **material_options(scene, job.material)}
    view = scene["views"][job.view]
    if job.turntable:
        over.update(turntable_camera(view, job.turntable))
        over["size"] = batch.size or "x".join(str(int(x)) for x in view.get("size", (512, 512)))
    elif batch.size:
        over["size"] = batch.size
    return resolve(RelightConfig, batch.config, "relight", over)


# --------------------------------------------------------------------------- tasks (run on workers)
@dataclass(frozen=True)
class Failure:
    """A task's error as a value (a pcrelight error's own exception may not survive pickling): its line, its
    exit status, its type."""

    message: str
    exit_code: int = 1
    kind: str = ""


@dataclass(frozen=True)
class Task:
    """What a worker needs to run one job (every path absolute)."""

    job: BatchJob
    cfg: Any                    # RelightConfig
    bsh: str
    scene: str
    out: str                    # the job's folder
    driver_pid: int             # the driver's process id: a worker refuses GL there
    driver_host: str


@dataclass(frozen=True)
class Prepare:
    """The shared part: ``pcrelight run CONFIG --to build-bsh``."""

    config: str
    seed: int | None
    driver_pid: int
    driver_host: str


_CTX: Any = None     # this worker process's GL context (made on its first job) and its own bound framebuffer
_FBO: Any = None


def worker_id() -> str:
    """``host:pid`` of this process."""
    return f"{socket.gethostname()}:{os.getpid()}"


def worker_context(driver_pid: int, driver_host: str) -> Any:
    """This worker's GL context, created on first use — never in the driver (RuntimeError there) — and made
    ready for the next job: its own framebuffer bound and the error flags cleared. (run_relight leaves the
    framebuffer it released as moderngl's bound one; the next object moderngl creates rebinds that deleted name:
    GL_INVALID_OPERATION, seen as "GL error while rasterising the G-buffer" on every second job.)"""
    global _CTX, _FBO
    if os.getpid() == driver_pid and socket.gethostname() == driver_host:
        raise RuntimeError("a GL context was asked for in the batch driver; GL belongs in the workers")
    from .. import gl

    if _CTX is None:
        if not os.environ.get("PCRELIGHT_EGL_DEVICE"):
            device = ray_gpu()
            if device is not None:   # one EGL device per worker: the GPU Ray gave this task
                os.environ["PCRELIGHT_EGL_DEVICE"] = str(device)
        _CTX = gl.create_context()
        _FBO = gl.bind_dummy_framebuffer(_CTX)
        log.info("worker %s: GL context %s", worker_id(), gl.context_info(_CTX)["renderer"])
    _FBO.use()
    for _ in range(16):            # glGetError returns one flag a call
        if _CTX.error == "GL_NO_ERROR":
            break
    return _CTX


def ray_gpu() -> int | None:
    """The first GPU Ray assigned to this worker (a task with ``num_gpus``), else None. Its id is taken as the
    EGL device index: NVIDIA's EGL enumerates its GPUs in the CUDA order (a node whose EGL also lists Mesa's
    software device lists it after them); set PCRELIGHT_EGL_DEVICE to override."""
    import sys

    if "ray" not in sys.modules:
        return None
    ray = sys.modules["ray"]
    try:
        ids = ray.get_gpu_ids() if ray.is_initialized() else []
    except Exception:  # noqa: BLE001 - not in a Ray worker
        return None
    return int(ids[0]) if ids else None


def node_local(path: str) -> str:
    """``path`` copied once a node into ``<tmp>/pcrelight-cache/`` (keyed by its path, size and mtime), so a job
    reads the BSH from the node's own disk and the shared file system serves it once a node, not once a job
    (bench/README.md "batch": that read is what stops a cluster scaling first)."""
    import hashlib
    import shutil
    import tempfile

    from .. import io

    src = Path(path)
    st = src.stat()
    key = hashlib.sha1(f"{src.resolve()}:{st.st_size}:{st.st_mtime_ns}".encode()).hexdigest()[:16]
    dst = Path(tempfile.gettempdir()) / "pcrelight-cache" / f"{src.stem}-{key}{src.suffix}"
    if not dst.exists():
        with io.atomic_path(dst) as tmp:
            shutil.copyfile(src, tmp)
        log.info("worker %s: %s copied to %s (%.1f MiB)", worker_id(), src, dst, st.st_size / 2 ** 20)
    return str(dst)


def _failure(e: BaseException) -> Failure:
    first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    if isinstance(e, PcrelightError):
        return Failure(first, e.exit_code, type(e).__name__)
    return Failure(f"internal error ({type(e).__name__}: {first})", 1, type(e).__name__)


def prepare_shared(p: Prepare) -> dict[str, Any] | Failure:
    """On a worker: the expansion and the BSH, once (``run_pipeline(config, to_stage="build-bsh")``: stages up
    to date are skipped). Returns the stages' report, or a :class:`Failure`."""
    from .runner import run_pipeline

    try:
        t0 = time.perf_counter()
        rep = run_pipeline(p.config, to_stage="build-bsh", seed=p.seed)
        ran = [v for v, e in rep["stages"].items() if not e.get("skipped")]
        return {"worker": worker_id(), "seconds": time.perf_counter() - t0, "ran": ran}
    except Exception as e:  # noqa: BLE001 - handed to the driver as a value
        return _failure(e)


def reference_error(relit_exr: Path, scene_path: Path, scene: dict, job: BatchJob) -> dict[str, Any]:
    """The job's error against the scene's path-traced reference ``truth/full_<view>_<material>.exr`` when
    there is one for it (the scene's own object, a scene view, a scene material, the reference's size), by
    :func:`pipeline.metrics.compare_to_reference` on 4×4 blocks (relit.exr ÷ the scene's exposure e: scene
    units); {} otherwise."""
    from .. import io
    from ..metrics import compare_to_reference

    refs = scene.get("references") or {}
    obj = scene.get("object") or {}
    ref = scene_path.parent / "truth" / f"full_{job.view}_{job.material}.exr"
    var = ref.with_name(ref.stem + "_var.exr")
    if (job.turntable or not job.material or job.material not in refs.get("materials", ())
            or Path(job.object) != (scene_path.parent / str(obj.get("file", ""))).resolve() or not ref.exists()):
        return {}
    img, r = io.read_image(relit_exr), io.read_image(ref)
    if img.shape[:2] != r.shape[:2]:
        return {}
    e = float(scene.get("exposure_e", 1.0))
    m = (img[..., 3] > 0.5) & (r[..., 3] > 0.5)
    if not m.any():
        return {}
    c = compare_to_reference(img[..., :3].astype(np.float64) / e, r[..., :3].astype(np.float64), m,
                             io.read_image(var)[..., :3].astype(np.float64) if var.exists() else None, block=4)
    return {"reference": str(ref), "ref_rms_block": c["rms_block"], "ref_mean_ratio": c["mean_ratio"]}


def job_spec(task: Task) -> dict[str, Any]:
    """What decides a job's outputs: the job, its resolved options, its BSH (compared on resume), as JSON
    gives it back."""
    return _plain({"job": dataclasses.asdict(task.job), "config": task.cfg.as_dict(), "bsh": task.bsh})


def _plain(o: Any) -> Any:
    """Tuples as lists, numbers as Python numbers: the form JSON gives back."""
    if isinstance(o, dict):
        return {str(k): _plain(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_plain(x) for x in o]
    if isinstance(o, np.generic):
        return o.item()
    return o


def relight_task(task: Task) -> dict[str, Any] | Failure:
    """On a worker: relight one job into its folder (:func:`pipeline.relight.relight.run_relight` with this worker's
    GL context), compare it with its reference, write done.json last. Returns done.json's content, or a
    :class:`Failure`."""
    from .. import io
    from ..relight.relight import run_relight

    out = Path(task.out)
    try:
        t0 = time.perf_counter()
        io.write_json(out / RUNNING, {"worker": worker_id(), "job": task.job.name})
        ctx = worker_context(task.driver_pid, task.driver_host)
        stats = run_relight(node_local(task.bsh), out, task.cfg, object_path=task.job.object, scene_path=task.scene,
                            view=task.job.view, ctx=ctx)
        scene = io.read_json(task.scene)
        err = reference_error(out / "relit.exr", Path(task.scene), scene, task.job)
        done = {"job": task.job.name, "spec": job_spec(task), "worker": worker_id(),
                "seconds": round(time.perf_counter() - t0, 3), "relight_s": round(float(stats["total_s"]), 3),
                "bytes_out": sum((out / f).stat().st_size for f in OUTPUTS), **err}
        io.write_json(out / DONE, done)
        (out / RUNNING).unlink(missing_ok=True)
        return done
    except Exception as e:  # noqa: BLE001 - handed to the driver as a value
        return _failure(e)


# --------------------------------------------------------------------------- the driver
def is_done(task: Task) -> dict[str, Any] | None:
    """done.json of a job whose outputs are complete, made with the same job and options, and newer than its
    inputs (the BSH, scene.json, the object); None when the job must run."""
    from .. import io
    from .runner import up_to_date

    out = Path(task.out)
    done = out / DONE
    if not done.exists() or not all((out / f).exists() for f in OUTPUTS):
        return None
    if not up_to_date([Path(task.bsh), Path(task.scene), Path(task.job.object)], [done, *(out / f for f in OUTPUTS)]):
        return None
    try:
        rec = io.read_json(done)
    except InputError:
        return None
    return rec if isinstance(rec, dict) and rec.get("spec") == job_spec(task) else None


def _bar(total: int) -> Any:
    """A tqdm bar across jobs on a terminal, its postfix the jobs done by each worker (pid:count); None elsewhere
    (not a terminal, CI, -q): a log line per job instead."""
    if not progress_enabled():
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc="batch", unit="job", dynamic_ncols=True, leave=True)


def run_batch(jobs_toml: str | os.PathLike, executor: str = "local", workers: int | None = None,
              address: str | None = None, force: bool = False, seed: int | None = None,
              verbosity: int = -1, gpus_per_job: float = 0.0) -> dict[str, Any]:
    """Run a JOBS.toml on an executor (module docstring): the shared expansion + BSH once, then every job not
    already done; writes ``<out>/summary.csv`` (job, status, seconds, worker, attempts, error against the
    reference when known, error message), ``<out>/contact_sheet.png`` and ``<out>/batch.json``. ``verbosity``:
    the workers' logging. Raises :class:`PcrelightError` when a job failed (after writing the summary)."""
    from .. import io
    from .stages import RunConfig, workspace_of

    t_start = time.perf_counter()
    batch = read_batch(jobs_toml, seed)
    ws = workspace_of(resolve(RunConfig, batch.config, "run", {}))
    scene = io.read_json(ws.scene)
    cfgs = {j.name: job_config(batch, j, scene) for j in batch.jobs}   # bad options: refused before anything runs
    me, host = os.getpid(), socket.gethostname()
    tasks = [Task(j, cfgs[j.name], str(ws.bsh.resolve()), str(ws.scene.resolve()), str(batch.out / j.name), me, host)
             for j in batch.jobs]
    log.info("read %s: %d job(s), pipeline config %s, outputs in %s", batch.jobs_toml, len(tasks), batch.config, batch.out)
    rows: dict[str, dict[str, Any]] = {}
    report: dict[str, Any] = {"jobs_toml": str(batch.jobs_toml), "config": str(batch.config), "executor": executor,
                              "out": str(batch.out)}
    with make_executor(executor, workers, address, verbosity, gpus_per_job, batch.retries) as ex:
        report["executor_line"] = ex.describe()
        report["workers"] = ex.workers
        log.info("executor %s", ex.describe())
        t0 = time.perf_counter()
        [(_, prep)] = list(ex.map(prepare_shared, [Prepare(str(batch.config), batch.seed, me, host)]))
        if isinstance(prep, (Failure, BaseException)):
            msg = prep.message if isinstance(prep, Failure) else str(prep)
            raise PcrelightError(f"{batch.config}: the shared expansion and BSH failed: {msg}")
        log.info("shared expansion and BSH: %s on %s in %.1f s (%s)", ws.bsh, prep["worker"], time.perf_counter() - t0,
                 "ran " + ", ".join(prep["ran"]) if prep["ran"] else "every stage up to date")
        report["shared"] = {"bsh": str(ws.bsh), "seconds": round(time.perf_counter() - t0, 3), **prep,
                            "report_html": str(ws.report) if ws.report.exists() else None}  # run's page of the shared part
        todo = []
        for t in tasks:
            done = None if force else is_done(t)
            if done is not None:
                rows[t.job.name] = {**done, "status": "skipped", "attempts": 0}
            else:
                todo.append(t)
        if rows:
            log.info("%d job(s) done already (outputs newer than their inputs, same options): skipped", len(rows))
        bar = _bar(len(tasks))
        if bar is not None:
            bar.update(len(rows))
        per_worker: dict[str, int] = {}
        attempts = {t.job.name: 0 for t in todo}
        t_jobs = time.perf_counter()
        try:
            for _round in range(1 if ex.reruns_lost else batch.retries + 1):   # one policy: the executor's
                if not todo:
                    break
                for t in todo:
                    attempts[t.job.name] += 1
                lost = []
                for i, outcome in ex.map(relight_task, todo):
                    check_interrupt()
                    t = todo[i]
                    name = t.job.name
                    if isinstance(outcome, WorkerLost):
                        lost.append(t)
                        log.warning("%s: %s; it runs again", name, outcome)
                        continue
                    if isinstance(outcome, (Failure, BaseException)):
                        msg = outcome.message if isinstance(outcome, Failure) else f"{type(outcome).__name__}: {outcome}"
                        rows[name] = {"job": name, "status": "failed", "error": msg, "attempts": attempts[name]}
                        log.warning("%s: failed: %s", name, msg)
                    else:
                        rows[name] = {**outcome, "status": "ran", "attempts": attempts[name]}
                        per_worker[outcome["worker"]] = per_worker.get(outcome["worker"], 0) + 1
                        if bar is None:
                            log.info("%s: %.1f s on %s (%d of %d)", name, outcome["seconds"], outcome["worker"],
                                     len(rows), len(tasks))
                    if bar is not None:
                        bar.set_postfix_str(" ".join(f"{w.rsplit(':', 1)[-1]}:{n}" for w, n in sorted(per_worker.items())))
                        bar.update(1)
                todo = lost
            for t in todo:   # lost more often than retries allow
                rows[t.job.name] = {"job": t.job.name, "status": "failed", "attempts": attempts[t.job.name],
                                    "error": f"its worker died {attempts[t.job.name]} times"}
        finally:
            if bar is not None:
                bar.close()
            wall = time.perf_counter() - t_jobs
            ran = sum(1 for r in rows.values() if r["status"] == "ran")
            report.update(jobs=len(tasks), ran=ran, skipped=sum(1 for r in rows.values() if r["status"] == "skipped"),
                          failed=sum(1 for r in rows.values() if r["status"] == "failed"),
                          jobs_seconds=round(wall, 3), jobs_per_hour=round(3600 * ran / wall, 1) if ran and wall > 0 else None,
                          per_worker=per_worker, total_seconds=round(time.perf_counter() - t_start, 3))
            write_summary(batch.out / "summary.csv", [rows[t.job.name] for t in tasks if t.job.name in rows])
            io.write_json(batch.out / "batch.json", report)
    sheet = contact_sheet(batch.out / "contact_sheet.png", [batch.out / t.job.name for t in tasks
                                                            if rows.get(t.job.name, {}).get("status") in ("ran", "skipped")])
    report["contact_sheet"] = str(sheet) if sheet else None
    io.write_json(batch.out / "batch.json", report)
    log.info("batch: %d ran, %d skipped, %d failed in %.1f s (%s jobs/hour on %d worker(s)); %s, %s", report["ran"],
             report["skipped"], report["failed"], report["total_seconds"], report["jobs_per_hour"], report["workers"],
             batch.out / "summary.csv", sheet)
    if report["failed"]:
        raise PcrelightError(f"{batch.out / 'summary.csv'}: {report['failed']} of {len(tasks)} job(s) failed")
    return report


SUMMARY_COLUMNS = ("job", "status", "seconds", "worker", "attempts", "relight_s", "bytes_out", "ref_rms_block",
                   "ref_mean_ratio", "reference", "error")


def write_summary(path: Path, rows: list[dict[str, Any]]) -> None:
    """summary.csv: one row a job (:data:`SUMMARY_COLUMNS`; empty where unknown), atomically."""
    from .. import io

    with io.atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=SUMMARY_COLUMNS, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)


def contact_sheet(path: Path, folders: list[Path]) -> Path | None:
    """A PNG grid of the jobs' relit.png, each titled by its job (at most :data:`SHEET_MAX`, evenly spaced);
    None when there is nothing to show."""
    from .. import io

    if not folders:
        return None
    if len(folders) > SHEET_MAX:
        folders = [folders[int(i)] for i in np.linspace(0, len(folders) - 1, SHEET_MAX).round()]
        log.info("contact sheet: %d of the jobs, evenly spaced", SHEET_MAX)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = math.ceil(math.sqrt(len(folders)))
    rows = math.ceil(len(folders) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(1.6 * cols, 1.75 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, f in zip(axes.ravel(), folders):
        ax.imshow(np.clip(io.read_image(f / "relit.png")[..., :3], 0, 1), interpolation="nearest")
        ax.set_title(f.name, fontsize=5)
    fig.tight_layout(pad=0.3)
    io.save_figure(path, fig, dpi=120)
    return path
