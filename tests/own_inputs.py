"""Small inputs for ``pcrelight run --cloud … --photo … --object …`` (tests/test_run_own.py, make demo-own's check):
a closed box room scanned as points (uchar sRGB colours, no normals, as a phone scan), a cabinet standing in it,
a bright ceiling lamp (overexposed in the scan), an HDR photo of it splatted from a camera inside, and a
small glTF object."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline import io
from pipeline.color import srgb_encode

ROOM = (np.array([-2.0, 0.0, -2.5]), np.array([2.0, 2.5, 2.5]))      # metres, +Y up
CABINET = (np.array([-1.9, 0.0, -2.4]), np.array([-0.9, 1.2, -1.6]))  # stands on the floor, in a corner
LAMP = (np.array([-0.4, 2.5, -0.4]), np.array([0.4, 2.5, 0.4]))       # a square on the ceiling
LAMP_RADIANCE = 30.0                                                  # HDR value of the lamp (walls ≤ ~0.8)


def _box_surface(lo: np.ndarray, hi: np.ndarray, spacing: float, rng: np.random.Generator, inward: bool):
    pts, nrm = [], []
    for a in range(3):
        for side, val in ((-1.0, lo[a]), (1.0, hi[a])):
            u, v = [b for b in range(3) if b != a]
            nu = max(2, int((hi[u] - lo[u]) / spacing))
            nv = max(2, int((hi[v] - lo[v]) / spacing))
            g = np.stack(np.meshgrid((np.arange(nu) + 0.5) / nu, (np.arange(nv) + 0.5) / nv, indexing="ij"), -1).reshape(-1, 2)
            g = g + rng.uniform(-0.3, 0.3, g.shape) / [nu, nv]
            p = np.zeros((len(g), 3))
            p[:, a] = val
            p[:, u] = lo[u] + g[:, 0] * (hi[u] - lo[u])
            p[:, v] = lo[v] + g[:, 1] * (hi[v] - lo[v])
            n = np.zeros((len(g), 3))
            n[:, a] = -side if inward else side
            pts.append(p)
            nrm.append(n)
    return np.concatenate(pts), np.concatenate(nrm)


def box_room(spacing: float = 0.08, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points, normals, HDR linear colours) of the room, metres, +Y up."""
    rng = np.random.default_rng(seed)
    p, n = _box_surface(*ROOM, spacing, rng, inward=True)
    q, m = _box_surface(*CABINET, spacing, rng, inward=False)
    keep = q[:, 1] > 1e-6                              # its bottom face is on the floor, unseen
    p, n = np.concatenate([p, q[keep]]), np.concatenate([n, m[keep]])
    c = np.empty_like(p)
    c[:] = (0.55, 0.5, 0.45)                           # walls
    c[p[:, 1] < 1e-6] = (0.35, 0.25, 0.2)              # floor
    c[p[:, 0] > 2.0 - 1e-6] = (0.2, 0.35, 0.6)         # a blue wall
    c[len(p) - int(keep.sum()):] = (0.6, 0.15, 0.1)    # the cabinet
    lamp = np.all((p >= LAMP[0] - 1e-6) & (p <= LAMP[1] + 1e-6), axis=1)
    c[lamp] = LAMP_RADIANCE
    # a phone scan sees the ceiling from afar: half as many points there as on the floor (the floor decides up)
    sparse = (p[:, 1] > ROOM[1][1] - 1e-6) & ~lamp & (rng.random(len(p)) < 0.5)
    return p[~sparse], n[~sparse], c[~sparse]


def write_scan(path: Path, points: np.ndarray, colors_hdr: np.ndarray) -> None:
    """The scan as a phone gives it: 8-bit sRGB colours (LDR: clipped at 1), no normals."""
    ldr = np.clip(colors_hdr, 0.0, 1.0)
    io.write_cloud(path, io.Cloud(points.astype(np.float32), np.zeros_like(points, np.float32), ldr.astype(np.float32)),
                   uchar_colors=True)
    _drop_normals(path)


def _drop_normals(path: Path) -> None:
    from plyfile import PlyData, PlyElement

    v = PlyData.read(str(path))["vertex"].data
    keep = [n for n in v.dtype.names if n not in ("nx", "ny", "nz")]
    out = np.empty(len(v), dtype=[(n, v.dtype[n]) for n in keep])
    for n in keep:
        out[n] = v[n]
    PlyData([PlyElement.describe(out, "vertex")], text=False, byte_order="<").write(str(path))


def photo(points: np.ndarray, colors_hdr: np.ndarray, size: tuple[int, int] = (96, 64)) -> np.ndarray:
    """An HDR photo of the room (linear, RGB) from a camera inside it that sees the lamp."""
    from pipeline.relight.gbuffer import Camera
    from pipeline.expansion.splats import knn_splat_radii, render_view

    cam = Camera(np.array([1.5, 1.2, 2.0]), np.array([-0.5, 1.6, -1.0]), np.array([0.0, 1.0, 0.0]), 70.0, size)
    img = render_view(points, colors_hdr, knn_splat_radii(points), cam.view_matrix(), cam.fov_deg, size)
    return np.ascontiguousarray(img[..., :3])


def write_object(path: Path) -> None:
    """A 0.5 m cube-ish rounded object (an icosphere squashed), glTF, grey Lambert."""
    from pipeline.scene.geometry import object_sphere

    V, F, N = object_sphere(2)
    V = V * np.array([0.25, 0.3, 0.25])
    io.write_mesh(path, V, F, N, base_color=(0.8, 0.8, 0.8), metallic=0.0, roughness=1.0)


def write_inputs(folder: Path) -> dict[str, Path]:
    """scan.ply (uchar, no normals), photo.exr, object.glb in ``folder``; returns their paths."""
    folder.mkdir(parents=True, exist_ok=True)
    p, _, c = box_room()
    write_scan(folder / "scan.ply", p, c)
    # the photo's values as Radiance RGBE holds them (8-bit mantissas: ~1 % steps), so that a .hdr copy of
    # photo.exr is the same photo, not a requantised one
    io.write_image(folder / "photo_rgbe.hdr", photo(p, c))
    io.write_image(folder / "photo.exr", io.read_image(folder / "photo_rgbe.hdr"))
    write_object(folder / "object.glb")
    return {"cloud": folder / "scan.ply", "photo": folder / "photo.exr", "object": folder / "object.glb"}
