"""pcrelight batch (pipeline/run/batch.py, pipeline/run/executor.py, pipeline/run/executor_ray.py) on a tiny scene: the
shipped scene.json and object, a 20k-point LDR cloud with nothing overexposed (the plan skips the expansion:
the shared part is build-bsh alone), 4 jobs of 32² (2 views + a 2-view turntable), micro-buffer 8.

Local Ray: ``ray.init(num_cpus=2, include_dashboard=False)`` for the module, shut down after. Checked: Ray's
results are byte-identical to the local executor's; the driver never makes a GL context; a worker SIGKILLed
in the middle of a job loses nothing (the job reruns, every output as in the clean run); a rerun skips the
jobs that are done and runs only what is not."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from pipeline.run import batch as B
from pipeline import io

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "data_samples"
JOBS = ("object_view1_lambert", "object_view2_lambert", "turntable_object_0000", "turntable_object_0001")


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """The inputs folder, the pipeline config (pipe.toml) and a JOBS.toml writer in one folder."""
    d = tmp_path_factory.mktemp("batch")
    (d / "in").mkdir()
    for f in ("scene.json", "object.glb"):
        shutil.copy(SAMPLES / f, d / "in" / f)
    c = io.read_cloud(SAMPLES / "cloud_ldr.ply")
    c = c.subset(np.sort(np.random.default_rng(0).choice(len(c), 20000, replace=False)))
    c.colors = np.minimum(c.colors, 0.85).astype(np.float32)      # nothing overexposed: no expansion
    io.write_cloud(d / "in" / "cloud_ldr.ply", c)
    (d / "pipe.toml").write_text(f'seed = 0\n[run]\ninputs = "{d / "in"}"\nworkspace = "{d / "ws"}"\n'
                                 'previews = false\n[relight]\nmicrobuffer = 8\n')
    return d


def jobs_toml(d: Path, out: str) -> Path:
    p = d / f"{out}.toml"
    p.write_text(f'[batch]\nconfig = "{d / "pipe.toml"}"\nout = "{d / out}"\nsize = "32x32"\n'
                 '[grid]\nviews = ["view1", "view2"]\nmaterials = ["lambert"]\n'
                 '[turntable]\nview = "view1"\naxis = [0, 1, 0]\nviews = 2\n')
    return p


def outputs(folder: Path) -> dict[str, bytes]:
    return {f"{j}/{n}": (folder / j / n).read_bytes() for j in JOBS for n in ("relit.exr", "relit.png")}


def summary(folder: Path) -> dict[str, dict]:
    with open(folder / "summary.csv") as f:
        return {r["job"]: r for r in csv.DictReader(f)}


def without_driver_gl(toml: Path, executor: str) -> dict:
    """run_batch with 2 workers while this process (the driver) cannot create a GL context."""
    from pipeline import gl

    def no_gl(*a, **k):
        raise AssertionError("the batch driver created a GL context")

    mp = pytest.MonkeyPatch()
    mp.setattr(gl, "create_context", no_gl)
    try:
        return B.run_batch(toml, executor, workers=2)
    finally:
        mp.undo()


@pytest.fixture(scope="module")
def local_run(scene):
    """The reference: every job on the local executor (2 spawned workers); the driver's GL is forbidden."""
    return scene / "local", without_driver_gl(jobs_toml(scene, "local"), "local")


@pytest.fixture(scope="module")
def ray_cluster():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, configure_logging=False, log_to_driver=False)
    yield ray
    ray.shutdown()


def test_local_batch_runs_every_job_once_and_writes_its_summary(local_run, scene):
    out, rep = local_run
    assert rep["ran"] == 4 and rep["failed"] == 0 and rep["shared"]["ran"] == ["build-bsh"]
    rows = summary(out)
    assert sorted(rows) == sorted(JOBS)
    assert all(r["status"] == "ran" and float(r["seconds"]) > 0 and r["worker"] for r in rows.values())
    assert (out / "contact_sheet.png").stat().st_size > 0
    img = io.read_image(out / JOBS[0] / "relit.exr")
    assert img.shape == (32, 32, 4) and img[..., 3].sum() > 20 and np.isfinite(img).all()
    # the turntable's second view (π about +Y through view1's target) sees the object from the other side
    t0, t1 = (io.read_json(out / j / "stats.json")["camera"] for j in JOBS[2:])
    scn = io.read_json(scene / "in" / "scene.json")["views"]["view1"]
    e0, e1, c = np.asarray(t0["eye"]), np.asarray(t1["eye"]), np.asarray(scn["target"])
    assert np.allclose(e0, scn["eye"]) and np.allclose((e0 + e1)[[0, 2]], 2 * c[[0, 2]]) and np.isclose(e0[1], e1[1])


def test_ray_gives_the_local_executors_bytes(local_run, scene, ray_cluster):
    rep = without_driver_gl(jobs_toml(scene, "ray"), "ray")
    assert rep["ran"] == 4 and rep["shared"]["ran"] == []          # the BSH is built once: up to date here
    assert ray_cluster.is_initialized()                              # a Ray given is left running
    assert outputs(scene / "ray") == outputs(local_run[0])
    assert all(r["worker"].rsplit(":", 1)[1] != str(os.getpid()) for r in summary(scene / "ray").values())


def _kill_first_running(out: Path, killed: list[int], stop: threading.Event) -> None:
    """SIGKILL the worker of the first job that says it is running (once)."""
    while not stop.is_set() and not killed:
        for r in out.glob("*/running.json"):
            try:
                pid = int(json.loads(r.read_text())["worker"].rsplit(":", 1)[1])
            except (OSError, ValueError, KeyError):
                continue
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)
            killed.append(r.parent.name)
            return
        time.sleep(0.05)


@pytest.mark.parametrize("executor", ["ray", "local"])
def test_a_worker_killed_mid_job_loses_nothing(local_run, scene, executor, request):
    if executor == "ray":
        request.getfixturevalue("ray_cluster")
    out = scene / f"kill_{executor}"
    killed: list = []
    stop = threading.Event()
    th = threading.Thread(target=_kill_first_running, args=(out, killed, stop), daemon=True)
    th.start()
    try:
        rep = B.run_batch(jobs_toml(scene, f"kill_{executor}"), executor, workers=2)
    finally:
        stop.set()
        th.join()
    assert killed, "no job was seen running"
    pid, job = killed
    assert rep["ran"] == 4 and rep["failed"] == 0
    assert outputs(out) == outputs(local_run[0])                    # every job, as in the clean run
    done = io.read_json(out / job / "done.json")
    assert done["worker"].rsplit(":", 1)[1] != str(pid)              # the killed job ran again elsewhere
    assert not list(out.glob("*/running.json")) and not list(out.glob("*/.*tmp*"))


def test_a_stopped_driver_says_so_and_the_rerun_finishes(local_run, scene, ray_cluster):
    """`pcrelight batch --executor ray --address` (joining the test's Ray) SIGTERMed once a job is done: one line,
    exit 143 (ray.init's own SIGTERM handler, which aborted the driver, is replaced by pcrelight's); the rerun
    runs only the jobs not done, and every output is as in the clean run."""
    import subprocess
    import sys

    out = scene / "term"
    toml = jobs_toml(scene, "term")
    addr = ray_cluster.get_runtime_context().gcs_address
    proc = subprocess.Popen([sys.executable, str(ROOT / "cli.py"), "batch", str(toml), "--executor", "ray",
                             "--address", addr, "--workers", "1"], stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    while proc.poll() is None and not list(out.glob("*/done.json")) and time.monotonic() - t0 < 120:
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    err = proc.communicate(timeout=60)[1]
    done = len(list(out.glob("*/done.json")))
    assert proc.returncode == 143, err[-2000:]
    assert err.strip().splitlines()[-1] == "pcrelight: interrupted by signal 15; outputs left as they were"
    assert 1 <= done < 4 and not list(out.glob("*/.*tmp*"))
    rep = B.run_batch(toml, "ray", workers=2)
    assert rep["skipped"] == done and rep["ran"] == 4 - done
    assert outputs(out) == outputs(local_run[0])


def test_a_rerun_skips_done_jobs_and_runs_the_rest(local_run, scene):
    out = scene / "local"
    before = {j: (out / j / "relit.exr").stat().st_mtime_ns for j in JOBS}
    rep = B.run_batch(jobs_toml(scene, "local"), "local", workers=1)
    assert rep["skipped"] == 4 and rep["ran"] == 0
    assert {j: (out / j / "relit.exr").stat().st_mtime_ns for j in JOBS} == before
    assert {r["status"] for r in summary(out).values()} == {"skipped"}
    # a job killed before its done.json, and one whose options changed: only those run again
    (out / JOBS[1] / "done.json").unlink()
    rec = io.read_json(out / JOBS[3] / "done.json")
    rec["spec"]["config"]["microbuffer"] = 16
    io.write_json(out / JOBS[3] / "done.json", rec)
    ref = outputs(out)
    rep = B.run_batch(jobs_toml(scene, "local"), "local", workers=1)
    assert rep["ran"] == 2 and rep["skipped"] == 2
    assert {j for j, r in summary(out).items() if r["status"] == "ran"} == {JOBS[1], JOBS[3]}
    assert outputs(out) == ref


def test_reference_error_is_measured_against_the_scenes_path_trace(tmp_path):
    """A relit.exr equal to e × truth/full_view1_lambert.exr (the reference in LDR units) has 0 error."""
    scene_path = SAMPLES / "scene.json"
    scene = io.read_json(scene_path)
    ref = io.read_image(SAMPLES / "truth" / "full_view1_lambert.exr")
    io.write_image(tmp_path / "relit.exr", np.concatenate([ref[..., :3] * scene["exposure_e"], ref[..., 3:4]], -1))
    job = B.BatchJob("j", str((SAMPLES / "object.glb").resolve()), "view1", "lambert")
    err = B.reference_error(tmp_path / "relit.exr", scene_path, scene, job)
    assert err["ref_rms_block"] < 1e-6 and abs(err["ref_mean_ratio"] - 1) < 1e-6
    assert B.reference_error(tmp_path / "relit.exr", scene_path, scene, B.BatchJob("j", job.object, "view1", "")) == {}


def test_bad_jobs_are_one_line_and_nothing_runs(scene, cli_run):
    bad = scene / "bad.toml"
    bad.write_text(f'[batch]\nconfig = "{scene / "pipe.toml"}"\nout = "{scene / "bad"}"\n[grid]\nviews = ["view9"]\n')
    code, _, err = cli_run("batch", bad)
    assert code == 2 and "no view 'view9'" in err and len(err.strip().splitlines()) == 1
    bad.write_text(f'[batch]\nconfig = "{scene / "pipe.toml"}"\n[grid]\nobjects = ["{scene / "nope.glb"}"]\n')
    code, _, err = cli_run("batch", bad)
    assert code == 1 and "nope.glb: no such object file" in err
    bad.write_text(f'[batch]\nconfig = "{scene / "pipe.toml"}"\n[turntable]\nviews = 0\n')
    code, _, err = cli_run("batch", bad)
    assert code == 2 and "views must be an integer" in err
    code, _, err = cli_run("batch", jobs_toml(scene, "x"), "--executor", "dask")
    assert code == 2 and "--executor" in err
    assert not (scene / "bad").exists() and not (scene / "x").exists()
