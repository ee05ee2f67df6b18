"""The object in the user's photo (issue 44): relight from the photo's registered camera, the photo as background
pixel for pixel, and the room's change by the object (its shadows, its light) by differential rendering on the
cloud's own geometry.

Camera (:func:`photo_camera`): the pinhole that expose-match registered (exposure.npz ``photo_K``,
``photo_world_to_camera``: OpenCV axes, square pixels, centred principal point), at the photo's size.

Room receivers (:func:`room_surface`): the BSH's leaves splatted from that camera (the cube-map splatter's disc rule,
:func:`pipeline.expansion.splats.view_index`): each pixel's nearest leaf disc; the receiver is the pixel ray's hit
on that disc's plane (its centre's depth where the ray grazes it), its normal the leaf's, turned to the camera.
Pixels that see no leaf keep the photo as it is; without a photo (``--composite``) the background is the leaves
rendered as flat 3D Gaussians (:func:`room_background`: smooth where discs are blotchy), a hole filled with its
nearest covered pixel's.

The change (:func:`pipeline.relight.room_shadow.changed_by_object`, the model the room shadow uses for the room's
leaves): L' = L·E_black/E_empty + ρ·(E_obj − E_black), ρ = L / E_empty capped at the median over the receivers, with
L the pixel's leaf radiance (the cloud: smooth where the photo is noisy), and the photo's pixel P' = P · L'/L,
from three classic walks at each receiver (albedo-1 Lambert): the room alone, the object's surfels black, the
object lit (:func:`pipeline.relight.room_shadow.irradiance_with_and_without`). This is the ratio form of Debevec's
differential rendering (photo + with − without) with the receiver's albedo taken from the capture itself (ρ = L /
E_empty): it needs no albedo estimate, the walk's own errors at a receiver (its neighbours at the horizon) cancel in
E_black / E_empty, and a pixel lit by light the cloud does not hold (a sun patch) is scaled, not brightened by its
sun. Receivers: pixels where the object's bounding sphere may cover ≥ :data:`SHARE` of their cosine-weighted
hemisphere; the others keep the photo (the object changes their light by less than that bound). Shaded adaptively
(:func:`pipeline.relight.adaptive.shade_adaptive`, ε :data:`EPS`): a coarse grid, refined where the change is not
coherent (a shadow's edge), the rest interpolated on the room's G-buffer.

The object: relight's radiance at the pixels whose centre it covers, in the photo's units (÷ α: the cloud is α ×
the photo), over the background with its coverage from :data:`SUPERSAMPLE`² samples a pixel (anti-aliased edges;
an edge pixel whose centre misses the object takes its nearest covered neighbour's colour).

Outputs (:func:`write_composite`): composite.exr (R,G,B,A the beauty with A the object's coverage, and the layers
object.{R,G,B,A} (premultiplied), shadow.{R,G,B} (P'/P: the matte, 1 where unchanged), depth.Z [m], N.{X,Y,Z}
(world normals)), composite.png (the photo's display mapping). Not separated: the object's diffuse and specular
parts (relight gathers them together).

Units: metres, radians, linear radiance in the photo's units.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..camera import Camera
from ..errors import InputError
from ..runtime import get_logger

log = get_logger("relight")

SHARE = 0.01        # room pixels where the object's bounding sphere may cover ≥ this of the cosine-weighted hemisphere
                    # ((R/d)² ≥ SHARE: d ≤ 10 R) are receivers; the others keep the photo
EPS = 0.05          # adaptive shading of the change: refine a block whose corners' P'/P differ by more than this
MIN_STEP = 4        # ... down to a grid of this many pixels (the rest interpolated on the room's G-buffer)
STEP = 8            # the coarse grid of the room receivers [pixels]
SUPERSAMPLE = 4     # the object's coverage: SUPERSAMPLE × SUPERSAMPLE samples a pixel
LIFT = 0.01         # a receiver sits this × its leaf's splat radius above the disc (as the room shadow's)
GAUSS_TANGENT = 0.5 # the background without a photo: a leaf's Gaussian σ [× its spacing] (bench/splats: 0.5 / 0.6 /
                    # 0.8 gave 14.9 / 16.8 / 22.6 % 4×4-block RMS on the shipped photo's view)
GAUSS_ALPHA = 0.05  # ... a pixel of less coverage is a hole, filled from its nearest covered pixel


def photo_camera(K: np.ndarray, world_to_camera: np.ndarray, size: tuple[int, int], where: Any) -> Camera:
    """The registered photo's pinhole as relight's look-at camera: ``K`` 3×3, ``world_to_camera`` 4×4 (OpenCV: x
    right, y down, z forward), ``size`` (W, H) [pixels]. Refuses (``where``: the file named) a camera relight cannot
    draw: non-square pixels or a principal point off the centre by more than half a pixel."""
    K = np.asarray(K, np.float64).reshape(3, 3)
    M = np.asarray(world_to_camera, np.float64).reshape(4, 4)
    W, H = int(size[0]), int(size[1])
    if not np.all(np.isfinite(K)) or not np.all(np.isfinite(M)) or K[1, 1] <= 0:
        raise InputError(where, "the registered camera is not finite")
    if abs(K[0, 0] - K[1, 1]) > 1e-3 * K[1, 1] or abs(K[0, 2] - W / 2) > 0.5 or abs(K[1, 2] - H / 2) > 0.5:
        raise InputError(where, f"the registered camera (fx {K[0, 0]:.2f}, fy {K[1, 1]:.2f}, centre {K[0, 2]:.1f},"
                                f"{K[1, 2]:.1f}) is not a centred square-pixel pinhole for a {W}×{H} photo")
    R, t = M[:3, :3], M[:3, 3]
    eye = -R.T @ t
    fov = math.degrees(2.0 * math.atan((H / 2.0) / K[1, 1]))
    return Camera(eye, eye + R[2], -R[1], fov, (W, H))


def registered(exposure: dict[str, np.ndarray]) -> bool:
    """Whether exposure.npz holds one registered pinhole photo (``photo_K``, ``photo_world_to_camera``)."""
    return "photo_K" in exposure and "photo_world_to_camera" in exposure


def room_surface(centers: np.ndarray, normals: np.ndarray, radii: np.ndarray, cam: Camera) -> dict[str, np.ndarray]:
    """The room seen by ``cam``: the leaf discs (``centers``/``normals`` (L, 3), ``radii`` (L,) [m]) splatted
    (:func:`pipeline.expansion.splats.view_index`). Returns (H, W) ``mask`` and ``index`` (the leaf, −1 none),
    (H, W, 3) float32 ``position`` (the pixel ray on the leaf's plane, lifted :data:`LIFT` × its radius) and
    ``normal`` (the leaf's, facing the camera), (H, W) ``depth`` [m along the ray]."""
    from ..expansion.splats import view_index

    W, H = cam.size
    idx, _ = view_index(centers, radii, cam.view_matrix(), cam.fov_deg, cam.size)
    mask = idx >= 0
    rays = cam.rays().reshape(-1, 3)
    k = idx.reshape(-1)
    hit = np.flatnonzero(k >= 0)
    c = np.asarray(centers, np.float64)[k[hit]]
    n = np.asarray(normals, np.float64)[k[hit]]
    r = np.asarray(radii, np.float64)[k[hit]]
    d = rays[hit]
    eye = np.asarray(cam.eye, np.float64)
    cos = np.einsum("ij,ij->i", d, n)
    n = np.where(cos[:, None] > 0, -n, n)                      # the side the camera sees
    cos = -np.abs(cos)
    along = np.einsum("ij,ij->i", c - eye, d)                   # the centre's depth along the ray
    tp = np.einsum("ij,ij->i", c - eye, n) / np.where(cos < -1e-3, cos, -1.0)
    ok = (cos < -0.1) & (np.abs(tp - along) <= 2.0 * r / np.maximum(-cos, 1e-3))
    t = np.where(ok, tp, along)
    pos = np.zeros((H * W, 3))
    nrm = np.zeros((H * W, 3))
    dep = np.zeros(H * W)
    pos[hit] = eye + t[:, None] * d + LIFT * r[:, None] * n
    nrm[hit] = n
    dep[hit] = t
    return {"mask": mask, "index": idx, "position": pos.reshape(H, W, 3).astype(np.float32),
            "normal": nrm.reshape(H, W, 3).astype(np.float32), "depth": dep.reshape(H, W).astype(np.float32)}


def near_pixels(surface: dict[str, np.ndarray], center: np.ndarray, radius: float, share: float = SHARE) -> np.ndarray:
    """(H, W) bool: room pixels where the object's bounding sphere (``center``, ``radius`` [m]) may cover ≥ ``share``
    of the cosine-weighted hemisphere and is not wholly below the receiver's plane (the room shadow's rule,
    :func:`pipeline.relight.room_shadow.near_leaves`)."""
    from .room_shadow import near_leaves

    m = surface["mask"].reshape(-1)
    sel = near_leaves(surface["position"].reshape(-1, 3), surface["normal"].reshape(-1, 3), m,
                      np.asarray(center, np.float64), radius, share)
    out = np.zeros(m.shape, bool)
    out[sel] = True
    return out.reshape(surface["mask"].shape)


def coverage(ctx: Any, parts: list[dict[str, Any]], cam: Camera, ss: int = SUPERSAMPLE) -> np.ndarray:
    """(H, W) float32 in [0, 1]: the share of ``ss`` × ``ss`` samples a pixel that the object covers (its
    G-buffer rasterised at ``ss`` × the size)."""
    from dataclasses import replace

    from .gbuffer import render_gbuffer

    W, H = cam.size
    big = render_gbuffer(ctx, parts, replace(cam, size=(W * ss, H * ss)))["mask"]
    return big.reshape(H, ss, W, ss).mean(axis=(1, 3)).astype(np.float32)


def room_background(ctx: Any, centers: np.ndarray, normals: np.ndarray, colors: np.ndarray, cam: Camera) -> np.ndarray:
    """The room's picture from ``cam`` without a photo: the BSH's leaves as flat 3D Gaussians
    (:func:`pipeline.expansion.gaussians.splats_on_surface`: σ = :data:`GAUSS_TANGENT` × each leaf's spacing,
    :func:`~pipeline.expansion.gaussians.surface_spacing`, along its plane) rendered on GL, un-premultiplied where α > :data:`GAUSS_ALPHA`,
    the rest filled from the nearest covered pixel. (H, W, 3) float32, row 0 at the top, the leaves' units.
    Measured on the shipped photo's view against the path trace (docs/bench/splats.md): 4×4-block RMS 14.9 % for
    the cloud's points as Gaussians against 57 % as discs."""
    from ..expansion import gaussians as G

    W, H = cam.size
    c = np.asarray(centers, np.float64)
    s = G.splats_on_surface(c, np.asarray(normals, np.float64), G.surface_spacing(c), tangent=GAUSS_TANGENT)
    img, _ = G.render_gaussians(s["pos"], s["sigma"], s["quat"], s["opacity"], colors, cam.view_matrix(),
                                G.focal_px(cam.fov_deg, H), cam.size, ctx=ctx)
    have = img[..., 3] > GAUSS_ALPHA
    rgb = np.where(have[..., None], img[..., :3] / np.maximum(img[..., 3:4], 1e-6), 0.0).astype(np.float32)
    return nearest_fill(rgb, have, np.ones_like(have))


def nearest_fill(rgb: np.ndarray, have: np.ndarray, need: np.ndarray) -> np.ndarray:
    """``rgb`` (H, W, 3) with the pixels ``need`` (H, W) bool given the colour of their nearest ``have`` pixel: the
    object's edge pixels whose centre it misses, the room's pixels no leaf disc covers (its holes)."""
    from scipy.ndimage import distance_transform_edt

    need = need & ~have
    if not need.any() or not have.any():
        return rgb
    _, (iy, ix) = distance_transform_edt(~have, return_indices=True)
    out = rgb.copy()
    out[need] = rgb[iy[need], ix[need]]
    return out


def differential(ctx: Any, surface: dict[str, np.ndarray], receive: np.ndarray, radiance: np.ndarray, cam: Camera,
                 room: np.ndarray, room_splat: np.ndarray, merged: np.ndarray, merged_splat: np.ndarray, params: Any,
                 emitters: np.ndarray | None, object_dirs: np.ndarray | None, t: Any) -> tuple[np.ndarray, dict]:
    """P'/P (H, W, 3) float32 (1 off ``receive``): the room's change by the object at the room receivers
    ``receive`` (H, W) bool of ``surface`` (:func:`room_surface`), shaded adaptively (module docstring), with ρ from
    ``radiance`` (H, W, 3): the room leaf's radiance at each pixel, the cloud's units (not the photo's pixel, whose
    noise would enter the ratio). Returns (the ratio, stats)."""
    from ..gather.base import Receivers
    from .adaptive import shade_adaptive
    from .room_shadow import changed_by_object, irradiance_with_and_without

    H, W = receive.shape
    pos = surface["position"].reshape(-1, 3)
    nrm = surface["normal"].reshape(-1, 3)
    eye = np.asarray(cam.eye, np.float32)
    px = radiance.reshape(-1, 3).astype(np.float64)
    cap: list[Any] = []
    walked = [0]

    def shade(idx: np.ndarray) -> np.ndarray:
        n = np.ascontiguousarray(nrm[idx])
        v = eye[None] - pos[idx]
        v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-30)
        recv = Receivers(np.ascontiguousarray(pos[idx]), n, np.ascontiguousarray(v, np.float32),
                         np.ones((len(idx), 3), np.float32), np.zeros(len(idx), np.float32),
                         np.ones(len(idx), np.float32), n)
        e_room, e_black, e_obj = irradiance_with_and_without(ctx, recv, room, room_splat, merged, merged_splat,
                                                             params, emitters, object_dirs)
        L = px[idx]
        if not cap:   # ρ's cap: the median over the first (coarse, image-wide) level's lit receivers
            lit = (e_room > 1e-12 * max(float(e_room.max()), 1e-30)).all(1)
            rho = L[lit] / np.maximum(e_room[lit], 1e-300)
            cap.append(np.median(rho, axis=0) if len(rho) else np.zeros(3))
        walked[0] += len(idx)
        return changed_by_object(L, e_room, e_black, e_obj, cap[0]).astype(np.float32)

    ratio = np.ones((H, W, 3), np.float32)
    stats: dict[str, Any] = {"receivers": int(receive.sum()), "share": SHARE, "eps": EPS, "step": STEP,
                             "min_step": MIN_STEP}
    if receive.any():
        with t.step("differential"):
            img, ad = shade_adaptive(shade, receive, surface["normal"], surface["position"], EPS, step=STEP,
                                     min_step=MIN_STEP)
        ratio[receive] = img[receive]
        stats.update(walked=walked[0], levels=ad["levels"], rho_cap=[round(float(x), 6) for x in cap[0]])
    lum = ratio[receive] @ np.array([0.2126, 0.7152, 0.0722], np.float32) if receive.any() else np.ones(1)
    stats.update(ratio_min=round(float(lum.min()), 4), ratio_mean=round(float(lum.mean()), 4),
                 darker_5pct=int(np.count_nonzero(lum < 0.95)), brighter_5pct=int(np.count_nonzero(lum > 1.05)))
    return ratio, stats


def composite_layers(photo: np.ndarray, ratio: np.ndarray, obj: np.ndarray, mask: np.ndarray, cover: np.ndarray,
                     surface: dict[str, np.ndarray], obj_depth: np.ndarray, obj_normal: np.ndarray) -> dict[str, np.ndarray]:
    """The named layers of composite.exr (module docstring): the photo × ``ratio`` under the object ``obj`` (H, W, 3,
    the photo's units, valid where ``mask``) with coverage ``cover``."""
    a = cover[..., None].astype(np.float32)
    o = nearest_fill(obj.astype(np.float32), mask, cover > 0) * a               # premultiplied
    back = photo.astype(np.float32) * ratio
    beauty = o + back * (1.0 - a)
    depth = np.where(cover > 0, obj_depth, surface["depth"]).astype(np.float32)
    normal = np.where((cover > 0)[..., None], obj_normal, surface["normal"]).astype(np.float32)
    return {"R": beauty[..., 0], "G": beauty[..., 1], "B": beauty[..., 2], "A": a[..., 0],
            "object.R": o[..., 0], "object.G": o[..., 1], "object.B": o[..., 2], "object.A": a[..., 0],
            "shadow.R": ratio[..., 0], "shadow.G": ratio[..., 1], "shadow.B": ratio[..., 2], "depth.Z": depth,
            "N.X": normal[..., 0], "N.Y": normal[..., 1], "N.Z": normal[..., 2]}


def write_composite(out_dir: Any, layers: dict[str, np.ndarray], photo: np.ndarray, key: float | None = None,
                    hdr: bool = False) -> None:
    """composite.exr (every layer, float32, named as Nuke and OIIO read them) and composite.png (the beauty, with
    the tone mapping's key set on the photo alone, so the plate looks as it does without the object); with ``hdr``
    composite.hdr (Radiance RGBE: the beauty)."""
    from pathlib import Path

    from .. import display, io

    out = Path(out_dir)
    names = list(layers)
    io.write_image(out / "composite.exr", np.stack([layers[k] for k in names], axis=-1), channels=names)
    beauty = np.stack([layers["R"], layers["G"], layers["B"]], axis=-1)
    exposure, _ = display.auto_exposure(photo, None, key)
    io.write_png(out / "composite.png", display.tonemap(beauty, key=key, exposure=exposure))
    if hdr:
        io.write_image(out / "composite.hdr", beauty)
