"""The expansion at the paper's scale (issue 23 item 5): make-scene's ``full`` preset (3 M points) through
expose-match → render-cubemaps → patchmatch → reproject → poisson → build-bsh, each stage a fresh
``pcrelight <verb>`` process as a user runs it, timed against the paper's Table 1 (SPONZA, 3.0 M points:
HDR expansion 180.5 s, BSH 13.82 s).

    .venv/bin/python -m bench.expansion.bench_expansion_full INPUTS [--work DIR] [--out bench/expansion/expansion_full.csv]
        [--size 1024] [--max-views 6] [--photo-fov 70] [--to build-bsh]

INPUTS holds ``photo.exr`` and ``cloud_ldr.ply`` (``pcrelight make-scene --preset full --out INPUTS
--cloud-target 0 --photos bright --no-references`` writes them without the ground-truth references, which
take hours at this size). Per stage: wall seconds, CPU seconds (user + sys of the process and its threads),
peak resident memory (the process's ``ru_maxrss`` from ``os.wait4``) and the 1-minute load average when it
ended; one CSV row each, plus the expansion total (expose-match … poisson) and Table 1's figures. Stage
options: each verb's defaults (cube faces 1024², ≤ 6 automatic views, PatchMatch 5 iterations / patch 7 /
3 levels), expose-match ``--photo-fov`` as make-scene's photo (70°). The machine is shared: compare rows of
one run, and read the CPU column beside the wall one.
"""

from __future__ import annotations

import argparse
import csv
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]
PAPER = {"expansion": 180.5, "build-bsh": 13.82}   # Table 1, SPONZA (3.0 M points, 3 shots) [s]


def stages(inputs: Path, work: Path, a: argparse.Namespace) -> list[tuple[str, list[str]]]:
    """(verb, arguments) of each stage, in order."""
    photo, ldr = inputs / "photo.exr", inputs / "cloud_ldr.ply"
    return [
        ("expose-match", [str(photo), str(ldr), "--photo-fov", str(a.photo_fov), "--out", str(work / "exposure.npz"),
                          "--photo-ldr", str(work / "photo_ldr.exr")]),
        ("render-cubemaps", [str(ldr), "--size", str(a.size), "--max-views", str(a.max_views),
                             "--out", str(work / "cubemaps")]),
        ("patchmatch", [str(work / "cubemaps"), "--photo", str(photo), "--exposure", str(work / "exposure.npz"),
                        "--photo-ldr", str(work / "photo_ldr.exr"), "--out", str(work / "hdr_faces")]),
        ("reproject", [str(ldr), str(work / "cubemaps"), str(work / "hdr_faces"), "--out", str(work / "cloud_proj.ply")]),
        ("poisson", [str(work / "cloud_proj.ply"), "--ldr", str(ldr), "--out", str(work / "cloud_hdr.ply")]),
        ("build-bsh", [str(work / "cloud_hdr.ply"), "--out", str(work / "bsh.npz")]),
    ]


def run_stage(verb: str, args: list[str], log: Path) -> dict:
    """One ``pcrelight verb args`` process: wall, CPU and peak RSS (``os.wait4``'s rusage of that child)."""
    cmd = [sys.executable, "-c", "import sys; sys.argv[0] = 'pcrelight'; from cli import main; sys.exit(main())",
           verb, *args]
    with open(log, "w") as f:
        t0 = time.perf_counter()
        p = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, cwd=ROOT,
                             env=dict(os.environ, PYTHONPATH=str(ROOT)))
        _, status, ru = os.wait4(p.pid, 0)
        wall = time.perf_counter() - t0
    p.returncode = os.waitstatus_to_exitcode(status)
    return {"stage": verb, "rc": p.returncode, "wall_s": round(wall, 3), "cpu_s": round(ru.ru_utime + ru.ru_stime, 3),
            "peak_rss_mb": round(ru.ru_maxrss / 1024.0, 1), "load1": round(os.getloadavg()[0], 2), "log": str(log)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("inputs", type=Path)
    ap.add_argument("--work", type=Path, default=ROOT / "bench" / "_work" / "expansion_full")
    ap.add_argument("--out", type=Path, default=HERE / "expansion_full.csv")
    ap.add_argument("--size", type=int, default=1024, help="cube-face size [pixels] (the verb's default, the paper's)")
    ap.add_argument("--max-views", type=int, default=6)
    ap.add_argument("--photo-fov", type=float, default=70.0)
    ap.add_argument("--from", dest="start", default="expose-match", help="first stage (earlier outputs reused)")
    ap.add_argument("--to", default="build-bsh", help="last stage")
    ap.add_argument("--label", default="", help="a label for the rows (commit, machine state)")
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    todo = stages(a.inputs, a.work, a)
    verbs = [v for v, _ in todo]
    todo = todo[verbs.index(a.start): verbs.index(a.to) + 1]
    sys.path.insert(0, str(ROOT))
    from pipeline.io import read_cloud

    n_points = len(read_cloud(a.inputs / "cloud_ldr.ply").points)
    rows = []
    for verb, args in todo:
        r = run_stage(verb, args, a.work / f"{verb}.log")
        r.update(label=a.label, n_points=n_points, size=a.size)
        rows.append(r)
        print(f"{verb:16s} {r['wall_s']:9.1f} s wall {r['cpu_s']:9.1f} s CPU  peak {r['peak_rss_mb']:8.0f} MB  "
              f"load {r['load1']:.1f}  rc {r['rc']}", flush=True)
        if r["rc"] != 0:
            print(f"{verb} failed: see {r['log']}", file=sys.stderr)
            break
    exp = [r for r in rows if r["stage"] not in ("build-bsh",)]
    if len(exp) == 5 and all(r["rc"] == 0 for r in exp):      # the whole expansion ran in this invocation
        rows.append({"stage": "expansion total", "rc": 0, "wall_s": round(sum(r["wall_s"] for r in exp), 3),
                     "cpu_s": round(sum(r["cpu_s"] for r in exp), 3),
                     "peak_rss_mb": max(r["peak_rss_mb"] for r in exp), "load1": round(os.getloadavg()[0], 2),
                     "log": "", "label": a.label, "n_points": n_points, "size": a.size})
    for r in rows:
        r["paper_s"] = PAPER["expansion"] if r["stage"] == "expansion total" else PAPER.get(r["stage"], "")
    keys = ["label", "n_points", "size", "stage", "rc", "wall_s", "cpu_s", "peak_rss_mb", "paper_s", "load1", "log"]
    new = not a.out.exists()
    with open(a.out, "a", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        if new:
            w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k, "") for k in keys})
    print(f"appended {len(rows)} rows to {a.out}")


if __name__ == "__main__":
    main()
