"""``pcrelight batch`` throughput and fault trials: a turntable of the shipped object (data_samples/, the demo's
expansion and BSH from configs/demo.toml) relit with 1 and 2 Ray workers and with the local executor.

    python -m bench.batch.bench_batch [--views 36] [--size 96x96] [--out bench/batch/batch.csv]

Runs, each a whole ``pcrelight batch`` process (Ray started and stopped by it), outputs under
bench/_work/batch/:
  ray-1, ray-2     every job (--force) with 1 and 2 workers: jobs/hour over the jobs phase
  local-2          the local executor, 2 workers: relit.exr must be byte-identical to ray-1's, job by job
  ray-2-kill       --force with 2 workers; one worker SIGKILLed in the middle of a job (the pid its running.json
                   names): every job must finish, byte-identical to ray-1
  resume           the same again without --force: every job skipped
  driver-kill      the driver SIGTERMed after a third of the jobs, then rerun: the rerun runs only what was not done
Per run: wall seconds of the process, jobs run/skipped, jobs/hour, mean seconds a job on its worker, bytes a job
writes, the BSH's bytes (what a worker reads once), identical (relit.exr bytes against ray-1).
The 100-node estimate built from these rows is in bench/README.md ("batch").
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]
WORK = ROOT / "bench" / "_work" / "batch"


def jobs_toml(out: Path, views: int, size: str) -> Path:
    """A JOBS.toml: the demo config's expansion and BSH, a ``views``-view turntable of the shipped object."""
    p = WORK / f"{out.name}.toml"
    p.write_text(f'[batch]\nconfig = "{ROOT / "configs" / "demo.toml"}"\nout = "{out}"\nsize = "{size}"\n'
                 f'[turntable]\nobject = "{ROOT / "data_samples" / "object.glb"}"\nview = "view1"\n'
                 f'axis = [0.0, 1.0, 0.0]\nviews = {views}\n')
    return p


def batch(toml: Path, executor: str, workers: int, *extra: str, kill_worker_after: float | None = None,
          term_driver_after_jobs: int | None = None) -> tuple[float, int, bool]:
    """Run ``pcrelight batch`` as a process from the repository root; optionally SIGKILL a worker in the middle of
    a job once ``kill_worker_after`` s have passed, or SIGTERM the driver once that many jobs are done.
    Returns (wall seconds, exit status, whether a kill was delivered)."""
    out = Path(next(line.split('"')[1] for line in toml.read_text().splitlines() if line.startswith("out")))
    cmd = [sys.executable, str(ROOT / "cli.py"), "batch", str(toml), "--executor", executor, "--workers", str(workers), *extra]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, stderr=subprocess.PIPE, text=True)
    killed = False
    while proc.poll() is None:
        time.sleep(0.2)
        if killed:
            continue
        if kill_worker_after is not None and time.perf_counter() - t0 > kill_worker_after:
            running = sorted(out.glob("*/running.json"))
            if running:
                pid = int(json.loads(running[0].read_text())["worker"].rsplit(":", 1)[1])
                os.kill(pid, signal.SIGKILL)
                print(f"  killed worker {pid} running {running[0].parent.name}")
                killed = True
        if term_driver_after_jobs is not None and len(list(out.glob("*/done.json"))) >= term_driver_after_jobs:
            proc.send_signal(signal.SIGTERM)
            print(f"  SIGTERM to the driver after {term_driver_after_jobs} jobs")
            killed = True
    err = proc.stderr.read() if proc.stderr else ""
    wall = time.perf_counter() - t0
    if proc.returncode not in (0,) and not (term_driver_after_jobs is not None and killed):
        print(err[-3000:])
    return wall, proc.returncode, killed


def hashes(out: Path) -> dict[str, str]:
    return {p.parent.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(out.glob("*/relit.exr"))}


def row(name: str, executor: str, workers: int, out: Path, wall: float, rc: int, ref: dict[str, str] | None,
        note: str = "") -> dict:
    rep = json.loads((out / "batch.json").read_text())
    with open(out / "summary.csv") as f:
        rows = list(csv.DictReader(f))
    ran = [r for r in rows if r["status"] == "ran"]
    h = hashes(out)
    return {"run": name, "executor": executor, "workers": workers, "jobs": rep["jobs"], "ran": rep["ran"],
            "skipped": rep["skipped"], "failed": rep["failed"], "exit": rc, "process_s": round(wall, 1),
            "jobs_phase_s": rep["jobs_seconds"], "jobs_per_hour": rep["jobs_per_hour"],
            "mean_job_s": round(sum(float(r["seconds"]) for r in ran) / len(ran), 2) if ran else "",
            "bytes_per_job": round(sum(int(r["bytes_out"]) for r in rows if r["bytes_out"]) / max(1, len(rows))),
            "bsh_bytes": (ROOT / rep["shared"]["bsh"]).stat().st_size,
            "identical": "" if ref is None else (h == ref), "retried": sum(1 for r in rows if r["attempts"] not in ("0", "1")),
            "note": note}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, default=36)
    ap.add_argument("--size", default="96x96")
    ap.add_argument("--out", type=Path, default=HERE / "batch.csv")
    ap.add_argument("--runs", default="ray-1,ray-2,local-2,ray-2-kill,resume,driver-kill")
    a = ap.parse_args()
    WORK.mkdir(parents=True, exist_ok=True)
    runs = a.runs.split(",")
    rows, ref = [], None
    os.chdir(ROOT)
    if "ray-1" not in runs and (WORK / "ray-1").exists():   # a partial rerun: ray-1's outputs are the reference
        ref = hashes(WORK / "ray-1")
    for name in runs:
        ex, w = ("local", 2) if name.startswith("local") else ("ray", 1 if name == "ray-1" else 2)
        out = WORK / ("ray-2-kill" if name == "resume" else name)
        toml = jobs_toml(out, a.views, a.size)
        print(f"+ {name}: {a.views} jobs, {a.size}, {ex} × {w}")
        note = ""
        if name == "ray-2-kill":
            wall, rc, k = batch(toml, ex, w, "--force", kill_worker_after=30.0)
            note = "one worker SIGKILLed mid-job" if k else "no kill delivered"
        elif name == "resume":
            wall, rc, _ = batch(toml, ex, w)
            note = "rerun of ray-2-kill without --force"
        elif name == "driver-kill":
            shutil.rmtree(out, ignore_errors=True)   # (the SIGTERM is sent on a count of done.json files)
            wall0, rc0, k = batch(toml, ex, w, "--force", term_driver_after_jobs=max(1, a.views // 3))
            done0 = len(list(out.glob("*/done.json")))
            wall, rc, _ = batch(toml, ex, w)
            note = f"driver SIGTERMed (exit {rc0}) after {done0} jobs done in {wall0:.0f} s; this row: the rerun"
        else:
            wall, rc, _ = batch(toml, ex, w, "--force")
        r = row(name, ex, w, out, wall, rc, ref, note)
        if name == "ray-1":
            ref = hashes(out)
            r["identical"] = ""
        print("  ", r)
        rows.append(r)
    if a.out.exists():   # a partial rerun (--runs): the other runs' rows stay, in their order
        with open(a.out) as f:
            old = list(csv.DictReader(f))
        new = {r["run"]: r for r in rows}
        rows = [new.pop(r["run"], r) for r in old] + list(new.values())
    with open(a.out, "w", newline="") as f:
        wr = csv.DictWriter(f, fieldnames=list(rows[0]))
        wr.writeheader()
        wr.writerows(rows)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
