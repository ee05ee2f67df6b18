"""build-bsh and relight at the paper's scale (issue 46): the same synthetic room at N = 200 k, 3 M, 10 M … points,
each stage a fresh ``pcrelight`` process as a user runs it: wall and CPU seconds, peak resident memory.

    .venv/bin/python -m bench.relight.bench_cloud_scale [--ns 200000,3000000] [--size 512x512]
        [--work bench/_work/cloud_scale] [--out bench/relight/cloud_scale.csv]

A cloud whose build would not fit in the free memory is refused by build-bsh in one line (its ``message`` column).

Cloud: ``bench.bsh.bench_bsh.surface_cloud`` (an 8 × 4 × 6 m room and three spheres, sampled by area, a textured
colour: noise 0.1), written as a binary float32 PLY. Object: the shipped knot (data_samples/object.glb) at the
room's middle, 1.9 m across, Lambert 0.8, relight's defaults (classic, m 24, bounces auto, adaptive 0.3), one
camera. Per row: the stage, N, wall and CPU (user + sys) seconds, peak RSS (``os.wait4``), the load; for relight
also its walk's node visits; and build-bsh's memory model (``pipeline.bsh.build_bsh.memory_needed``) beside the
measured peak, so the refusal rule's margin is on record. The numba cache is the install's (``make setup`` warmed it):
the times are a user's second run. The machine is shared: read the CPU column beside the wall one.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from bench.benchlib import ROOT, write_rows
from bench.bsh.bench_bsh import surface_cloud
from bench.expansion.bench_expansion_full import run_stage


RELIGHT_STEPS = ("read", "room_shadow", "surfels", "walk", "gather", "gatherer", "upload")


def scene_json(folder: Path) -> Path:
    """data_samples/scene.json with the knot at the synthetic room's middle and view1 looking at it from a corner."""
    sc = json.loads((ROOT / "data_samples" / "scene.json").read_text())
    s = 0.95
    sc["object"]["to_world"] = [[s, 0, 0, 4.0], [0, s, 0, 1.6], [0, 0, s, 3.0], [0, 0, 0, 1]]
    sc.pop("object2", None)
    sc["views"] = {"view1": {"eye": [1.2, 2.6, 5.4], "target": [4.0, 1.6, 3.0], "up": [0, 1, 0], "fov_deg": 40.0,
                             "size": [512, 512]}}
    shutil.copy(ROOT / "data_samples" / "object.glb", folder / "object.glb")
    out = folder / "scene.json"
    out.write_text(json.dumps(sc))
    return out


def main() -> None:
    from pipeline.bsh.build_bsh import memory_needed
    from pipeline.io import Cloud, read_json, write_cloud

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ns", default="200000,3000000")
    ap.add_argument("--size", default="512x512")
    ap.add_argument("--work", type=Path, default=ROOT / "bench" / "_work" / "cloud_scale")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "relight" / "cloud_scale.csv")
    ap.add_argument("--make-cloud", nargs=2, metavar=("N", "PLY"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.make_cloud:
        p, nn, c = surface_cloud(int(a.make_cloud[0]), noise=0.1)
        write_cloud(Path(a.make_cloud[1]), Cloud(p.astype(np.float32), nn.astype(np.float32), c.astype(np.float32)))
        return
    os.environ["PCRELIGHT_CACHE_DIR"] = "off"       # every stage computes what it would cache (a first run's times)
    a.work.mkdir(parents=True, exist_ok=True)
    scene = scene_json(a.work)
    rows = []
    for n in (int(x) for x in a.ns.split(",")):
        d = a.work / f"n{n}"
        d.mkdir(exist_ok=True)
        ply = d / "cloud.ply"
        # made in a child process: a stage's ru_maxrss counts the pages it shared with this process when it was
        # forked, so this process stays small (a 30 M-point cloud made here put 4.8 GB into a refusal's peak)
        subprocess.run([sys.executable, "-m", __spec__.name, "--make-cloud", str(n), str(ply)], check=True, cwd=ROOT)
        b = run_stage("build-bsh", [str(ply), "--out", str(d / "bsh.npz"), "-q"], d / "build-bsh.log")
        rep = read_json(d / "bsh.json") if b["rc"] == 0 else {"counts": {}}
        rows.append({**b, "n": n, "nodes": rep["counts"].get("n_nodes"), "walk_visits": None,
                     "model_mb": round(memory_needed(n) / 2 ** 20, 1),
                     **{f"{k}_s": rep.get("timings_s", {}).get(k) for k in ("read", "spacing", "pack", "write")},
                     "message": "" if b["rc"] == 0 else Path(b["log"]).read_text().strip().splitlines()[-1]})
        print(rows[-1], flush=True)
        if b["rc"] != 0:
            continue
        r = run_stage("relight", ["--bsh", str(d / "bsh.npz"), "--scene", str(scene), "--view", "view1", "--size", a.size,
                                  "--brdf", "lambert", "--albedo", "0.8,0.8,0.8", "--out", str(d / "relit"), "-q"],
                      d / "relight.log")
        st = read_json(d / "relit" / "stats.json") if r["rc"] == 0 else {}
        tm = st.get("time_s", {})
        rows.append({**r, "n": n, "nodes": rep["counts"].get("n_nodes"), "walk_visits": st.get("nodes_visited"),
                     "model_mb": None, **{f"{k}_s": tm.get(k) for k in RELIGHT_STEPS},
                     "bsh_upload_s": (st.get("startup_s") or {}).get("bsh_upload"), "message": ""})
        print(rows[-1], flush=True)
        ply.unlink()
    keys = list(dict.fromkeys(k for r in rows for k in r))
    for r in rows:
        r["log"] = os.path.relpath(r["log"], ROOT)
    write_rows(a.out, [{k: r.get(k, "") for k in keys} for r in rows])


if __name__ == "__main__":
    main()
