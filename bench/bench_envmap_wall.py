"""Where the environment map fails: a sphere moved towards a wall of the shipped room, envmap against
classic PBGI (which sees the room from every receiver).

    .venv/bin/python bench/bench_envmap_wall.py [SCENE_DIR] [--bsh bsh.npz] [--distances 6.5,3,1.5,0.8,0.5,0.35]
        [--radius 0.25] [--size 128] [--m 32] [--out bench/envmap_wall_small.csv]

The sphere (radius ``--radius`` m, ray-cast G-buffer: bench_relight.sphere_gbuffer) sits at the knot's centre
(1.5, 1.3, −0.5) moved along −z so that its centre is d metres from the room's z = −7 wall (d = 6.5: the knot's
place); the camera looks at it from 2 m along +x (both the side facing the wall and the side facing away
are in view). A sphere is convex — no self-shadowing — so classic PBGI (m = ``--m``, the paper's model, no
object surfels) and envmap differ by what the environment map leaves out: the parallax and occlusion of
the room near the object. Per d and material (Lambert 0.8; GGX 0.25 white metal): relative RMS of envmap
against classic over the sphere's pixels, on the half facing the wall (n·(−z) > 0.3) and the half facing
away (n·z > 0.3), the mean ratio, and the seconds of each (envmap: capture + filtering + shading).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from bench_relight import sphere_gbuffer  # noqa: E402
from bench_relight_truth import truth_bsh, write_rows  # noqa: E402

from pipeline import gl, io  # noqa: E402
from pipeline.bsh_format import nodes_from_bsh  # noqa: E402
from pipeline.gather import GATHERERS, GatherParams, Receivers  # noqa: E402
from pipeline.runtime import Timings, setup_logging  # noqa: E402

WALL_Z = -7.0
CENTRE = np.array([1.5, 1.3, -0.5])


def rel_rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean((a - b) ** 2)) / max(np.sqrt(np.mean(b ** 2)), 1e-30)) if len(b) else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path, nargs="?", default=ROOT / "data_samples")
    ap.add_argument("--bsh", type=Path)
    ap.add_argument("--distances", default="6.5,3,1.5,0.8,0.5,0.35")
    ap.add_argument("--radius", type=float, default=0.25)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--m", type=int, default=32)
    ap.add_argument("--materials", default="lambert,ggx0.25")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "envmap_wall_small.csv")
    ap.add_argument("--work", type=Path, default=ROOT / "bench" / "_work" / "envmap")
    a = ap.parse_args()
    setup_logging(-1)
    b = io.read_npz(truth_bsh(a.scene, a.bsh, a.work), "pcrelight.bsh/1")
    nodes, splat, emit = nodes_from_bsh(b), b.get("splat_radius"), b.get("emitters")
    ctx = gl.create_context()
    gl.bind_dummy_framebuffer(ctx)
    rows = []
    for d in (float(x) for x in a.distances.split(",")):
        c = CENTRE.copy()
        c[2] = WALL_Z + d
        mask, P, N, V, flat = sphere_gbuffer(a.size, c + [2.0, 0.0, 0.0], c, c, a.radius)
        n = len(P)
        toward, away = N[:, 2] < -0.3, N[:, 2] > 0.3
        for mat in a.materials.split(","):
            if mat == "lambert":
                kind, base, met, rough, masking = "lambert", 0.8, 0.0, 1.0, "height-correlated"
            else:
                kind, base, met, rough, masking = "ggx", 1.0, 1.0, float(mat[3:]), "separable"
            recv = Receivers(P, N, V, np.full((n, 3), base, np.float32), np.full(n, met, np.float32),
                             np.full(n, rough, np.float32))
            out, secs = {}, {}
            for method, m in (("classic", a.m), ("envmap", 16)):
                params = GatherParams(m, brdf=kind, masking=masking, object_center=tuple(c), lobe_m=16)
                t0 = time.perf_counter()
                g = GATHERERS[method](ctx, nodes, params, splat_radius=splat, emitters=emit)
                out[method], _ = g.run(recv, flat, mask.shape, Timings())
                secs[method] = time.perf_counter() - t0
                g.release()
            e, r = out["envmap"], out["classic"]
            row = {"distance_m": d, "material": mat, "pixels": n, "rel_rms": round(rel_rms(e, r), 4),
                   "rel_rms_facing_wall": round(rel_rms(e[toward], r[toward]), 4),
                   "rel_rms_facing_away": round(rel_rms(e[away], r[away]), 4),
                   "mean_ratio": round(float(e.sum() / max(r.sum(), 1e-30)), 4),
                   "mean_ratio_facing_wall": round(float(e[toward].sum() / max(r[toward].sum(), 1e-30)), 4),
                   "envmap_s": round(secs["envmap"], 2), "classic_s": round(secs["classic"], 2)}
            rows.append(row)
            print(row, flush=True)
    write_rows(a.out, rows)


if __name__ == "__main__":
    main()
