"""Environment-map image-based lighting (papers 002 and 004; the baseline of paper 000 Fig. 14).

The cloud is seen from **one point**, the object's centre (``GatherParams.object_center``; without it the
centre of the first receivers' bounding box): a cube map of the BSH's leaves is splatted by
:func:`pipeline.expansion.splats.render_cube_map` (render-cubemaps' splatter: numba, depth-tested discs, back faces culled;
radii: :func:`capture_points`) and bsh.npz's emitters are added as eq9.comp.glsl adds them (:func:`add_emitters`),
then

* **diffuse**: the irradiance E(n) = Σ L Ω max(0, n·ω) over the cube map (area-averaged to
  :data:`IRRADIANCE_CUBE` texels a face), stored as a lat-long map of :data:`IRRADIANCE_SIZE` read bilinearly
  (002 §3.1 uses 32×16: on one bright texel 2–3× the error of 64×32, 7.6 % / 1.0 % of the peak max / RMS
  against 2.4 % / 0.4 %) — or (``diffuse="sh"``) the 3-band spherical-harmonics irradiance of Ramamoorthi & Hanrahan
  2001 baked into a 64×32 map. Measured here (:func:`diffuse_error`, bench/README.md "envmap"): the map is
  the more accurate on the shipped room (its small bright lamps and sun are what 9 coefficients ring on);
* **specular**: the split sum (Karis 2013): a prefiltered radiance cube whose level i holds the GGX lobe of
  roughness i / (levels − 1), made by a GLSL pass on the gather's context (``envmap.prefilter.comp.glsl``:
  GGX importance sampling with PDF-based mip filtering, Colbert & Křivánek 2007), read at the mirror
  direction with the level from the roughness (002 §3.2), times a (n·v, roughness) table of the BRDF's
  F0 scale and bias (``envmap.lut.comp.glsl``, from brdf.glsl — the BRDFs are shared, not copied).

What it leaves out, by construction: **no occlusion or parallax by the room near the object** — every
receiver sees the room as seen from the centre, so a wall close to the object lights both sides of it
alike and a receiver facing the wall sees it at the wrong distance (bench/gatherers/bench_envmap_wall.py measures
it); **no self-shadowing** (the object is not in its environment: relight's ``--surfels`` auto is off for
this method and an explicit count is refused). Adaptive shading (``--adaptive``) works as for the others.

Units: metres, radians, radiance in linear RGB float32 (W·sr⁻¹·m⁻² up to a common scale).
"""

from __future__ import annotations

import math
import time
from typing import Any, Optional

import numpy as np

from ..bsh.format import GATHER_BINDINGS, IMAGE_BINDINGS, LEAF, as_nodes, decode_cones, glsl_defines
from ..runtime import Timings, check_interrupt, get_logger
from .base import BRDF_IDS, MASK_IDS, GatherParams, Receivers

log = get_logger("relight")

CUBE_SIZE = 128                 # capture face side [texels]; level 0 of the prefiltered map (0.7° a texel)
ROUGH_LEVELS = 6                # prefiltered levels 128² … 4²: roughness 0, 0.2, …, 1
PREFILTER_SAMPLES = 256         # GGX samples a prefiltered texel
LUT_SIZE = 32                   # (n·v, roughness) table side
LUT_SAMPLES = 1024              # samples a table entry
IRRADIANCE_CUBE = 64            # face side the irradiance convolution runs at (area-averaged capture)
IRRADIANCE_SIZE = (64, 32)      # lat-long irradiance map (W, H); 002 §3.1's 32×16 has 2–3× its error (diffuse_error)
SH_BAKE_SIZE = (64, 32)         # lat-long map the SH irradiance is baked into (diffuse="sh")
DIFFUSE_MODES = ("map", "sh")
DISPATCH = 65536 * 4            # receivers a dispatch
GL_RGBA32F = 0x8814
GL_TEXTURE_CUBE_MAP_SEAMLESS = 0x884F


# --------------------------------------------------------------------------- cube-map geometry (numpy)
def cube_texel_dirs(size: int) -> tuple[np.ndarray, np.ndarray]:
    """(unit direction (6, S, S, 3), solid angle (6, S, S) [sr]) of every texel of a cube map laid out as
    :func:`pipeline.camera.cube_cameras` lays it out (face f, row = t, column = s; OpenGL cube-map
    convention). Solid angles exact (ΣΩ = 4π): the area-element integral of the face plane."""
    from ..camera import face_rotations

    e = np.linspace(-1.0, 1.0, size + 1)
    c = (e[:-1] + e[1:]) / 2
    X, Y = np.meshgrid(c, c)                       # X along columns (camera x), Y along rows (camera y)
    cam = np.stack([X, Y, -np.ones_like(X)], -1)   # camera looks down −z
    rot = face_rotations()                         # world→camera rows
    d = np.einsum("fji,hwj->fhwi", rot, cam)      # Rᵀ c
    d /= np.linalg.norm(d, axis=-1, keepdims=True)

    def f(x, y):
        return np.arctan2(x * y, np.sqrt(x * x + y * y + 1.0))

    x0, x1 = np.meshgrid(e[:-1], e[:-1])[0], np.meshgrid(e[1:], e[1:])[0]
    y0, y1 = np.meshgrid(e[:-1], e[:-1])[1], np.meshgrid(e[1:], e[1:])[1]
    om = f(x1, y1) - f(x0, y1) - f(x1, y0) + f(x0, y0)
    return d, np.broadcast_to(om, (6, size, size)).copy()


def area_downsample(rgb: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A (6, S, S, 3) radiance cube map averaged over k×k texel blocks (solid-angle weighted) to (6, s, s, 3),
    with the coarse texels' directions and solid angles (:func:`cube_texel_dirs`); s = ``size`` divides S."""
    S = rgb.shape[1]
    k = S // size
    if k * size != S:
        raise ValueError(f"cube side {S} is not a multiple of {size}")
    _, om = cube_texel_dirs(S)
    w = (rgb * om[..., None]).reshape(6, size, k, size, k, 3).sum((2, 4))
    d, om2 = cube_texel_dirs(size)
    return w / om2[..., None], d, om2


def latlong_dirs(w: int, h: int) -> np.ndarray:
    """(h, w, 3) unit directions at the texel centres of a lat-long map: θ = (i + ½)/h · π from +Y (row i),
    φ = (j + ½)/w · 2π − π (column j), direction (sin θ cos φ, cos θ, sin θ sin φ) — the shader's lookup."""
    th = (np.arange(h) + 0.5) / h * np.pi
    ph = (np.arange(w) + 0.5) / w * 2 * np.pi - np.pi
    T, P = np.meshgrid(th, ph, indexing="ij")
    return np.stack([np.sin(T) * np.cos(P), np.cos(T), np.sin(T) * np.sin(P)], -1)


def irradiance_exact(rgb: np.ndarray, normals: np.ndarray, chunk: int = 256) -> np.ndarray:
    """E(n) = Σ_texels L Ω max(0, n·ω) (K, 3) over a (6, S, S, 3) radiance cube map at its own resolution."""
    d, om = cube_texel_dirs(rgb.shape[1])
    d = d.reshape(-1, 3)
    lw = (rgb.reshape(-1, 3) * om.reshape(-1, 1)).astype(np.float64)
    n = np.asarray(normals, np.float64).reshape(-1, 3)
    out = np.empty((len(n), 3))
    for a in range(0, len(n), chunk):
        out[a:a + chunk] = np.maximum(n[a:a + chunk] @ d.T, 0.0) @ lw
    return out


def irradiance_latlong(rgb: np.ndarray, size: tuple[int, int] = IRRADIANCE_SIZE,
                       cube: int = IRRADIANCE_CUBE) -> np.ndarray:
    """(h, w, 3) float32 irradiance map: E at the lat-long texel centres, from the cube map area-averaged to
    ``cube`` texels a face (the clamped cosine is smooth on that scale)."""
    w, h = size
    lo, d, om = area_downsample(np.asarray(rgb, np.float64), min(cube, rgb.shape[1]))
    dirs = latlong_dirs(w, h).reshape(-1, 3).astype(np.float32)
    lw = (lo * om[..., None]).reshape(-1, 3).astype(np.float32)
    dt = np.ascontiguousarray(d.reshape(-1, 3).T, np.float32)
    E = np.empty((len(dirs), 3), np.float32)
    for a in range(0, len(dirs), 128):                            # 128 × 6·64² float32: 12 MiB at a time
        E[a:a + 128] = np.maximum(dirs[a:a + 128] @ dt, 0.0) @ lw
    return E.reshape(h, w, 3)


def sh9_basis(d: np.ndarray) -> np.ndarray:
    """Real spherical harmonics of bands 0–2 (..., 9) at unit directions d (..., 3)."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    return np.stack([0.282095 * np.ones_like(x), 0.488603 * y, 0.488603 * z, 0.488603 * x,
                     1.092548 * x * y, 1.092548 * y * z, 0.315392 * (3 * z * z - 1), 1.092548 * x * z,
                     0.546274 * (x * x - y * y)], -1)


def irradiance_sh9(rgb: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """E(n) (K, 3) from the 3-band SH projection of the radiance (Ramamoorthi & Hanrahan 2001: Â_l = π,
    2π/3, π/4) — exact for environments of bands ≤ 2, a ringing approximation of small bright sources."""
    d, om = cube_texel_dirs(rgb.shape[1])
    Y = sh9_basis(d.reshape(-1, 3))
    coef = Y.T @ (rgb.reshape(-1, 3).astype(np.float64) * om.reshape(-1, 1))      # (9, 3)
    A = np.array([np.pi] + [2 * np.pi / 3] * 3 + [np.pi / 4] * 5)
    return sh9_basis(np.asarray(normals, np.float64)) @ (coef * A[:, None])


def latlong_lookup(img: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Bilinear read of a lat-long map at directions (K, 3), φ wrapping, θ clamped to the first/last row
    — what the shader's sampler does (numpy twin, for measurements)."""
    h, w = img.shape[:2]
    n = np.asarray(normals, np.float64)
    u = (np.arctan2(n[:, 2], n[:, 0]) + np.pi) / (2 * np.pi) * w - 0.5
    v = np.clip(np.arccos(np.clip(n[:, 1], -1, 1)) / np.pi * h - 0.5, 0, h - 1)
    j0 = np.floor(u).astype(int)
    i0 = np.minimum(np.floor(v).astype(int), h - 2)
    fu, fv = (u - j0)[:, None], (v - i0)[:, None]
    j0, j1 = j0 % w, (j0 + 1) % w
    return ((1 - fv) * ((1 - fu) * img[i0, j0] + fu * img[i0, j1])
            + fv * ((1 - fu) * img[i0 + 1, j0] + fu * img[i0 + 1, j1]))


def diffuse_error(rgb: np.ndarray, n_dirs: int = 2000, seed: int = 0) -> dict[str, float]:
    """Relative RMS (over random normals, against :func:`irradiance_exact`) of the irradiance maps of
    :data:`IRRADIANCE_SIZE` (``map``) and 002's 32×16 (``map32x16``) and of the SH9 irradiance (``sh``), and
    their largest errors relative to the mean irradiance (``*_max_rel``)."""
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(n_dirs, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    ref = irradiance_exact(rgb, n)
    s = float(np.sqrt(np.mean(ref ** 2)))
    out = {}
    for name, est in (("map", latlong_lookup(irradiance_latlong(rgb), n)),
                      ("map32x16", latlong_lookup(irradiance_latlong(rgb, (32, 16), 32), n)),
                      ("sh", irradiance_sh9(rgb, n))):
        out[f"{name}_rel_rms"] = float(np.sqrt(np.mean((est - ref) ** 2)) / s)
        out[f"{name}_max_rel"] = float(np.abs(est - ref).max() / max(float(np.abs(ref).mean()), 1e-30))
    return out


# --------------------------------------------------------------------------- capture
CAPTURE_SCALE = 1.25            # a leaf's disc in the capture = this × its splat radius (bsh.npz, its share of area)


def capture_points(nodes: np.ndarray, splat_radius: Optional[np.ndarray], eye: np.ndarray,
                   object_first: int = -1) -> dict[str, np.ndarray]:
    """The splats of the environment seen from ``eye``: the BSH's leaves (before ``object_first``, the object's
    own surfels, when ≥ 0) that splat something, with their cone axis as normal. bsh.npz's emitters are not
    splatted but added by :func:`add_emitters`.

    Two radii [m]: ``radius`` = :data:`CAPTURE_SCALE` × the leaf's splat radius (None: its node radius), the
    disc relight's walk splats, a little grown; ``fill_radius`` = :func:`pipeline.expansion.splats.knn_splat_radii` over the
    leaf centres (render-cubemaps' hole-free rule), for the texels the first leaves empty. A leaf larger than
    the median of the first is split into k ≈ (r / median)² splats of the median radius on its disc:
    splats.py's sphere depth lets a larger disc win a boundary with smaller coplanar ones (a power diagram),
    so a bright patch made of larger leaves than its surroundings grew — bench_relight's synthetic room: its
    2 × 2 m ceiling panel (leaves 2.3× the ceiling's) took 15 % too many texels. Measured against classic
    PBGI at the same point (m 32, 64 random normals, Lambert), split / unsplit: synthetic room centre 1.061 /
    1.128 (RMS 6.5 / 13.3 %), 0.5 m from its wall 1.082 / 1.308 (10.7 / 40.2 %); shipped room (the knot's
    centre, 3 other places) 0.967–1.017 / 0.935–1.004 (RMS 2.2–6.6 / 1.7–9.6 %); the knn radii alone
    0.913–1.029 on the shipped room (3.9–15.5 %: a voxel leaf's neighbours are ~2.7× its splat radius away,
    so silhouettes swell)."""
    from ..expansion.splats import knn_splat_radii

    nd = as_nodes(nodes)
    n_env = len(nd) if object_first < 0 else int(object_first)
    leaf = np.flatnonzero(nd["right"][:n_env] == LEAF)
    own = nd["radius"] if splat_radius is None else np.asarray(splat_radius)
    leaf = leaf[own[leaf] > 0]                                       # emitters' leaves splat nothing
    pos = nd["center"][leaf].astype(np.float64)
    nrm, _ = decode_cones(nd["cone"][leaf])
    col = nd["color"][leaf].astype(np.float32)
    rad = (CAPTURE_SCALE * own[leaf]).astype(np.float64)
    fill = knn_splat_radii(pos).astype(np.float64) if len(pos) > 1 else rad.copy()
    # a leaf larger than the median splat radius r0 becomes k ≈ (r/r0)² splats of radius r0 on its disc (Vogel
    # spiral in its tangent plane): equal radii meet at the midpoints between centres, not at the power-diagram
    # boundary of splats.py's sphere depth, which a larger disc wins
    r0 = float(np.median(rad)) if len(rad) else 0.0
    k = np.where(rad > r0, np.ceil((rad / max(r0, 1e-30)) ** 2), 1).astype(np.int64)
    big = np.flatnonzero(k > 1)
    if len(big):
        from .walk import tangent_frame

        rep = np.repeat(big, k[big])
        j = np.arange(len(rep)) - np.repeat(np.cumsum(k[big]) - k[big], k[big])
        kk = k[rep]
        rr = rad[rep] * np.sqrt((j + 0.5) / kk) * np.sqrt(1.0 - 1.0 / kk)   # spread over the disc, cells ≈ r0
        ang = j * 2.399963229728653                                           # golden angle [rad]
        t, b = tangent_frame(nrm[rep])
        sub = pos[rep] + (rr * np.cos(ang))[:, None] * t + (rr * np.sin(ang))[:, None] * b
        keep = np.ones(len(pos), bool)
        keep[big] = False
        pos = np.concatenate([pos[keep], sub])
        col = np.concatenate([col[keep], col[rep]])
        nrm = np.concatenate([nrm[keep], nrm[rep]])
        fill = np.concatenate([fill[keep], fill[rep]])
        rad = np.concatenate([rad[keep], np.full(len(rep), r0)])
    return {"position": pos, "color": col, "normal": np.asarray(nrm, np.float64),
            "radius": rad, "fill_radius": fill, "leaves": np.int64(len(leaf))}


def add_emitters(faces: np.ndarray, emitters: np.ndarray, eye: np.ndarray) -> int:
    """Add bsh.npz's emitters (E, 12) to a captured cube map (6, S, S, 5) in place, as eq9.comp.glsl adds them
    to a micro-buffer: each is radiance L over the solid angle π r² ((1 − c)/4 + c max(0, cos θ_e)) / (d² + r²)
    (a quarter of its disc from any side for its object's closed part, cos θ_e for the flat share c), put
    into the texel of its direction — as L × that solid angle / the texel's — where the texel holds nothing
    nearer than its depth − max(r, 0.02 d) (depths along the face's axis). Splatted as discs instead, they
    would take the sphere-depth splat's boundary bias (:func:`capture_points`). Returns how many were added."""
    from ..camera import cube_cameras
    from ..expansion.splats import project

    e = np.asarray(emitters, np.float64).reshape(-1, 12)
    if not len(e):
        return 0
    S = faces.shape[1]
    _, om = cube_texel_dirs(S)
    cams = cube_cameras(np.asarray(eye, np.float64).reshape(1, 3), S)
    w = e[:, :3] - eye
    dist = np.linalg.norm(w, axis=1)
    ok = dist > 0
    e, w, dist = e[ok], w[ok], dist[ok]
    u = w / dist[:, None]
    ax = np.argmax(np.abs(w), 1)
    face = 2 * ax + (np.take_along_axis(w, ax[:, None], 1)[:, 0] < 0)
    added = 0
    for f in range(6):
        k = np.flatnonzero(face == f)
        if not len(k):
            continue
        col, row, depth = project(e[k, :3], cams["K"][f], cams["world_to_camera"][f])
        col = np.clip(col.astype(np.int64), 0, S - 1)
        row = np.clip(row.astype(np.int64), 0, S - 1)
        r = e[k, 3]
        z, cov = faces[f, row, col, 4], faces[f, row, col, 3] > 0
        vis = ~cov | (z >= depth - np.maximum(r, 0.02 * depth))
        c = e[k, 7]
        seen = (1 - c) * 0.25 + c * np.maximum(0.0, -(e[k, 4:7] * u[k]).sum(1))
        omega = np.pi * r * r * seen / (dist[k] ** 2 + r * r)
        gain = (omega / om[f, row, col])[:, None] * e[k, 8:11]
        kk = np.flatnonzero(vis)
        np.add.at(faces[f, ..., :3], (row[kk], col[kk]), gain[kk].astype(np.float32))
        added += len(kk)
    return added


# --------------------------------------------------------------------------- the gatherer
class EnvmapGatherer:
    """Image-based lighting from a cube map of the cloud captured at the object's centre (module docstring).

    ``run`` captures and filters the environment on its first call (``timings`` steps ``envmap_capture``,
    ``envmap_filter``), then shades every receiver with one pass (``gather``). ``diffuse`` map|sh (see
    :data:`DIFFUSE_MODES`). :meth:`set_environment` takes a radiance cube map directly (tests, benches)."""

    OBJECT_SURFELS = False  # relight: the object is not in its own environment (no self-shadowing)

    def __init__(self, ctx: Any, nodes: np.ndarray, params: GatherParams, splat_radius: Optional[np.ndarray] = None,
                 emitters: Optional[np.ndarray] = None, diffuse: str = "map", cube_size: int = CUBE_SIZE) -> None:
        from .. import gl

        if diffuse not in DIFFUSE_MODES:
            raise ValueError(f"diffuse must be one of {DIFFUSE_MODES}")
        self.ctx, self.params, self.diffuse, self.cube_size = ctx, params, diffuse, int(cube_size)
        self.nodes, self.splat_radius, self.emitters = nodes, splat_radius, emitters
        self.eye = None if params.object_center is None else np.asarray(params.object_center, np.float64).reshape(3)
        binds = glsl_defines(GATHER_BINDINGS)
        self.shade = gl.make_compute(ctx, "envmap.shade.comp.glsl", here=__file__, defines=binds)
        self.prefilter = gl.make_compute(ctx, "envmap.prefilter.comp.glsl", here=__file__,
                                         defines=glsl_defines(IMAGE_BINDINGS))
        self.lut_prog = gl.make_compute(ctx, "envmap.lut.comp.glsl", here=__file__, defines=glsl_defines(IMAGE_BINDINGS))
        self.tex: dict[str, Any] = {}
        self.faces: Optional[np.ndarray] = None     # the captured (6, S, S, 5) R, G, B, A, Z (None: set_environment)
        self.info: dict[str, Any] = {}
        self._report = False

    # ------------------------------------------------------------------ environment
    def capture(self, eye: np.ndarray, t: Optional[Timings] = None) -> np.ndarray:
        """Splat the environment from ``eye`` [m] and filter it (:meth:`set_environment`); returns the faces
        (6, S, S, 5) R, G, B, coverage, depth [m]."""
        from ..expansion.splats import render_cube_map

        t = t or Timings()
        t0 = time.perf_counter()
        S = self.cube_size
        with t.step("envmap_capture"):
            pts = capture_points(self.nodes, self.splat_radius, eye, self.params.object_first)
            faces, _ = render_cube_map(pts["position"], pts["color"], pts["radius"], eye, S, normals=pts["normal"],
                                       max_px=float(S))
            holes = faces[..., 3] == 0
            filled = 0.0
            if holes.any():                                     # the hole-free radii where the discs left gaps
                fill, _ = render_cube_map(pts["position"], pts["color"], pts["fill_radius"], eye, S,
                                          normals=pts["normal"], max_px=float(S))
                faces[holes] = fill[holes]
                filled = float(np.mean(holes & (fill[..., 3] > 0)))
            n_emit = add_emitters(faces, self.emitters, eye) if self.emitters is not None else 0
        hole = float(1.0 - faces[..., 3].mean())
        self.faces = faces
        self.eye = np.asarray(eye, np.float64).reshape(3)
        cov = faces[..., 3] > 0
        near = float(np.min(faces[..., 4][cov])) if cov.any() else float("inf")
        log.info("envmap: captured %d leaves + %d emitters from (%.3f, %.3f, %.3f) m into a %d² cube map in "
                 "%.2f s: %.2f %% of its texels from the hole-free radii, %.2f %% empty (no radiance), nearest surface "
                 "%.3f m", int(pts["leaves"]), n_emit, *self.eye, S,
                 time.perf_counter() - t0, 100 * filled, 100 * hole, near)
        self.set_environment(faces[..., :3], t)
        self.info.update(eye=[float(x) for x in self.eye], cube_size=self.cube_size, leaves=int(pts["leaves"]),
                         splats=int(len(pts["position"])), emitters=n_emit, empty_share=hole, filled_share=filled,
                         nearest_surface_m=near)
        return faces

    def set_environment(self, rgb: np.ndarray, t: Optional[Timings] = None) -> None:
        """Use the radiance cube map ``rgb`` (6, S, S, 3) (:func:`pipeline.expansion.splats.render_cube_map` layout,
        S a power of two ≥ 32): irradiance map, and for a glossy BRDF the prefiltered cube and the BRDF table on
        the GPU."""
        t = t or Timings()
        rgb = np.ascontiguousarray(rgb, np.float32)
        S = rgb.shape[1]
        if rgb.shape != (6, S, S, 3) or S < 32 or S & (S - 1):
            raise ValueError(f"the cube map must be (6, S, S, 3) with S a power of two ≥ 32, got {rgb.shape}")
        self._release_textures()
        ctx = self.ctx
        with t.step("envmap_filter"):
            if self.diffuse == "map":
                irr = irradiance_latlong(rgb)
            else:
                w, h = SH_BAKE_SIZE
                irr = irradiance_sh9(rgb, latlong_dirs(w, h).reshape(-1, 3)).reshape(h, w, 3).astype(np.float32)
            tex = ctx.texture((irr.shape[1], irr.shape[0]), 4, np.concatenate([irr, np.ones_like(irr[..., :1])], -1).tobytes(),
                              dtype="f4")
            tex.repeat_x, tex.repeat_y = True, False
            tex.filter = (ctx.LINEAR, ctx.LINEAR)
            self.tex["irr"] = tex
            self.irradiance = irr
            ctx.enable_direct(GL_TEXTURE_CUBE_MAP_SEAMLESS)
            if self.params.brdf == "lambert":                     # no specular part: no prefiltered cube
                self.tex["pref"] = ctx.texture_cube((1, 1), 4, np.zeros(24, np.float32).tobytes(), dtype="f4")
                self.levels = 1
            else:
                self._prefilter(rgb)
            self._lut()
            ctx.finish()
        err = ctx.error
        if err != "GL_NO_ERROR":
            raise RuntimeError(f"GL error after the environment-map filtering: {err}")
        self._report = True

    def _prefilter(self, rgb: np.ndarray) -> None:
        """The prefiltered radiance cube (``envmap.prefilter.comp.glsl``): level i = GGX roughness i / (levels − 1)."""
        ctx, S = self.ctx, rgb.shape[1]
        src = ctx.texture_cube((S, S), 4, dtype="f4")
        rgba = np.concatenate([rgb, np.ones_like(rgb[..., :1])], -1)
        for f in range(6):
            src.write(f, np.ascontiguousarray(rgba[f]).tobytes())
        src.build_mipmaps()
        src.filter = (ctx.LINEAR_MIPMAP_LINEAR, ctx.LINEAR)
        self.tex["src"] = src
        levels = min(ROUGH_LEVELS, int(math.log2(S)) + 1)
        pref = ctx.texture_cube((S, S), 4, dtype="f4")
        pref.build_mipmaps(0, levels - 1)                              # allocates levels 0 … levels−1
        pref.filter = (ctx.LINEAR_MIPMAP_LINEAR, ctx.LINEAR)
        self.tex["pref"] = pref
        self.levels = levels
        p = self.prefilter
        src.use(location=0)
        self._set(p, src=0, src_omega=4 * math.pi / (6 * S * S), src_max_lod=float(math.log2(S)))
        for lev in range(levels):
            size = S >> lev
            pref.bind_to_image(IMAGE_BINDINGS["IMAGE_OUT"], read=False, write=True, level=lev, format=GL_RGBA32F)
            self._set(p, size=size, roughness=lev / (levels - 1), samples=1 if lev == 0 else PREFILTER_SAMPLES)
            p.run(group_x=(size + 7) // 8, group_y=(size + 7) // 8, group_z=6)
            check_interrupt()

    def _lut(self) -> None:
        kind = self.params.brdf
        lut = self.ctx.texture((LUT_SIZE, LUT_SIZE), 4, dtype="f4")
        lut.repeat_x = lut.repeat_y = False
        lut.filter = (self.ctx.LINEAR, self.ctx.LINEAR)
        if kind != "lambert":
            lut.bind_to_image(IMAGE_BINDINGS["IMAGE_OUT"], read=False, write=True, level=0, format=GL_RGBA32F)
            self._set(self.lut_prog, size=LUT_SIZE, samples=LUT_SAMPLES, brdf_kind=BRDF_IDS[kind],
                      masking=MASK_IDS[self.params.masking])
            self.lut_prog.run(group_x=(LUT_SIZE + 7) // 8, group_y=(LUT_SIZE + 7) // 8)
        self.tex["lut"] = lut

    def lut(self) -> np.ndarray:
        """(LUT_SIZE, LUT_SIZE, 3) the (A, B, C) table, row j = roughness j/(LUT_SIZE − 1), column i = n·v
        i/(LUT_SIZE − 1) (≥ 1e-3)."""
        return np.frombuffer(self.tex["lut"].read(), np.float32).reshape(LUT_SIZE, LUT_SIZE, 4)[..., :3]

    # ------------------------------------------------------------------ gather
    def run(self, recv: Receivers, pixels: Optional[np.ndarray] = None, shape: Optional[tuple[int, int]] = None,
            timings: Optional[Timings] = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Radiance (P, 3) float32 leaving each receiver towards its eye, and stats (``method_stats``: the
        capture's, on the run that made it)."""
        t = timings or Timings()
        P = len(recv)
        if "pref" not in self.tex:
            if self.eye is None:
                if P == 0:
                    return np.zeros((0, 3), np.float32), self._stats(0)
                lo, hi = recv.position.min(0), recv.position.max(0)
                self.eye = (lo.astype(np.float64) + hi) / 2
                log.info("envmap: no object centre given; capturing at the receivers' bounding-box centre")
            self.capture(self.eye, t)
        out = np.zeros((P, 3), np.float32)
        ctx, g = self.ctx, self.shade
        self.tex["irr"].use(location=0)
        self.tex["pref"].use(location=1)
        self.tex["lut"].use(location=2)
        self._set(g, irr=0, pref=1, dfg=2, max_lod=float(self.levels - 1), lut_size=LUT_SIZE, brdf_kind=BRDF_IDS[self.params.brdf])
        B = GATHER_BINDINGS
        with t.step("gather"):
            for lo in range(0, P, DISPATCH):
                check_interrupt()
                hi = min(P, lo + DISPATCH)
                r = recv.slice(lo, hi)
                n = hi - lo
                bufs = [ctx.buffer(np.concatenate([a, b[:, None]], 1).astype(np.float32).tobytes())
                        for a, b in ((r.position, r.roughness), (r.normal, r.metallic),
                                     (r.base_color, np.zeros(n)), (r.view, np.zeros(n)))]
                res = ctx.buffer(reserve=n * 16)
                for buf, name in zip((*bufs, res), ("RECV_A", "RECV_B", "RECV_C", "RECV_D", "OUT")):
                    buf.bind_to_storage_buffer(B[name])
                self._set(g, n_recv=n, first=0)
                g.run(group_x=(n + 63) // 64)
                out[lo:hi] = np.frombuffer(res.read(), np.float32).reshape(n, 4)[:, :3]
                for b in (*bufs, res):
                    b.release()
        err = ctx.error
        if err != "GL_NO_ERROR":
            raise RuntimeError(f"GL error after the environment-map shading: {err}")
        return out, self._stats(P)

    def _stats(self, P: int) -> dict[str, Any]:
        st: dict[str, Any] = {"receivers": P, "tiles": 1 if P else 0, "tile_receivers": min(P, DISPATCH),
                              "microbuffer_bytes": 0, "nodes_visited": 0, "start_nodes": 0, "walk_passes": 0,
                              "gather_budget_bytes": self.params.memory_budget_bytes, "cut": {}}
        if self._report:
            st["method_stats"] = {"envmap": {**self.info, "diffuse": self.diffuse,
                                             "irradiance_size": list(self.irradiance.shape[1::-1]),
                                             "prefiltered_levels": self.levels, "prefilter_samples": PREFILTER_SAMPLES,
                                             "occlusion_near_object": False, "self_shadowing": False}}
            self._report = False
        return st

    @staticmethod
    def _set(prog: Any, **kw: Any) -> None:
        from .. import gl

        gl.set_uniforms(prog, **kw)

    def _release_textures(self) -> None:
        for x in self.tex.values():
            x.release()
        self.tex = {}

    def release(self) -> None:
        self._release_textures()
        for p in (self.shade, self.prefilter, self.lut_prog):
            p.release()
