"""The walk's speed on llvmpipe, before and after a change, against a bare-loop floor (issue 23, item 1).

    .venv/bin/python -m bench.speed.bench_walk_profile --root /tmp/pcr_dc72d67 [--bsh /tmp/bsh_gt.npz] [--size 512x512]
        [--reps 3] [--adaptive 0.3 0] [--out bench/speed/walk_profile.csv]

``--root`` is a second checkout of the pipeline (e.g. ``git archive dc72d67 | tar -x -C /tmp/pcr_dc72d67``), the
"before"; "after" is this checkout. Each measurement is one worker process (the two trees both call their package
``pipeline``), run alternately: for every repetition, every ``--adaptive`` value, the before and after trees, the
walk with splats and with PROF_NOSPLAT (stopped nodes not splatted: the traversal's own cost). Every worker runs
relight on ``--view`` (defaults otherwise: classic, m 24, the object's surfels, the BSH given) and reports the walk's
wall seconds (stats ``time_s.walk`` + ``walk_lobe``), its process CPU seconds (all threads, less sensitive to
other load on the machine), node visits and visits per second; one extra worker per tree counts the splats
(PROF_SPLATS; the same for both trees when the images agree) and the images are compared bit for bit.
The floor: a compute shader that reads K nodes of the same node array per invocation (consecutive, from a
scattered start) and accumulates them, at the walk's invocation count — node reads per second with nothing else.
``uptime``'s load averages are written with every row (2 cores shared with other work: compare within a run).

``--parts``: the splat's parts as well, on this checkout (each row one more part of the splat than the previous; the
images of these rows are wrong, and their node visits may differ a little, the object's bounce light being wrong):
``PROF_NOSPLAT`` the traversal, ``PROF_QUEUE_ONLY`` + the queue's pushes and reads, ``PROF_SETUP_ONLY`` + the stopped
node re-read and put in the splat frame, ``PROF_TEXEL_EMPTY`` + the splat's bounds and its row and texel loops
(no texel test), ``PROF_NOWRITE`` + the texel tests (no micro-buffer read or write); ``walk`` = all of it. The
summary scales each row's CPU seconds by the walk's node visits / the row's.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]

from bench.benchlib import load

FLOOR_SRC = """#version 430
layout(local_size_x = 64) in;
struct Node { uint right; uint skip; float cx, cy, cz; float r, g, b; float radius; uint cone; };
layout(std430, binding = 0) readonly buffer Nodes { Node nodes[]; };
layout(std430, binding = 1) writeonly buffer Out { float outv[]; };
uniform uint n_inv;
uniform uint n_nodes;
uniform int k_nodes;
void main() {
    uint k = gl_GlobalInvocationID.x;
    if (k >= n_inv) return;
    uint i = (k * 7919u) % n_nodes;
    float acc = 0.0;
    for (int j = 0; j < k_nodes; ++j) {
        Node nd = nodes[i];
        acc += nd.cx * nd.cy + nd.cz - nd.radius + float(nd.skip & 1u);
        i = i + 1u < n_nodes ? i + 1u : 0u;
    }
    outv[k] = acc;
}
"""


PARTS = ("PROF_QUEUE_ONLY", "PROF_SETUP_ONLY", "PROF_TEXEL_EMPTY", "PROF_NOWRITE")


def worker(args: argparse.Namespace) -> None:
    """One relight in this process with the pipeline at --root; prints one JSON line."""
    sys.path.insert(0, str(Path(args.root).resolve()))
    sys.path.insert(0, str(HERE))
    from pipeline.gather.walk import WalkGatherer
    from pipeline.relight.relight import RelightConfig, run_relight
    from pipeline.runtime import setup_logging

    setup_logging(-1)
    WalkGatherer.PROFILE_DEFINES = tuple(d for d in args.defs.split(",") if d)
    cpu = [0.0]
    orig = WalkGatherer.walk_and_gather

    def timed(self, *a, **k):   # the walk's tiles + Eq. 9 (small) + the tiles' uploads and read-backs (small): CPU
        # seconds of every thread of the process (walk_profile.csv's rows before 2026-12-03 12:35 timed the tiles alone)
        c0 = time.process_time()
        try:
            return orig(self, *a, **k)
        finally:
            cpu[0] += time.process_time() - c0

    WalkGatherer.walk_and_gather = timed
    cfg = RelightConfig(size=args.size, adaptive=float(args.adaptive_one))
    cfg.check()
    t0 = time.perf_counter()
    st = run_relight(Path(args.bsh), Path(args.outdir), cfg, scene_path=Path(args.scene) / "scene.json", view=args.view)
    ts = st["time_s"]
    print("RESULT " + json.dumps({"walk_s": ts.get("walk", 0.0) + ts.get("walk_lobe", 0.0), "walk_cpu_s": cpu[0],
                                  "nodes_visited": int(st["nodes_visited"]), "receivers": int(st.get("covered_pixels", 0)),
                                  "total_s": time.perf_counter() - t0}), flush=True)


def floor_worker(args: argparse.Namespace) -> None:
    """Node reads per second of the bare loop (this checkout's GL context)."""
    sys.path.insert(0, str(ROOT))
    from pipeline import gl
    from pipeline.bsh.format import nodes_from_bsh

    ctx = gl.create_context()
    nodes = nodes_from_bsh(dict(np.load(args.bsh)))
    n_inv, k = int(args.floor_invocations), 2048
    nb = ctx.buffer(nodes.tobytes())
    ob = ctx.buffer(reserve=4 * n_inv)
    prog = ctx.compute_shader(FLOOR_SRC)
    nb.bind_to_storage_buffer(0)
    ob.bind_to_storage_buffer(1)
    prog["n_inv"].value, prog["n_nodes"].value, prog["k_nodes"].value = n_inv, len(nodes), k
    prog.run(group_x=1)                 # compile
    ctx.finish()
    best = []
    for _ in range(3):
        c0, t0 = time.process_time(), time.perf_counter()
        prog.run(group_x=(n_inv + 63) // 64)
        ob.read(size=4)
        ctx.finish()
        best.append((time.perf_counter() - t0, time.process_time() - c0))
    w, c = min(best)
    print("RESULT " + json.dumps({"walk_s": w, "walk_cpu_s": c, "nodes_visited": n_inv * k, "receivers": n_inv,
                                  "total_s": w}), flush=True)


def run_worker(root: str, defs: str, adaptive: float, args: argparse.Namespace, outdir: str, floor: bool = False) -> dict:
    cmd = [sys.executable, "-m", __spec__.name, "--worker", "--root", root, "--defs", defs, "--adaptive-one", str(adaptive),
           "--bsh", args.bsh, "--scene", args.scene, "--view", args.view, "--size", args.size, "--outdir", outdir,
           "--floor-invocations", str(args.floor_invocations)] + (["--floor"] if floor else [])
    res = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"})
    line = [x for x in res.stdout.splitlines() if x.startswith("RESULT ")]
    if res.returncode != 0 or not line:
        raise RuntimeError(f"worker failed ({root}, {defs}): {res.stderr[-2000:]}")
    return json.loads(line[0][7:])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", default="/tmp/pcr_dc72d67", help="the 'before' checkout")
    ap.add_argument("--same-root", default="", help="the tree whose image 'after' must equal bit for bit (default: --root; "
                    "give this checkout with the walk files of --root when other files changed since)")
    ap.add_argument("--bsh", default="/tmp/bsh_gt.npz")
    ap.add_argument("--scene", default=str(ROOT / "data_samples"))
    ap.add_argument("--view", default="view1")
    ap.add_argument("--size", default="512x512")
    ap.add_argument("--adaptive", type=float, nargs="+", default=[0.3])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--floor-invocations", type=int, default=16384)
    ap.add_argument("--out", default=str(HERE / "walk_profile.csv"))
    ap.add_argument("--parts", action="store_true", help="also the splat's parts (PROF_QUEUE_ONLY, PROF_SETUP_ONLY, "
                    "PROF_TEXEL_EMPTY, PROF_NOWRITE) on this checkout")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--floor", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--defs", default="", help=argparse.SUPPRESS)
    ap.add_argument("--adaptive-one", default="0.3", help=argparse.SUPPRESS)
    ap.add_argument("--outdir", default="", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        (floor_worker if args.floor else worker)(args)
        return
    if not (Path(args.root) / "pipeline").is_dir():
        sys.exit(f"--root {args.root}: no pipeline/ there (git archive <commit> | tar -x -C {args.root})")
    trees = {"before": str(Path(args.root).resolve()), "after": str(ROOT)}
    tmp = Path("/tmp/bench_walk_profile")
    rows, splats, same = [], {}, {}
    sys.path.insert(0, str(ROOT))
    from pipeline.io import read_image as read_exr
    for ad in args.adaptive:                     # splat counts (PROF_SPLATS: after's walk; before's when the images
        r = run_worker(str(ROOT), "PROF_SPLATS", ad, args, str(tmp / f"after_{ad}_splats"))   # agree) and the image
        splats[("after", ad)] = splats[("before", ad)] = r["nodes_visited"]
        run_worker(str(Path(args.same_root or args.root).resolve()), "", ad, args, str(tmp / f"same_{ad}"))
    for rep in range(args.reps):
        f = run_worker(str(ROOT), "", 0.0, args, "", floor=True)
        rows.append({"rep": rep, "tree": "floor", "adaptive": "", "variant": "bare loop", **f, "splats": "",
                     "load_1_5_15": load()})
        print(rows[-1], flush=True)
        for ad in args.adaptive:
            for name, root in (trees.items() if rep % 2 == 0 else reversed(list(trees.items()))):
                for variant, defs in (("walk", ""), ("traversal (PROF_NOSPLAT)", "PROF_NOSPLAT")):
                    out = tmp / f"{name}_{ad}_{'full' if not defs else 'nosplat'}"
                    r = run_worker(root, defs, ad, args, str(out))
                    rows.append({"rep": rep, "tree": name, "adaptive": ad, "variant": variant, **r,
                                 "splats": splats[(name, ad)] if not defs else "", "load_1_5_15": load()})
                    print(rows[-1], flush=True)
            for defs in (PARTS if args.parts else ()):
                r = run_worker(str(ROOT), defs, ad, args, str(tmp / f"after_{ad}_{defs}"))
                rows.append({"rep": rep, "tree": "after", "adaptive": ad, "variant": f"part ({defs})", **r,
                             "splats": "", "load_1_5_15": load()})
                print(rows[-1], flush=True)
    for ad in args.adaptive:
        a, b = (read_exr(tmp / d / "relit.exr") for d in (f"same_{ad}", f"after_{ad}_full"))
        same[ad] = bool(np.array_equal(a, b, equal_nan=True))
    for r in rows:
        r["visits_per_s"] = round(r["nodes_visited"] / max(r["walk_s"], 1e-9))
        r["visits_per_cpu_s"] = round(r["nodes_visited"] / max(r["walk_cpu_s"], 1e-9))
        r["image_same_as_before"] = same.get(r["adaptive"], "") if r["tree"] == "after" else ""
        for k in ("walk_s", "walk_cpu_s", "total_s"):
            r[k] = round(r[k], 3)
    cols = ["rep", "tree", "adaptive", "variant", "walk_s", "walk_cpu_s", "nodes_visited", "visits_per_s",
            "visits_per_cpu_s", "splats", "receivers", "total_s", "image_same_as_before", "load_1_5_15"]
    with open(args.out, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    print(f"wrote {args.out}")
    for ad in args.adaptive:
        for variant in ("walk", "traversal (PROF_NOSPLAT)"):
            v = {n: [r["walk_s"] for r in rows if r["tree"] == n and r["adaptive"] == ad and r["variant"] == variant]
                 for n in trees}
            c = {n: [r["walk_cpu_s"] for r in rows if r["tree"] == n and r["adaptive"] == ad and r["variant"] == variant]
                 for n in trees}
            print(f"adaptive {ad} {variant}: before {np.median(v['before']):.2f} s ({min(v['before']):.2f}-{max(v['before']):.2f}), "
                  f"after {np.median(v['after']):.2f} s ({min(v['after']):.2f}-{max(v['after']):.2f}); CPU before "
                  f"{np.median(c['before']):.2f}, after {np.median(c['after']):.2f}; ratio (wall, median) "
                  f"{np.median(v['before']) / np.median(v['after']):.2f}, images same: {same[ad]}")
        if args.parts:       # the parts' CPU seconds (medians), each the difference to the previous row; a row's
            # CPU seconds scaled by the walk's node visits / its own (the profiling rows' wrong images change the
            # object's bounce light, hence the adaptive refinement: ~14 % more visits at 512² on view1)
            seq = ["traversal (PROF_NOSPLAT)", *(f"part ({d})" for d in PARTS), "walk"]
            nv = float(np.median([r["nodes_visited"] for r in rows if r["tree"] == "after" and r["adaptive"] == ad
                                  and r["variant"] == "walk"]))
            med = [float(np.median([r["walk_cpu_s"] * nv / max(r["nodes_visited"], 1) for r in rows
                                    if r["tree"] == "after" and r["adaptive"] == ad and r["variant"] == name]))
                   for name in seq]
            names = ["traversal", "queue pushes + reads", "node re-read + splat frame",
                     "splat bounds + row/texel loop control", "texel tests", "micro-buffer reads/writes"]
            print(f"adaptive {ad}, after, walk CPU s {med[-1]:.2f} (medians): " + "; ".join(
                f"{n} {b - a if i else b:.2f} ({(b - a if i else b) / med[-1]:.0%})"
                for i, (n, a, b) in enumerate(zip(names, [0.0, *med[:-1]], med))))


if __name__ == "__main__":
    main()
