"""Gaussian splats as the room's picture (issue 47): a splat room made from the shipped exact cloud, rendered from
the photo's true camera, against the path-traced view without the object — beside the disc splats that draw the
cloud today — then the import's colours through a 3DGS file, and the renderer's speed.

    .venv/bin/python -m bench.splats.splat_room [SCENE] [--out bench/splats/splat_room.csv]

Rows (``splat_room.csv``):

* ``kind = background``: ``gaussians σ=t`` — :func:`pipeline.expansion.gaussians.splats_on_surface` on
  ``cloud_gt.ply`` (one flat Gaussian a point, σ = t × its spacing (:func:`surface_spacing`: the mean of its 8 nearest distances, itself included) along
  its tangent plane, 0.05 × that along its normal, opacity 0.95), coloured with the exact radiance × the photo's
  scale k, rendered by :func:`render_gaussians` and un-premultiplied where α > 0.05 (black elsewhere: holes
  counted); ``discs`` — :func:`pipeline.expansion.splats.render_view`; then the BSH's leaves (build-bsh's defaults)
  as relight ``--composite`` draws them without a photo — as Gaussians (:func:`pipeline.relight.composite.room_background`)
  and as discs with holes filled (before).
  Against ``truth/photo_without.exr`` (Mitsuba, 1024 paths a pixel): mean ratio and relative RMS of 2×2 / 4×4 / 8×8
  block means with the truth's own noise on each scale.
* ``kind = import``: the splat room written as a 3DGS ``.ply`` (f_dc from the LDR cloud's sRGB colours, ln σ,
  quaternions, logit opacity, 45 f_rest terms) and read back by ``import``'s reader
  (:func:`pipeline.io.read_gaussian_splats`; written by :func:`pipeline.io.write_gaussian_splats`): the largest and the mean relative colour error against the LDR
  cloud (colours above 0.02), normals' largest angle [deg], splats kept.
* ``kind = speed``: ``render_gaussians`` on N splats at 512×384, seconds (whole call: sort, upload, draw, read
  back) and millions of splats a second, for the room and 1 M random splats of 1 cm and 3 mm.

One side-by-side PNG (``splat_room.png``, its labels in ``splat_room.txt``): truth | the points as Gaussians (the
first σ) | the leaves as Gaussians | the leaves as discs | the points as discs | |leaves as Gaussians − truth| × 4.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent

from bench.benchlib import ROOT, write_rows  # noqa: E402

from pipeline import display, gl, io  # noqa: E402
from pipeline.color import srgb_encode  # noqa: E402
from pipeline.expansion import gaussians as G  # noqa: E402
from pipeline.expansion.splats import knn_splat_radii, render_view  # noqa: E402
from pipeline.metrics import compare_to_reference  # noqa: E402



def errors(img: np.ndarray, ref: np.ndarray, var: np.ndarray) -> dict:
    """Mean ratio and 2×2 / 4×4 / 8×8 block RMS (with the reference's noise) over the whole image."""
    out = {"mean_ratio": round(float(img.sum() / ref.sum()), 4)}
    mask = np.ones(ref.shape[:2], bool)
    for b in (2, 4, 8):
        c = compare_to_reference(img, ref, mask, ref_var=var, block=b)
        out[f"rms_{b}x{b}"] = round(c["rms_block"], 4)
        out[f"noise_{b}x{b}"] = round(c["ref_noise_block"], 4)
    return out


def _leaf_discs(cp, nd, b, leaf, cam) -> np.ndarray:
    """The --composite background before the Gaussians: each pixel's nearest leaf disc, holes nearest-filled."""
    surf = cp.room_surface(nd["center"][leaf], b["normal"][leaf], b["splat_radius"][leaf], cam)
    W, H = cam.size
    seen = np.zeros((H, W, 3), np.float32)
    seen[surf["mask"]] = nd["color"][leaf][surf["index"][surf["mask"]]]
    return cp.nearest_fill(seen, surf["mask"], np.ones_like(surf["mask"]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", nargs="?", type=Path, default=Path("data_samples"))
    ap.add_argument("--tangent", default="0.5,0.6,0.8", help="σ along the surface as multiples of the spacing")
    ap.add_argument("--out", type=Path, default=HERE / "splat_room.csv")
    ap.add_argument("--bsh", type=Path, default=None, help="the room's BSH (default: build-bsh of cloud_gt.ply)")
    ap.add_argument("--write-3dgs", type=Path, default=None,
                    help="only write the splat room made from the LDR cloud (σ = 0.5 × spacing) as a 3DGS .ply here and stop "
                         "(the input of `pcrelight run --cloud` in docs/bench/splats.md)")
    a = ap.parse_args()
    root = a.scene
    gt, ldr = io.read_cloud(root / "cloud_gt.ply"), io.read_cloud(root / "cloud_ldr.ply")
    if a.write_3dgs is not None:
        lp = np.asarray(ldr.points, np.float64)
        s = G.splats_on_surface(lp, np.asarray(ldr.normals, np.float64), G.surface_spacing(lp), tangent=0.5)
        io.write_gaussian_splats(a.write_3dgs, s["pos"], s["sigma"], s["quat"], s["opacity"],
                                 srgb_encode(np.clip(np.asarray(ldr.colors, np.float64), 0, 1)))
        print(f"wrote {a.write_3dgs}: {len(lp)} splats")
        return
    pts, rad, nrm = (np.asarray(x, np.float64) for x in (gt.points, gt.colors, gt.normals))
    tr = np.load(root / "truth" / "truth.npz")
    K, M = tr["photo_K"], tr["photo_world_to_camera"]
    w, h = (int(x) for x in tr["photo_size"])
    if abs(K[0, 0] - K[1, 1]) > 1e-6 * K[0, 0] or abs(K[0, 2] - w / 2) > 1e-6 or abs(K[1, 2] - h / 2) > 1e-6:
        raise SystemExit("the photo's K is not square and centred: the renderer's pinhole is")
    k = float(json.loads((root / "scene.json").read_text())["photo_scale_k"])
    V = np.diag([1.0, -1.0, -1.0, 1.0]) @ M                      # OpenCV → OpenGL eye space
    ref = io.read_image(root / "truth" / "photo_without.exr")[..., :3]
    var = io.read_image(root / "truth" / "photo_without_var.exr")[..., :3]
    spacing = G.surface_spacing(pts)
    ctx = gl.create_context()
    gl.bind_dummy_framebuffer(ctx)
    rows, panels = [], []
    for t in (float(x) for x in a.tangent.split(",")):
        s = G.splats_on_surface(pts, nrm, spacing, tangent=t)
        t0 = time.perf_counter()
        img, st = G.render_gaussians(s["pos"], s["sigma"], s["quat"], s["opacity"], k * rad, V, float(K[0, 0]), (w, h),
                                     ctx=ctx)
        dt = time.perf_counter() - t0
        cov = img[..., 3] > 0.05
        un = np.where(cov[..., None], img[..., :3] / np.maximum(img[..., 3:4], 1e-6), 0.0).astype(np.float32)
        rows.append({"kind": "background", "renderer": f"gaussians σ={t:g}", "splats": len(pts), "seconds": round(dt, 3),
                     "holes": int((~cov).sum()), "cut": st["cut"], **errors(un, ref, var)})
        print(rows[-1], flush=True)
        if not panels:
            panels = [ref.astype(np.float32), un]
    t0 = time.perf_counter()
    rv = render_view(pts, k * rad, knn_splat_radii(pts), V, float(np.degrees(2 * np.arctan(h / 2 / K[1, 1]))), (w, h))
    dt = time.perf_counter() - t0
    rows.append({"kind": "background", "renderer": "discs (render_view)", "splats": len(pts), "seconds": round(dt, 3),
                 "holes": int((rv[..., 3] == 0).sum()), "cut": 0, **errors(rv[..., :3], ref, var)})
    print(rows[-1], flush=True)
    # the BSH's leaves (what relight --composite draws without a photo): as Gaussians, and as discs (before)
    from bench.benchlib import truth_bsh
    from pipeline.bsh.format import LEAF, as_nodes
    from pipeline.relight import composite as cp

    b = io.read_npz(truth_bsh(root, a.bsh, ROOT / "bench" / "_work" / "splats"), "pcrelight.bsh/1",
                    keys=("nodes", "splat_radius", "normal"))
    nd = as_nodes(b["nodes"])
    leaf = np.flatnonzero((nd["right"] == LEAF) & (np.linalg.norm(nd["color"], axis=1) > 0))
    cam = cp.photo_camera(K, M, (w, h), root / "truth" / "truth.npz")
    for name, draw in (("BSH leaves as Gaussians (relight --composite)",
                        lambda: cp.room_background(ctx, nd["center"][leaf], b["normal"][leaf], nd["color"][leaf], cam)),
                       ("BSH leaves as discs, holes filled (before)", lambda: _leaf_discs(cp, nd, b, leaf, cam))):
        t0 = time.perf_counter()
        img = k * draw()
        dt = time.perf_counter() - t0
        panels.append(img.astype(np.float32))
        rows.append({"kind": "background", "renderer": name, "splats": len(leaf), "seconds": round(dt, 3), "holes": 0,
                     "cut": 0, **errors(img, ref, var)})
        print(rows[-1], flush=True)
    err = np.abs(panels[2] - ref).mean(2, keepdims=True) * 4
    panels += [rv[..., :3].astype(np.float32), np.repeat(err, 3, 2).astype(np.float32)]
    io.write_png(a.out.with_suffix(".png"), display.side_by_side(panels, exposure_from=0))
    a.out.with_suffix(".txt").write_text("left to right: truth photo_without, the points as Gaussians (σ = the first), "
                                         "the BSH leaves as Gaussians (relight --composite), the leaves as discs "
                                         "(before), the points as discs (render_view), |leaves as Gaussians − truth| × 4 "
                                         "(one exposure)\n")
    # the import's colours through a 3DGS file
    s = G.splats_on_surface(pts, np.asarray(ldr.normals, np.float64), spacing, tangent=0.5)
    lin = np.clip(np.asarray(ldr.colors, np.float64), 0, 1)
    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "room_3dgs.ply"
        io.write_gaussian_splats(f, s["pos"], s["sigma"], s["quat"], s["opacity"], srgb_encode(lin))
        t0 = time.perf_counter()
        scan = io.read_gaussian_splats(f)
        dt = time.perf_counter() - t0
    bright = lin > 0.02
    rel = np.abs(scan.colors.astype(np.float64) - lin)[bright] / lin[bright]
    ang = np.degrees(np.arccos(np.clip(np.abs(np.sum(scan.normals * np.asarray(ldr.normals), 1)), -1, 1)))
    rows.append({"kind": "import", "renderer": "read_gaussian_splats", "splats": len(scan.points), "seconds": round(dt, 3),
                 "colour_rel_max": round(float(rel.max()), 5), "colour_rel_mean": round(float(rel.mean()), 6),
                 "normal_deg_max": round(float(ang.max()), 4)})
    print(rows[-1], flush=True)
    # speed
    cases = [("room", s["pos"], s["sigma"], s["quat"])]
    rng = np.random.default_rng(0)
    for sig in (0.01, 0.003):
        n = 1_000_000
        cases.append((f"1M random σ={sig}", rng.uniform(-2, 2, (n, 3)), np.full((n, 3), sig), np.tile([1.0, 0, 0, 0], (n, 1))))
    from pipeline.camera import Camera
    cam = Camera(np.array([0.3, 0.5, 4.0]), np.zeros(3), np.array([0, 1.0, 0]), 50.0, (512, 384))
    for name, p, sg, q in cases:
        VV, ff = (V, float(K[0, 0]) * 384 / h) if name == "room" else (cam.view_matrix(), G.focal_px(50.0, 384))
        best = None
        for _ in range(3):
            t0 = time.perf_counter()
            G.render_gaussians(p, sg, q, np.full(len(p), 0.9), np.ones((len(p), 3)), VV, ff, (512, 384), ctx=ctx)
            dt = time.perf_counter() - t0
            best = dt if best is None else min(best, dt)
        rows.append({"kind": "speed", "renderer": name, "splats": len(p), "seconds": round(best, 3),
                     "msplats_per_s": round(len(p) / best / 1e6, 3)})
        print(rows[-1], flush=True)
    cols = sorted({k for r in rows for k in r}, key=lambda c: [k for r in rows for k in r].index(c))
    write_rows(a.out, [{c: r.get(c, "") for c in cols} for r in rows])


if __name__ == "__main__":
    main()
