"""Why expose-match's registration grew past 15 GB on make-scene full's 3 M points (issue 23 item 5): the neighbour
pairs :func:`pipeline.expansion.register_photo.smooth_features` holds at the point refinement's σ = 8 and 4 photo pixels, for the
cloud's points in the photo's frame at its TRUE pose (an upper bound on the registration's: no occlusion test), on
the whole cloud and on the fixed 500 000-point subset the registration now uses (:func:`register_subset`). Before the
fix every pair was held at once, as Python lists (≈ 36 B a pair) and then int64/float64 pair arrays (≈ 64 B a pair).

    .venv/bin/python -m bench.photos.register_pairs INPUTS      # INPUTS: cloud_ldr.ply, photo.exr, truth/truth.npz
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from pipeline import io  # noqa: E402
from pipeline.expansion.register_photo import point_features, register_subset  # noqa: E402


def main() -> None:
    d = Path(sys.argv[1])
    tr = io.read_npz(d / "truth" / "truth.npz", "pcrelight.truth/1")
    c = io.read_cloud(d / "cloud_ldr.ply")
    h, w = io.read_image(d / "photo.exr").shape[:2]
    P = c.points.astype(np.float64)
    W, K = tr["photo_world_to_camera"], tr["photo_K"]
    cc = P @ W[:3, :3].T + W[:3, 3]
    with np.errstate(all="ignore"):
        u, v = K[0, 0] * cc[:, 0] / cc[:, 2] + K[0, 2], K[1, 1] * cc[:, 1] / cc[:, 2] + K[1, 2]
    _, use, _ = point_features(c.colors)
    sub = register_subset(len(P))
    for name, s in (("whole cloud", np.arange(len(P))), ("registration subset", sub)):
        if s is None:
            continue
        sel = s[(cc[s, 2] > 1e-3) & (u[s] >= 0) & (u[s] <= w) & (v[s] >= 0) & (v[s] <= h) & use[s]]
        tree = cKDTree(P[sel])
        for sig in (8.0, 4.0):
            sm = sig * np.maximum(cc[sel, 2], 1e-3) / K[0, 0]
            t = time.perf_counter()
            n = tree.query_ball_point(P[sel], 2 * sm, return_length=True, workers=-1)
            print(f"{name} ({len(s)} points): {len(sel)} in the frame, σ {sig:g} px: {n.sum():.3e} pairs (mean {n.mean():.0f}); "
                  f"all at once ≈ {n.sum() * 36 / 1e9:.1f} GB of lists + {n.sum() * 64 / 1e9:.1f} GB of pair arrays "
                  f"({time.perf_counter() - t:.1f} s)", flush=True)


if __name__ == "__main__":
    main()
