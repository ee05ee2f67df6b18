"""Make data_samples/own/ (``make demo-own``'s capture) from the shipped ``small`` scene (data_samples/,
make-scene seed 0), in the forms a user brings them: the scan as a phone app exports it (a random 60 000 of
the 200 000 LDR cloud points, centimetres, Z up, 8-bit sRGB colours, no normals), the photo as Radiance .hdr
(RGBE) and the object as a renamed glTF binary. Made here, from data this repository generates: same licence
as the repository. Run from the repository root: ``python data_samples/own/convert.py``; deterministic."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

from pipeline import io
from pipeline.color import srgb_encode

SRC, DST = Path("data_samples"), Path("data_samples/own")
N = 60_000


def main() -> None:
    c = io.read_cloud(SRC / "cloud_ldr.ply")
    idx = np.sort(np.random.default_rng(0).choice(len(c), N, replace=False))
    p = c.points[idx].astype(np.float64) * 100.0                                  # metres → centimetres
    zup = np.stack([p[:, 0], -p[:, 2], p[:, 1]], axis=1)                          # +Y up → +Z up (x, −z, y)
    rgb = np.round(srgb_encode(np.clip(c.colors[idx], 0, 1)) * 255).astype(np.uint8)
    v = np.empty(N, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for k, name in enumerate("xyz"):
        v[name] = zup[:, k]
    v["red"], v["green"], v["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    PlyData([PlyElement.describe(v, "vertex")], text=False, byte_order="<").write(str(DST / "atrium_scan.ply"))
    io.write_image(DST / "atrium.hdr", io.read_image(SRC / "photo.exr")[..., :3])
    shutil.copyfile(SRC / "object.glb", DST / "knot.glb")


if __name__ == "__main__":
    main()
