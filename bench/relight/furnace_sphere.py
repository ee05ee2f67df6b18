"""The white furnace for the object's own light (issue 43): a Lambert UV sphere (radius 1 m, albedo 0.5) inside a
closed shell of radiance 1 (radius 6 m, 40 000 points, normals inward), relight 64² from (0, 0.5, 3): every object
pixel should read albedo × 1. Prints each variant's mean / min / max over the object pixels (÷ 0.5).

    .venv/bin/python -m bench.relight.furnace_sphere [--segments 64x32] [--variants "" "--surfels -1" ...]

Measured 2026-12-07 (64×32 facets, m 24): defaults 0.990; --bounces 0 0.980; --room-shadow off (with --bounces 0)
0.99993; --surfels -1 0.99993; --object-near 2, --object-stop 0.25, --disc-cone 3, --splat-lambda 0, --surfels
50000, --method hybrid, m 16: all 0.980 with --bounces 0 — not the object's surfels: the room shadow darkens the
shell by the share of its hemisphere the sphere covers (L'/L 0.980 at every shell leaf), the model of a reflecting
room, where an emitting shell stays at 1."""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from bench.benchlib import ROOT, WORK


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--segments", default="64x32", help="the UV sphere's longitude × latitude segments")
    ap.add_argument("--variants", nargs="*", default=["", "--bounces 0", "--bounces 0 --room-shadow off", "--surfels -1"])
    a = ap.parse_args()
    import trimesh

    from pipeline import io

    d = WORK / "furnace_sphere"
    d.mkdir(parents=True, exist_ok=True)
    n = 40000
    i = np.arange(n) + 0.5
    phi, th = np.arccos(1 - 2 * i / n), np.pi * (1 + 5 ** 0.5) * i
    p = 6.0 * np.stack([np.cos(th) * np.sin(phi), np.cos(phi), np.sin(th) * np.sin(phi)], 1)
    io.write_cloud(d / "shell.ply", io.Cloud(p.astype(np.float32), (-p / 6).astype(np.float32), np.ones((n, 3), np.float32)))
    cli = [sys.executable, str(ROOT / "cli.py")]
    subprocess.run([*cli, "build-bsh", str(d / "shell.ply"), "--out", str(d / "bsh.npz"), "-q"], check=True)
    cs, rs = map(int, a.segments.split("x"))
    m = trimesh.creation.uv_sphere(radius=1.0, count=[rs, cs])
    io.write_mesh(d / "sphere.glb", m.vertices, m.faces, m.vertex_normals, base_color=(0.5, 0.5, 0.5))
    for v in a.variants:
        out = d / ("o" + v.replace(" ", "_").replace("-", ""))
        t0 = time.time()
        subprocess.run([*cli, "relight", "--bsh", str(d / "bsh.npz"), "--object", str(d / "sphere.glb"), "--eye", "0,0.5,3",
                        "--target", "0,0,0", "--size", "64x64", "--brdf", "lambert", "--albedo", "0.5,0.5,0.5",
                        *v.split(), "--out", str(out), "-q"], check=True)
        img = io.read_image(out / "relit.exr")
        x = img[..., :3][img[..., 3] > 0.5] / 0.5
        print(f"{a.segments} [{v or 'defaults'}]: mean {x.mean():.5f} min {x.min():.4f} max {x.max():.4f} "
              f"({time.time() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
