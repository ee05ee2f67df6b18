"""A walk change before/after at 512², whole relight processes, alternated in one run (issue 23, item 1).

    .venv/bin/python -m bench.speed.bench_walk_restructure --before /tmp/tree_before --bsh bsh.npz [--scene DIR]
        [--views view1] [--materials lambert,ggx0.25] [--size 512x512] [--reps 2] [--before-env K=V,..] [--after-env K=V,..]
        [--out bench/speed/walk_restructure_512.csv]

``--before`` is a second checkout (``git archive <commit> | tar -x -C DIR``), "after" this one. Every repetition runs,
for each view and material, one relight process of each tree (bench_relight_steps.py's worker: relight's defaults,
the material of bench_relight_truth.material_kw), alternating which tree goes first, and one bare-loop floor
(bench_walk_profile.py's: node reads per CPU-second of a compute loop with nothing else, this checkout's context).
Per row: the walk's process CPU seconds (relight's ``walk`` + ``walk_lobe`` steps: the pixels' walks, not the bounce
passes'), the whole process's CPU seconds (the child's rusage), node visits (stats.json ``nodes_visited``), visits per
walk CPU-second, and whether the image equals the other tree's bit for bit (``relit.exr``, the same view and material).
``--before-env``/``--after-env``: environment variables of that side's relight processes (e.g. the same tree twice,
``--after-env LP_NATIVE_VECTOR_WIDTH=128``: llvmpipe's SIMD width).
CPU seconds count every thread (llvmpipe's too), so they are less sensitive to the other jobs of a shared machine
than wall seconds; ``load`` is /proc/loadavg when the worker ended.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]

from bench.speed import bench_relight_steps as steps
from bench.speed import bench_walk_profile as profile


def relight_row(root: str, view: str, mat: str, work: Path, a: argparse.Namespace, env: str = "") -> dict:
    """One relight process of the tree at ``root`` (with the environment variables ``env``, "K=V,K2=V2"): its step
    rows folded into one row."""
    ns = argparse.Namespace(root=root, bsh=a.bsh, scene=a.scene, view=view, size=a.size, lambert=False, material=mat,
                            work=str(work))
    extra = dict(kv.split("=", 1) for kv in env.split(",") if kv)
    saved = {k: os.environ.get(k) for k in extra}
    os.environ.update(extra)
    try:
        rows = {r["step"]: r for r in steps.run_worker(ns, 0)}
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    walk_cpu = sum(float(rows[k]["cpu_s"]) for k in ("walk", "walk_lobe") if k in rows)
    walk_s = sum(float(rows[k]["wall_s"]) for k in ("walk", "walk_lobe") if k in rows)
    nv = int(rows["process"]["nodes_visited"])
    return {"view": view, "material": mat, "walk_s": round(walk_s, 3), "walk_cpu_s": round(walk_cpu, 3),
            "process_s": rows["process"]["wall_s"], "process_cpu_s": rows["process"]["cpu_s"], "nodes_visited": nv,
            "visits_per_walk_cpu_s": round(nv / max(walk_cpu, 1e-9)), "shaded": rows["process"]["shaded"],
            "load": rows["process"]["load"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--before", required=True, help="the 'before' checkout")
    ap.add_argument("--bsh", required=True)
    ap.add_argument("--scene", default=str(ROOT / "data_samples"))
    ap.add_argument("--views", default="view1")
    ap.add_argument("--materials", default="lambert,ggx0.25")
    ap.add_argument("--size", default="512x512")
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--work", default="/tmp/bench_walk_restructure")
    ap.add_argument("--before-env", default="", help="K=V,... for the 'before' processes")
    ap.add_argument("--after-env", default="", help="K=V,... for the 'after' processes")
    ap.add_argument("--out", type=Path, default=HERE / "walk_restructure_512.csv")
    a = ap.parse_args()
    a.bsh, a.scene = str(Path(a.bsh).resolve()), str(Path(a.scene).resolve())
    if not (Path(a.before) / "pipeline").is_dir():
        sys.exit(f"pcrelight: {a.before}: no pipeline/ there (git archive <commit> | tar -x -C {a.before})")
    trees = [("before", str(Path(a.before).resolve())), ("after", str(ROOT))]
    fl = argparse.Namespace(bsh=a.bsh, scene=a.scene, view="view1", size=a.size, floor_invocations=16384)
    rows: list[dict] = []
    for rep in range(a.reps):
        f = profile.run_worker(str(ROOT), "", 0.0, fl, "", floor=True)
        floor = round(f["nodes_visited"] / max(f["walk_cpu_s"], 1e-9))
        rows.append({"rep": rep, "tree": "floor", "view": "", "material": "", "walk_s": round(f["walk_s"], 3),
                     "walk_cpu_s": round(f["walk_cpu_s"], 3), "nodes_visited": f["nodes_visited"],
                     "visits_per_walk_cpu_s": floor, "load": profile.load()})
        print(rows[-1], flush=True)
        for view in a.views.split(","):
            for mat in a.materials.split(","):
                for name, root in (trees if rep % 2 == 0 else trees[::-1]):
                    work = Path(a.work) / f"{name}_{view}_{mat}"
                    env = a.before_env if name == "before" else a.after_env
                    rows.append({"rep": rep, "tree": name, **relight_row(root, view, mat, work, a, env), "env": env})
                    print(rows[-1], flush=True)
    from pipeline.io import read_image
    for r in rows:
        if r["tree"] in ("before", "after"):
            im = [read_image(Path(a.work) / f"{n}_{r['view']}_{r['material']}" / "rep0" / "relit.exr")
                  for n in ("before", "after")]
            r["image_same"] = bool(np.array_equal(im[0], im[1], equal_nan=True))
    cols = ["rep", "tree", "view", "material", "walk_s", "walk_cpu_s", "process_s", "process_cpu_s", "nodes_visited",
            "visits_per_walk_cpu_s", "shaded", "image_same", "env", "load"]
    a.out.parent.mkdir(parents=True, exist_ok=True)
    with open(a.out, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    print(f"wrote {a.out}")
    med = lambda xs: float(np.median(xs)) if xs else float("nan")   # noqa: E731
    print(f"floor: {med([r['visits_per_walk_cpu_s'] for r in rows if r['tree'] == 'floor']) / 1e6:.0f} M node reads / CPU-s")
    for view in a.views.split(","):
        for mat in a.materials.split(","):
            sel = {n: [r for r in rows if r["tree"] == n and r["view"] == view and r["material"] == mat] for n, _ in trees}
            b, f = ({k: med([float(r[k]) for r in sel[n]]) for k in ("walk_cpu_s", "process_cpu_s", "visits_per_walk_cpu_s")}
                    for n in ("before", "after"))
            print(f"{view} {mat}: walk CPU s {b['walk_cpu_s']:.2f} -> {f['walk_cpu_s']:.2f} "
                  f"({b['walk_cpu_s'] / f['walk_cpu_s']:.2f}x), process CPU s {b['process_cpu_s']:.2f} -> "
                  f"{f['process_cpu_s']:.2f} ({b['process_cpu_s'] / f['process_cpu_s']:.2f}x), visits/CPU-s "
                  f"{b['visits_per_walk_cpu_s'] / 1e6:.1f} M -> {f['visits_per_walk_cpu_s'] / 1e6:.1f} M, images same: "
                  f"{all(r['image_same'] for r in sel['after'])}")


if __name__ == "__main__":
    main()
