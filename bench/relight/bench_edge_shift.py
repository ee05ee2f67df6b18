"""How far an open edge's surfel discs should move inwards (``pipeline.relight.surfels.EDGE_SHIFT``): the union of
the object BSH's leaf discs on a face-on plate against the plate's analytic form factor, by the share moved.

    .venv/bin/python -m bench.relight.bench_edge_shift [--shares 0,0.3,0.5,0.6,0.7,1] [--samples 400000] --out bench/relight/edge_shift.csv

A 2 × 2 m open plate (two triangles, y = 1, 4 000 surfels a side as relight samples them) seen from a receiver at the
origin facing it: a direction drawn from the cosine lobe counts where the discs of the plate's leaves (centres and
splat radii of :func:`surfels.object_bsh`) cover its hit on the plate's plane. Columns: the union's form factor, its
ratio to the analytic one (0.5546), the share of samples covered outside the plate (the overhang) and missed inside.
The discs of a round surfel overhang a straight edge; moved wholly inside it they leave slivers open between them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]

from bench.benchlib import part, plate_form_factor, write_rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shares", default="0,0.3,0.5,0.6,0.7,1")
    ap.add_argument("--samples", type=int, default=400000)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()
    import trimesh
    from scipy.spatial import cKDTree

    from pipeline.bsh.format import LEAF
    from pipeline.relight import surfels as sf

    v = np.array([[-1, 1, 1], [1, 1, 1], [1, 1, -1], [-1, 1, -1]], np.float64)
    m = trimesh.Trimesh(v, [[0, 2, 1], [0, 3, 2]], process=False)
    srf = sf.sample_surfels([part(m)], 4000, seed=0)
    rng = np.random.default_rng(0)
    u1, u2 = rng.random(a.samples), rng.random(a.samples)
    r, ph = np.sqrt(u1), 2 * np.pi * u2
    hit = np.stack([r * np.cos(ph), r * np.sin(ph)], 1) / np.sqrt(1 - u1)[:, None]   # (x, z) on the plane y = 1
    inside = (np.abs(hit) <= 1).all(1)
    want = 4 * plate_form_factor(1.0, 1.0, 1.0)
    rows = []
    keep = sf.EDGE_SHIFT
    try:
        for share in (float(s) for s in a.shares.split(",")):
            sf.EDGE_SHIFT = share
            b = sf.object_bsh(srf, cache=False)
            leaf = np.flatnonzero(b["nodes"]["right"] == LEAF)
            c = b["nodes"]["center"][leaf][:, [0, 2]].astype(np.float64)
            rad = b["splat_radius"][leaf].astype(np.float64)
            near = cKDTree(c).query_ball_point(hit, float(rad.max()))
            cov = np.array([bool(ix) and bool((np.linalg.norm(c[ix] - h, axis=1) <= rad[ix]).any())
                            for ix, h in zip(near, hit)])
            row = {"share_moved": share, "form_factor": round(float(cov.mean()), 5), "analytic": round(want, 5),
                   "ratio": round(float(cov.mean()) / want, 4), "covered_outside": round(float((cov & ~inside).mean()), 5),
                   "missed_inside": round(float((~cov & inside).mean()), 5), "samples": a.samples}
            rows.append(row)
            print(row, flush=True)
    finally:
        sf.EDGE_SHIFT = keep
    write_rows(a.out, rows)


if __name__ == "__main__":
    main()
