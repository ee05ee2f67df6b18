"""Benchmark of render-cubemaps' splatter, its automatic viewpoints and poisson's solvers.

    .venv/bin/python -m bench.expansion.bench_splat_poisson [--quick]

Synthetic input (no scene needed): the closed two-room box of tests/test_render_cubemaps.py,
sampled with N points (uniform on the surfaces, inward normals).  Writes
  bench/expansion/splat_poisson.csv   one row per measurement: what, n_points, size, unknowns, solver, seconds, extra
  bench/expansion/splat_poisson.png   one cube map's seconds against points (numba and, when a context opens,
                            GL point sprites; one line per face size), automatic viewpoints; Poisson
                            seconds against unknowns (direct vs amg)
Timings are wall-clock on this machine (2 cores, shared with other jobs): compare rows of one run.
"""
from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]

import numpy as np  # noqa: E402

from pipeline import io  # noqa: E402
from pipeline.expansion.poisson import knn_graph, solve_poisson  # noqa: E402
from pipeline.expansion.render_cubemaps import RenderCubemapsConfig, choose_viewpoints  # noqa: E402
from pipeline.expansion.splats import knn_splat_radii, render_cube_map  # noqa: E402
from pipeline.scene.geometry import two_rooms

BENCH = HERE   # the outputs (--out)


def timed(fn, *a, **k):
    t0 = time.perf_counter()
    r = fn(*a, **k)
    return r, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", type=Path, default=HERE, help="the folder of splat_poisson.{csv,png} (default bench/expansion/)")
    args = ap.parse_args()
    global BENCH
    BENCH = args.out
    BENCH.mkdir(parents=True, exist_ok=True)
    counts = [20_000, 100_000] if args.quick else [20_000, 200_000, 1_000_000]
    sizes = [256, 1024] if args.quick else [256, 512, 1024]
    rows = []
    try:
        from pipeline import gl

        ctx = gl.create_context()
        gl_name = gl.context_info(ctx)["renderer"]
    except Exception as e:  # noqa: BLE001 - no GL here: numba rows only
        print(f"no GL context ({e}); numba only")
        ctx, gl_name = None, None
    # warm the numba kernel
    p, c, _, _, n = two_rooms(2000)
    render_cube_map(p, c, knn_splat_radii(p).astype(float), np.array([1.0, 1, 1]), 32, normals=n)
    for npts in counts:
        pts, cols, pa, pb, nrm = two_rooms(npts)
        radii, t = timed(knn_splat_radii, pts)
        rows.append(dict(what="splat_radii", n_points=npts, seconds=t))
        radii = radii.astype(np.float64)
        for size in sizes:
            (faces, _), t = timed(render_cube_map, pts, cols, radii, np.array([1.0, 1.0, 1.0]), size)
            rows.append(dict(what="render_cube", n_points=npts, size=size, seconds=t,
                             extra=f"pixel coverage {faces[..., 3].mean():.4f}"))
            print(f"render {npts} points {size}²: {t:.2f} s")
            if ctx is not None:
                (gfaces, _), tg = timed(render_cube_map, pts, cols, radii, np.array([1.0, 1.0, 1.0]), size, gl_ctx=ctx)
                agree = float((np.abs(gfaces[..., 4] - faces[..., 4]) <= 1e-6 * faces[..., 4]).mean())
                rows.append(dict(what="render_cube_gl", n_points=npts, size=size, seconds=tg,
                                 extra=f"depth agrees with numba on {agree:.5f} of pixels"))
                print(f"render GL {npts} points {size}²: {tg:.2f} s")
        (eyes, info), t = timed(choose_viewpoints, pts, radii, pa | pb, RenderCubemapsConfig(), nrm)
        rows.append(dict(what="auto_viewpoints", n_points=npts, size=64, seconds=t,
                         extra=f"{info['candidates_free']} candidates, {len(eyes)} views, "
                               f"probe coverage {info['probe_coverage_after_each'][-1]:.3f}"))
        print(f"auto viewpoints {npts}: {t:.2f} s, {len(eyes)} views")
    # Poisson: unknowns = a patch of the 1M-point (or 100k) cloud
    pts, cols, _, _, _ = two_rooms(counts[-1])
    rng = np.random.default_rng(0)
    known = rng.uniform(1, 1000, len(pts))
    guide = np.full(len(pts), 0.95)
    from scipy.spatial import cKDTree

    tree = cKDTree(pts)
    for size in ([1_000, 10_000, 50_000] if args.quick else [1_000, 10_000, 100_000, 300_000]):
        omega = np.zeros(len(pts), dtype=bool)  # Ω = the `size` points nearest to a ceiling point
        omega[tree.query([1.0, 2.0, 1.0], k=size)[1]] = True
        g, tg = timed(knn_graph, pts, 16, omega)
        for solver in ("direct", "amg"):
            (_, _, info), t = timed(solve_poisson, g, omega, known, guide, solver)
            rows.append(dict(what="poisson", n_points=len(pts), unknowns=int(omega.sum()), solver=solver,
                             seconds=t, extra=f"graph {tg:.2f} s, residual {info['relative_residual']:.1e}"))
            print(f"poisson {int(omega.sum())} unknowns {solver}: {t:.2f} s")
    keys = ["what", "n_points", "size", "unknowns", "solver", "seconds", "extra"]
    with io.atomic_path(BENCH / "splat_poisson.csv") as tmp:
        with open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, keys)
            w.writeheader()
            for r in rows:
                w.writerow({k: r.get(k, "") for k in keys})
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    for size in sizes:
        rr = [r for r in rows if r["what"] == "render_cube" and r["size"] == size]
        ax[0].loglog([r["n_points"] for r in rr], [r["seconds"] for r in rr], "o-", label=f"numba {size}²")
        rg = [r for r in rows if r["what"] == "render_cube_gl" and r["size"] == size]
        if rg:
            ax[0].loglog([r["n_points"] for r in rg], [r["seconds"] for r in rg], "^:", label=f"GL {size}² ({gl_name})")
    ra = [r for r in rows if r["what"] == "auto_viewpoints"]
    ax[0].loglog([r["n_points"] for r in ra], [r["seconds"] for r in ra], "s--", label="automatic viewpoints")
    ax[0].set_xlabel("points")
    ax[0].set_ylabel("seconds")
    ax[0].legend()
    ax[0].set_title("render-cubemaps: one cube map (6 faces)")
    for solver in ("direct", "amg"):
        rr = [r for r in rows if r["what"] == "poisson" and r["solver"] == solver]
        ax[1].loglog([r["unknowns"] for r in rr], [r["seconds"] for r in rr], "o-", label=solver)
    ax[1].set_xlabel("unknowns |Ω|")
    ax[1].set_ylabel("seconds")
    ax[1].legend()
    ax[1].set_title("poisson solve (k = 16)")
    fig.tight_layout()
    io.save_figure(BENCH / "splat_poisson.png", fig)
    print("wrote bench/splat_poisson.csv, bench/expansion/splat_poisson.png")


if __name__ == "__main__":
    main()
