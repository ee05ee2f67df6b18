"""Where the environment map fails: a sphere moved towards a wall of a closed room, envmap against classic
PBGI (which sees the room from every receiver).

    .venv/bin/python -m bench.gatherers.bench_envmap_wall [--distances 3,1.5,0.8,0.5,0.35] [--radius 0.25] [--size 128]
        [--points 60000] [--out bench/gatherers/envmap_wall.csv]

The room is bench_relight.py's synthetic one (6 × 3 × 6 m, closed: coloured walls, a 2 × 2 m ceiling panel of
radiance 50; BSH by build-bsh's ``build_bsh``) — not the shipped scene, whose small bright sources make classic
itself move by up to 20 % between m 16 and 32 at points near its walls, too loose a reference. The sphere (radius
``--radius`` m, ray-cast G-buffer: bench_relight.sphere_gbuffer) sits at height 1.2 m, d metres from the red
wall at x = −3 (d = 3: the room's centre); the camera looks at it from 2 m along +z, so the half facing the wall
and the half facing away are both in view. A sphere is convex — no self-shadowing — so classic (m 32, the paper's
model) and envmap differ by what the environment map leaves out: the parallax and occlusion of the room near
the object. The capture's own error is measured apart: envmap and classic at the sphere's centre itself (64 random
normals, Lambert; ``same_point_*``) — what is left on the sphere beyond it is the parallax of the room near it.
Per d and material (Lambert 0.8; GGX 0.25 white metal): relative RMS of envmap against classic over
the sphere's pixels, on the half facing the wall (n·(−x) > 0.3) and the half facing away (n·x > 0.3), the mean
ratios, classic's own spread (m 24 against m 32), and the seconds of each (envmap: capture + filtering + shading).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]

from bench.benchlib import sphere_gbuffer, synthetic_room, write_rows

from pipeline import gl  # noqa: E402
from pipeline.gather import GATHERERS, GatherParams, Receivers  # noqa: E402
from pipeline.runtime import Timings, setup_logging  # noqa: E402

WALL_X = -3.0
CENTRE = np.array([0.0, 1.2, 0.0])


def rel_rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean((a - b) ** 2)) / max(np.sqrt(np.mean(b ** 2)), 1e-30)) if len(b) else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--distances", default="3,1.5,0.8,0.5,0.35")
    ap.add_argument("--radius", type=float, default=0.25)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--points", type=int, default=60000)
    ap.add_argument("--materials", default="lambert,ggx0.25")
    ap.add_argument("--out", type=Path, default=HERE / "envmap_wall.csv")
    a = ap.parse_args()
    setup_logging(-1)
    from pipeline.bsh.builder import build_bsh

    pts, nrm, col, *_ = synthetic_room(a.points)
    b = build_bsh(pts, nrm, col)
    nodes, splat, emit = b["nodes"], b.get("splat_radius"), b.get("emitters")
    ctx = gl.create_context()
    gl.bind_dummy_framebuffer(ctx)
    rows = []
    for d in (float(x) for x in a.distances.split(",")):
        c = CENTRE.copy()
        c[0] = WALL_X + d
        mask, P, N, V, flat = sphere_gbuffer(a.size, c + [0.0, 0.0, 2.0], c, c, a.radius)
        n = len(P)
        toward, away = N[:, 0] < -0.3, N[:, 0] > 0.3
        # the capture's own error: envmap and classic at the capture point itself (64 random normals, Lambert 1)
        rng = np.random.default_rng(0)
        pn = rng.normal(size=(64, 3))
        pn = (pn / np.linalg.norm(pn, axis=1, keepdims=True)).astype(np.float32)
        probe = Receivers(np.tile(c, (64, 1)).astype(np.float32), pn, pn, np.ones((64, 3), np.float32),
                          np.zeros(64, np.float32), np.ones(64, np.float32))
        po = {}
        for method, m in (("classic", 32), ("envmap", 16)):
            g = GATHERERS[method](ctx, nodes, GatherParams(m, object_center=tuple(c)), splat_radius=splat, emitters=emit)
            po[method], _ = g.run(probe)
            g.release()
        same_ratio = float(po["envmap"].sum() / max(po["classic"].sum(), 1e-30))
        same_rms = rel_rms(po["envmap"], po["classic"])
        for mat in a.materials.split(","):
            if mat == "lambert":
                kind, base, met, rough, masking = "lambert", 0.8, 0.0, 1.0, "height-correlated"
            else:
                kind, base, met, rough, masking = "ggx", 1.0, 1.0, float(mat[3:]), "separable"
            recv = Receivers(P, N, V, np.full((n, 3), base, np.float32), np.full(n, met, np.float32),
                             np.full(n, rough, np.float32))
            out, secs = {}, {}
            for key, method, m in (("classic", "classic", 32), ("classic24", "classic", 24), ("envmap", "envmap", 16)):
                params = GatherParams(m, brdf=kind, masking=masking, object_center=tuple(c), lobe_m=16)
                t0 = time.perf_counter()
                g = GATHERERS[method](ctx, nodes, params, splat_radius=splat, emitters=emit)
                out[key], _ = g.run(recv, flat, mask.shape, Timings())
                secs[key] = time.perf_counter() - t0
                g.release()
            e, r = out["envmap"], out["classic"]
            row = {"distance_m": d, "material": mat, "pixels": n,
                   "same_point_ratio": round(same_ratio, 4), "same_point_rel_rms": round(same_rms, 4),
                   "rel_rms": round(rel_rms(e, r), 4),
                   "rel_rms_facing_wall": round(rel_rms(e[toward], r[toward]), 4),
                   "rel_rms_facing_away": round(rel_rms(e[away], r[away]), 4),
                   "mean_ratio": round(float(e.sum() / max(r.sum(), 1e-30)), 4),
                   "mean_ratio_facing_wall": round(float(e[toward].sum() / max(r[toward].sum(), 1e-30)), 4),
                   "mean_ratio_facing_away": round(float(e[away].sum() / max(r[away].sum(), 1e-30)), 4),
                   "classic_m24_vs_m32": round(rel_rms(out["classic24"], r), 4),
                   "envmap_s": round(secs["envmap"], 2), "classic_s": round(secs["classic"], 2)}
            rows.append(row)
            print(row, flush=True)
    write_rows(a.out, rows)


if __name__ == "__main__":
    main()
