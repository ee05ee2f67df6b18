"""Numba's compile paid once per install (issue 46): ``python -m pipeline.run.warm`` — ``make setup`` runs it after
the install — runs the stages whose kernels numba compiles on tiny inputs of the dtypes real runs use, so that the
kernels' cache (``@njit(cache=True)``: files in ``__pycache__`` beside the sources, one per function and signature)
is written at install and the first real run loads it instead of compiling.

Warmed: build-bsh (the whole stage on a 4 000-point sphere: its 46 tree and cone kernels), the cloud splatter
(:func:`pipeline.expansion.splats.render_cube_map` and :func:`view_index`), PatchMatch
(:func:`pipeline.expansion.patchmatch.pyramid_patchmatch`). Not warmed: register_photo's kernels (they compile on a
registration's first run, ~10 s). Measured (docs/bench/bsh.md "cold start"): the first build-bsh of the shipped
cloud after the warm takes the warm time."""

from __future__ import annotations

import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def warm() -> dict[str, float]:
    """Run each warmed stage once on tiny inputs; returns seconds per part."""
    from .. import io
    from ..bsh.build_bsh import BuildBshConfig, run_build_bsh
    from ..expansion import patchmatch, splats

    out: dict[str, float] = {}
    rng = np.random.default_rng(0)
    n = 4000
    p = rng.normal(size=(n, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    col = np.abs(rng.normal(size=(n, 3))) * 0.5
    col[:12] = 2000.0                                        # a small bright lamp: the emitter kernels too
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        cloud = io.Cloud(points=(2.0 * p).astype(np.float32), normals=(-p).astype(np.float32), colors=col.astype(np.float32))
        io.write_cloud(Path(d) / "warm.ply", cloud)
        run_build_bsh(Path(d) / "warm.ply", Path(d) / "bsh.npz", BuildBshConfig())
        out["build-bsh"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        pts = cloud.points.astype(np.float64)
        radii = splats.knn_splat_radii(pts)
        splats.render_cube_map(pts, cloud.colors, radii, np.zeros(3), 16)
        splats.render_cube_map(pts, cloud.colors, radii, np.zeros(3), 16, normals=cloud.normals)
        splats.view_index(pts, radii, np.eye(4), 60.0, (16, 12))
        out["splats"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        src = rng.random((24, 24, 3)).astype(np.float32)
        patchmatch.pyramid_patchmatch(src, src[::-1].copy(), iterations=1)
        out["patchmatch"] = time.perf_counter() - t0
    return out


def main() -> None:
    from ..runtime import setup_logging

    setup_logging(-1)
    t0 = time.perf_counter()
    parts = warm()
    print(f"pcrelight: numba kernels compiled and cached in {time.perf_counter() - t0:.0f} s ("
          + ", ".join(f"{k} {v:.0f} s" for k, v in parts.items()) + ")", file=sys.stderr)


if __name__ == "__main__":
    main()
