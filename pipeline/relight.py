"""relight (DESIGN stage 7, paper 000 §5.2–§5.4): PBGI of a rasterised object by the HDR cloud's BSH.

Pipeline: G-buffer (``pipeline.gbuffer``) → receivers (covered pixels only) → per tile of
receivers: micro-buffer walk (``pbgi_walk.glsl``: classic = every receiver's start list is [root];
mipmapped/hybrid = start lists from ``pipeline.pbgi_mipmap.find_cut``) → final gather Eq. 9
(``pbgi_gather.glsl``) → relit.exr / relit.png / stats.json.

Micro-buffer: m×m hemispherical (orthographic) projection around the receiver's normal n with the
Duff et al. 2017 tangent frame; texel (u, v) ↔ x, y ∈ [-1, 1] at texel centres; radiance and depth
float32 in an SSBO (16 B a texel). Per-texel weights come from :func:`texel_table`:
``exact`` (default) integrates the solid angle and the projected solid angle of every texel that meets
the unit disc (a rim texel whose centre is outside the disc is kept: dropping those loses 1–2.5 % of
the cosine-weighted hemisphere at m = 8…32); ``paper`` uses Eq. 5's constant Ω = 2π/m² for the texels
whose centre is inside the disc, substituted for the node's solid angle as in §5.3.

Units: metres, radians, radiance in linear RGB float32 (W·sr⁻¹·m⁻² up to a common scale).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Optional

import numpy as np

from .config import StageConfig
from .errors import ConfigError, InputError, NotImplementedStage
from .runtime import Timings, check_interrupt, get_logger, progress

log = get_logger("relight")

BRDF_IDS = {"lambert": 0, "ggx": 1, "disney": 2}
MASK_IDS = {"height-correlated": 0, "separable": 1}
NODE_DTYPE = np.dtype([("right", "<u4"), ("skip", "<u4"), ("center", "<f4", (3,)), ("color", "<f4", (3,)),
                       ("radius", "<f4"), ("cone", "<u4")])
LEAF = 0xFFFFFFFF
TEXEL_BYTES = 16  # vec4 float32 (R, G, B, depth)


# --------------------------------------------------------------------------- config
# --preset: named points of the measured speed/accuracy trade (bench/bench_relight_tradeoff.py →
# bench/relight_tradeoff.csv: view1 of the shipped `small` scene, 128², Lambert 0.8 and GGX 0.25 against
# the path-traced gather references, noise-corrected relative RMS; bench/README.md "relight — speed/accuracy
# trade" gives the rule). CSV rows (lambert / ggx0.25):
#   exact    = rows 5 / 23: lowest error on both (0.078 / 0.129); stop 2 at m 32 gains nothing (row 33)
#   balanced = rows 4 / 22: within 14 % of exact's error (0.086 / 0.146) at 60 % of its nodes per pixel
#   fast     = rows 0 / 18: the cheapest within 2× exact's error on both (0.106 / 0.221), 28 % of its nodes
# A preset's values are applied first; every option given explicitly (CLI or TOML) still wins.
PRESETS: dict[str, dict[str, Any]] = {
    "fast": {"method": "hybrid", "microbuffer": 16, "omega_tr": 32.0, "stop_multiple": 4.0},
    "balanced": {"method": "hybrid", "microbuffer": 24, "omega_tr": 32.0, "stop_multiple": 4.0},
    "exact": {"method": "hybrid", "microbuffer": 32, "omega_tr": 32.0, "stop_multiple": 4.0},
}


@dataclass
class RelightConfig(StageConfig):
    """Options of ``pcrelight relight`` (units in brackets)."""

    preset: str = field(default="", metadata={"help": "speed/accuracy preset fast|balanced|exact from the measured front "
                                                      "(sets method, microbuffer, omega_tr, stop_multiple; explicit options win); "
                                                      "empty = the individual defaults"})
    size: str = field(default="", metadata={"help": "viewport WxH [pixels]; empty = the view's size in scene.json, else 512x512"})
    eye: str = field(default="", metadata={"help": "camera position x,y,z [m] (instead of --scene/--view)"})
    target: str = field(default="", metadata={"help": "camera target x,y,z [m]"})
    up: str = field(default="0,1,0", metadata={"help": "camera up vector x,y,z"})
    fov: Optional[float] = field(default=None, metadata={"help": "vertical field of view [degrees] (default 45 without a scene)"})
    microbuffer: int = field(default=24, metadata={"help": "micro-buffer side m (m×m texels; 8 for tests)", "choices": (8, 16, 24, 32)})
    method: str = field(default="classic", metadata={"help": "cut search (§5.2)", "choices": ("classic", "mipmapped", "hybrid")})
    brdf: str = field(default="", metadata={"help": "BRDF; empty = disney if the object has PBR materials, else lambert", "choices": ("", "lambert", "ggx", "disney")})
    albedo: str = field(default="", metadata={"help": "base colour r,g,b [linear, 0..1]; overrides the object's material"})
    roughness: Optional[float] = field(default=None, metadata={"help": "roughness [0..1] (GGX α = roughness²); overrides the object's"})
    metallic: Optional[float] = field(default=None, metadata={"help": "metallic [0..1]; overrides the object's"})
    masking: str = field(default="height-correlated", metadata={"help": "GGX Smith masking (separable = Mitsuba roughconductor)", "choices": ("height-correlated", "separable")})
    solid_angle: str = field(default="exact", metadata={"help": "micro-pixel solid angle in Eq. 9: exact per texel, or paper = Eq. 5's 2π/m²", "choices": ("exact", "paper")})
    stop_multiple: float = field(default=4.0, metadata={"help": "stop rule Ω(A) ≤ k·Ω_pix (§5.3: k = 4)"})
    lobe_samples: int = field(default=16, metadata={"help": "n: n×n VNDF samples integrate specular lobes narrower than --lobe-texels texels (0 = texel sum only)"})
    lobe_texels: float = field(default=64.0, metadata={"help": "VNDF lobe sampling when GGX α·m < this (default: always for m ≤ 32), else the texel sum"})
    disc_cone: float = field(default=1.0, metadata={"help": "splat nodes whose normal-cone half-angle ≤ this [rad] as discs (flat patches), others as spheres; -1 = spheres only (§5.2)"})
    splat_lambda: float = field(default=4.0, metadata={"help": "splat depth = centre distance + λ·(centre-to-ray distance); 0 = §5.2's centre distance"})
    omega_tr: float = field(default=32.0, metadata={"help": "hybrid threshold Ω_tr as a multiple of Ω_pix (§5.2.2: 32)"})
    memory_budget: float = field(default=1.0, metadata={"help": "GPU memory for micro-buffers and pair buffers [GiB]"})
    bloom: float = field(default=0.0, metadata={"help": "bloom strength in relit.png (0 = off)"})
    vignette: float = field(default=0.0, metadata={"help": "vignette strength in relit.png (0 = off)"})
    key: Optional[float] = field(default=None, metadata={"help": "Reinhard key for relit.png (default: automatic, Reinhard 2002)"})

    def __new__(cls, *args: Any, **kwargs: Any) -> "RelightConfig":
        # remember which fields were given (TOML/CLI values reach the constructor as keywords) so a
        # preset fills only the others
        obj = super().__new__(cls)
        names = [f.name for f in dataclasses.fields(cls)]
        obj._explicit = set(names[:len(args)]) | set(kwargs)
        return obj

    def __post_init__(self) -> None:
        if not self.preset:
            return
        if self.preset not in PRESETS:
            raise ConfigError(f"--preset must be one of {', '.join(PRESETS)}, got {self.preset!r}")
        for k, v in PRESETS[self.preset].items():
            if k not in getattr(self, "_explicit", set()):
                setattr(self, k, v)

    def check(self) -> None:
        if self.preset not in ("", *PRESETS):
            raise ConfigError(f"--preset must be one of {', '.join(PRESETS)}, got {self.preset!r}")
        if self.size:
            parse_size(self.size)
        self._require(self.microbuffer in (8, 16, 24, 32), "microbuffer", "must be 8, 16, 24 or 32")
        self._require(self.method in ("classic", "mipmapped", "hybrid"), "method", "must be classic, mipmapped or hybrid")
        self._require(self.brdf in ("", "lambert", "ggx", "disney"), "brdf", "must be lambert, ggx or disney")
        self._require(self.masking in MASK_IDS, "masking", "must be height-correlated or separable")
        self._require(self.solid_angle in ("exact", "paper"), "solid_angle", "must be exact or paper")
        self._require(self.stop_multiple > 0, "stop_multiple", "must be > 0")
        self._require(self.omega_tr >= 1, "omega_tr", "must be ≥ 1")
        self._require(0 <= self.splat_lambda <= 100, "splat_lambda", "must be in [0, 100]")
        self._require(0 <= self.lobe_samples <= 64, "lobe_samples", "must be in [0, 64]")
        self._require(-1 <= self.disc_cone <= math.pi, "disc_cone", "must be in [-1, π]")
        self._require(self.lobe_texels >= 0, "lobe_texels", "must be ≥ 0")
        self._require(self.memory_budget > 0, "memory_budget", "must be > 0")
        self._require(self.bloom >= 0, "bloom", "must be ≥ 0")
        self._require(0 <= self.vignette <= 2, "vignette", "must be in [0, 2]")
        if self.roughness is not None:
            self._require(0 <= self.roughness <= 1, "roughness", "must be in [0, 1]")
        if self.metallic is not None:
            self._require(0 <= self.metallic <= 1, "metallic", "must be in [0, 1]")
        if self.fov is not None:
            self._require(0 < self.fov < 180, "fov", "must be in (0, 180) degrees")
        for name in ("albedo", "eye", "target", "up"):
            if getattr(self, name):
                parse_vec3(getattr(self, name), name)
        if self.albedo:
            a = parse_vec3(self.albedo, "albedo")
            self._require(bool(np.all(a >= 0)), "albedo", "must be ≥ 0")
        if bool(self.eye) != bool(self.target):
            raise ConfigError("--eye and --target go together")


def parse_size(s: str) -> tuple[int, int]:
    """'WxH' → (W, H)."""
    try:
        w, h = (int(x) for x in s.lower().replace("×", "x").split("x"))
    except ValueError:
        raise ConfigError(f"--size must be WxH, got {s!r}") from None
    if not (1 <= w <= 16384 and 1 <= h <= 16384):
        raise ConfigError(f"--size must be within 1..16384 per side, got {s!r}")
    return w, h


def parse_vec3(s: str, name: str) -> np.ndarray:
    try:
        v = np.array([float(x) for x in s.replace(";", ",").split(",")], np.float64)
    except ValueError:
        v = np.zeros(0)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ConfigError(f"--{name} must be three numbers x,y,z, got {s!r}")
    return v


# --------------------------------------------------------------------------- micro-buffer texels
def texel_table(m: int, mode: str = "exact", nq: int = 64) -> np.ndarray:
    """(m·m, 4) float32 per texel (u, v) at row v·m + u: (x, y, Ω, proj).

    (x, y): tangent-plane coordinates of the texel's unit representative direction (z = √(1−x²−y²));
    Ω: solid angle [sr]; proj = ∫ cos dω over the texel [sr]. ``exact``: Ω = ∬ dx dy / z over
    texel ∩ unit disc, proj = area(texel ∩ disc), direction = normalised mean direction — integrated in
    y in closed form (arcsin) and in x by Gauss–Legendre split at the rim's kinks (ΣΩ = 2π and
    Σproj = π to 1e-6). ``paper``: Eq. 5, Ω = 2π/m² for texels whose centre is inside the disc,
    direction = centre, proj = Ω·z_centre. Ω = 0 marks an unused texel.
    """
    out = np.zeros((m, m, 4), np.float64)
    edges = np.linspace(-1.0, 1.0, m + 1)
    if mode == "paper":
        c = (edges[:-1] + edges[1:]) / 2
        X, Y = np.meshgrid(c, c)  # X along u (columns), Y along v (rows)
        r2 = X ** 2 + Y ** 2
        ok = r2 < 1
        om = 2 * np.pi / (m * m)
        out[..., 0] = np.where(ok, X, 0)
        out[..., 1] = np.where(ok, Y, 0)
        out[..., 2] = np.where(ok, om, 0)
        out[..., 3] = np.where(ok, om * np.sqrt(np.maximum(1 - r2, 0)), 0)
        return out.reshape(m * m, 4).astype(np.float32)
    if mode != "exact":
        raise ValueError(f"unknown solid-angle mode {mode!r}")
    gx, gw = np.polynomial.legendre.leggauss(nq)
    for v in range(m):
        y0, y1 = edges[v], edges[v + 1]
        for u in range(m):
            x0, x1 = edges[u], edges[u + 1]
            brk = [x0, x1]
            for yy in (y0, y1):
                xk = math.sqrt(max(1 - yy * yy, 0.0))
                brk += [s for s in (-xk, xk) if x0 < s < x1]
            brk = np.unique(brk)
            om = ar = mx = my = 0.0
            for a, b in zip(brk[:-1], brk[1:]):
                x = 0.5 * (b - a) * gx + 0.5 * (a + b)
                w = 0.5 * (b - a) * gw
                c = np.sqrt(np.maximum(1 - x * x, 0))
                lo, hi = np.clip(y0, -c, c), np.clip(y1, -c, c)
                with np.errstate(divide="ignore", invalid="ignore"):
                    asn = np.where(c > 0, np.arcsin(np.clip(hi / c, -1, 1)) - np.arcsin(np.clip(lo / c, -1, 1)), 0.0)
                om += float(np.sum(w * asn))
                ar += float(np.sum(w * (hi - lo)))
                mx += float(np.sum(w * x * asn))
                my += float(np.sum(w * (np.sqrt(np.maximum(c * c - lo * lo, 0)) - np.sqrt(np.maximum(c * c - hi * hi, 0)))))
            if om > 0:
                d = np.array([mx, my, ar]) / om
                d /= np.linalg.norm(d)
                out[v, u] = (d[0], d[1], om, ar)
    return out.reshape(m * m, 4).astype(np.float32)


def tangent_frame(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Duff et al. 2017 orthonormal basis (t, b) for unit normals n (..., 3), t × b = n (numpy twin
    of ``pbgi_frame``)."""
    n = np.asarray(n, np.float64)
    sgn = np.where(n[..., 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sgn + n[..., 2])
    bb = n[..., 0] * n[..., 1] * a
    t = np.stack([1.0 + sgn * n[..., 0] ** 2 * a, sgn * bb, -sgn * n[..., 0]], -1)
    b = np.stack([bb, sgn + n[..., 1] ** 2 * a, -n[..., 1]], -1)
    return t, b


# --------------------------------------------------------------------------- BSH nodes
def nodes_from_bsh(bsh: dict[str, np.ndarray], where: str = "bsh.npz") -> np.ndarray:
    """The (M,) structured 40-byte node array of a bsh.npz dict, checked."""
    nodes = bsh["nodes"]
    if nodes.dtype.itemsize != 40:
        raise InputError(where, f"'nodes' records are {nodes.dtype.itemsize} bytes, expected 40")
    raw = np.frombuffer(np.ascontiguousarray(nodes).tobytes(), dtype=NODE_DTYPE)
    if raw.size == 0:
        raise InputError(where, "the BSH has no nodes")
    if not (np.all(np.isfinite(raw["center"])) and np.all(np.isfinite(raw["color"])) and np.all(np.isfinite(raw["radius"]))):
        raise InputError(where, "non-finite node centre, colour or radius")
    if raw["skip"][0] != raw.size:
        raise InputError(where, f"root skip is {raw['skip'][0]}, expected M = {raw.size}")
    return raw


def encode_cone(axis: np.ndarray, half_angle: np.ndarray) -> np.ndarray:
    """Pack cones into the contract's RGBA8 (conservative: A rounded up, then widened until the
    decoded cone contains the true one). Used by tests to build BSHs; build-bsh has its own."""
    axis = np.asarray(axis, np.float64).reshape(-1, 3)
    half = np.asarray(half_angle, np.float64).reshape(-1)
    rgb = np.clip(np.rint((axis + 1) * 0.5 * 255), 0, 255).astype(np.uint32)
    dec = rgb / 255.0 * 2 - 1
    dec /= np.maximum(np.linalg.norm(dec, axis=1, keepdims=True), 1e-30)
    err = np.arccos(np.clip(np.sum(dec * axis, 1) / np.maximum(np.linalg.norm(axis, axis=1), 1e-30), -1, 1))
    a = np.clip(np.ceil((half + err) / np.pi * 255 + 1e-9), 0, 255).astype(np.uint32)
    return rgb[:, 0] | (rgb[:, 1] << 8) | (rgb[:, 2] << 16) | (a << 24)


def _merge_spheres(c1, r1, c2, r2):
    d = float(np.linalg.norm(c2 - c1))
    if d + r2 <= r1:
        return c1, r1
    if d + r1 <= r2:
        return c2, r2
    r = 0.5 * (d + r1 + r2)
    c = c1 + (c2 - c1) / d * (r - r1)
    return c, r * (1 + 1e-6)


def _merge_cones(a1, h1, a2, h2):
    th = float(np.arccos(np.clip(np.dot(a1, a2), -1, 1)))
    if th + h2 <= h1:
        return a1, h1
    if th + h1 <= h2:
        return a2, h2
    h = 0.5 * (th + h1 + h2)
    if h >= np.pi or th < 1e-12:
        return a1, min(max(h, h1, h2), np.pi)
    k = np.cross(a1, a2)
    k /= np.linalg.norm(k)
    ang = h - h1                       # rotate a1 towards a2 by this angle (Rodrigues)
    ax = a1 * np.cos(ang) + np.cross(k, a1) * np.sin(ang) + k * np.dot(k, a1) * (1 - np.cos(ang))
    return ax / np.linalg.norm(ax), h


def build_simple_bsh(points: np.ndarray, normals: np.ndarray, colors: np.ndarray,
                     leaf_radius: np.ndarray | float) -> np.ndarray:
    """A small, valid binary BSH (:data:`NODE_DTYPE`, depth-first, skip links) by median splits along
    the longest axis — one leaf per point, colours = mean of the points below, spheres and cones that
    contain their children exactly. For tests and tiny clouds; build-bsh is the real builder (Morton,
    LBVH, pruning). Python recursion: keep N ≲ 20 000."""
    p = np.asarray(points, np.float64)
    nrm = np.asarray(normals, np.float64)
    nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)
    col = np.asarray(colors, np.float64)
    N = len(p)
    if N == 0:
        raise ValueError("no points")
    lr = np.broadcast_to(np.asarray(leaf_radius, np.float64), (N,))
    M = 2 * N - 1
    nodes = np.zeros(M, NODE_DTYPE)
    cones = [None] * M
    counter = [0]

    def rec(idx):
        i = counter[0]
        counter[0] += 1
        if len(idx) == 1:
            j = idx[0]
            nodes[i]["right"] = LEAF
            nodes[i]["center"] = p[j]
            nodes[i]["color"] = col[j]
            nodes[i]["radius"] = lr[j]
            nodes[i]["skip"] = i + 1
            cones[i] = (nrm[j], 0.0)
            return i, p[j], lr[j], col[j], 1
        ext = p[idx].max(0) - p[idx].min(0)
        ax = int(np.argmax(ext))
        o = idx[np.argsort(p[idx, ax], kind="stable")]
        h = len(o) // 2
        _, c1, r1, s1, n1 = rec(o[:h])
        right, c2, r2, s2, n2 = rec(o[h:])
        c, r = _merge_spheres(c1, r1, c2, r2)
        a, hh = _merge_cones(*cones[i + 1], *cones[right])
        nodes[i]["right"] = right
        nodes[i]["skip"] = counter[0]
        nodes[i]["center"] = c
        nodes[i]["radius"] = r
        mean = (s1 * n1 + s2 * n2) / (n1 + n2)
        nodes[i]["color"] = mean
        cones[i] = (a, hh)
        return i, c, r, mean, n1 + n2

    import sys
    old = sys.getrecursionlimit()
    sys.setrecursionlimit(max(old, 10000))
    try:
        rec(np.arange(N))
    finally:
        sys.setrecursionlimit(old)
    axes = np.array([c[0] for c in cones])
    halves = np.array([c[1] for c in cones])
    nodes["cone"] = encode_cone(axes, halves)
    return nodes


def decode_cone(cone: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(axis (M,3) f32 normalised, half-angle (M,) f32 rad) exactly as pbgi_cone_decode does."""
    c = np.asarray(cone, np.uint32)
    rgb = np.stack([(c >> s) & 255 for s in (0, 8, 16)], -1).astype(np.float32) / np.float32(255) * 2 - 1
    ax = rgb / np.maximum(np.linalg.norm(rgb, axis=-1, keepdims=True), 1e-30)
    a = (c >> 24) & 255
    half = np.where(a == 255, np.float32(np.pi), a.astype(np.float32) / np.float32(255) * np.float32(np.pi))
    return ax.astype(np.float32), half.astype(np.float32)


def simple_bsh_arrays(points: np.ndarray, normals: np.ndarray, colors: np.ndarray,
                      leaf_radius: np.ndarray | float) -> dict[str, np.ndarray]:
    """Every array of the ``pcrelight.bsh/1`` schema for :func:`build_simple_bsh` (one leaf per point),
    so tests can write a real bsh.npz without build-bsh."""
    p = np.asarray(points, np.float64)
    nodes = build_simple_bsh(points, normals, colors, leaf_radius)
    M, N = len(nodes), len(p)
    leaf = nodes["right"] == LEAF
    # the leaves in depth-first order are the points in the builder's split order: recover by position
    from scipy.spatial import cKDTree

    _, order = cKDTree(p).query(nodes["center"][leaf].astype(np.float64))
    before = np.concatenate([[0], np.cumsum(leaf)])
    first = before[np.arange(M)]
    count = before[nodes["skip"].astype(np.int64)] - first
    nrm = np.asarray(normals, np.float64)
    nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)
    csum = np.concatenate([np.zeros((1, 3)), np.cumsum(nrm[order], axis=0)])
    nsum = csum[first + count] - csum[first]
    nsum /= np.maximum(np.linalg.norm(nsum, axis=1, keepdims=True), 1e-30)
    depth = np.zeros(M, np.int32)
    for i in range(M):  # children are deeper by one
        if not leaf[i]:
            depth[i + 1] = depth[nodes["right"][i]] = depth[i] + 1
    ax, half = decode_cone(nodes["cone"])
    lo = p.min(0)
    side = float((p.max(0) - lo).max()) or 1.0
    child = np.where(leaf[:, None], -1, np.stack([np.arange(M) + 1, nodes["right"].astype(np.int64)], 1)).astype(np.int32)
    return {"nodes": nodes, "center": nodes["center"].copy(),
            "radius": nodes["radius"].copy(), "color": nodes["color"].copy(), "cone_axis": ax, "cone_half_angle": half,
            "child": child, "first": first.astype(np.int64), "count": count.astype(np.int64),
            "order": np.asarray(order, np.int64), "normal": nsum.astype(np.float32), "depth": depth,
            "cluster": np.zeros(M, np.uint8), "bbox_min": lo.astype(np.float64), "cube_side": np.float64(side),
            "voxel_size": np.float64(side / 2 ** 21), "bits": np.int32(21), "n_voxels": np.int64(N),
            "n_nodes_full": np.int64(M)}


# --------------------------------------------------------------------------- receivers and the gather
@dataclass
class Receivers:
    """Shading points (covered G-buffer pixels), float32: position (P,3) [m], unit normal (P,3),
    unit direction to the eye (P,3), base colour (P,3) linear, metallic (P,), roughness (P,)."""

    position: np.ndarray
    normal: np.ndarray
    view: np.ndarray
    base_color: np.ndarray
    metallic: np.ndarray
    roughness: np.ndarray

    def __len__(self) -> int:
        return int(self.position.shape[0])

    def slice(self, lo: int, hi: int) -> "Receivers":
        return Receivers(*(getattr(self, f)[lo:hi] for f in ("position", "normal", "view", "base_color", "metallic", "roughness")))


StartLists = Callable[[int, int], tuple[np.ndarray, np.ndarray]]


def _fitting_ranges(lo: int, hi: int, offs: np.ndarray | None, max_nodes: int):
    """Split receivers [lo, hi) into consecutive ranges whose start lists (CSR ``offs`` relative to
    lo) hold at most ``max_nodes`` entries each (one receiver per range at the least)."""
    if offs is None or offs[-1] <= max_nodes:
        yield lo, hi
        return
    a = 0
    n = hi - lo
    while a < n:
        b = int(np.searchsorted(offs, offs[a] + max_nodes, side="right")) - 1
        b = min(max(b, a + 1), n)
        yield lo + a, lo + b
        a = b


def tile_size(m: int, memory_budget_bytes: float, max_ssbo: int | None, n_recv: int) -> int:
    """Receivers per tile so that tile × m² × 16 B ≤ the budget (and ≤ the GL's largest SSBO)."""
    per = m * m * TEXEL_BYTES
    cap = int(memory_budget_bytes // per)
    if max_ssbo:
        cap = min(cap, int(max_ssbo // per))
    return max(1, min(cap, max(n_recv, 1)))


def walk_iteration_budget(ctx: Any) -> int:
    """Loop iterations per receiver and walk pass. Mesa llvmpipe stops the loops of a shader
    invocation after 65535 iterations in total, counted over a SIMD vector (8 lanes at 256 bits):
    keep lanes × budget well below that. Other drivers: 65536 (bounds one dispatch's time)."""
    import re

    renderer = str(ctx.info.get("GL_RENDERER", ""))
    if "llvmpipe" in renderer.lower():
        mm = re.search(r"(\d+)\s*bits", renderer)
        lanes = max(1, int(mm.group(1)) // 32) if mm else 16
        return max(256, 40000 // lanes)
    return 65536


class Gatherer:
    """Classic PBGI walk + Eq. 9 gather on a moderngl context, tiled under a memory budget.

    ``nodes``: (M,) :data:`NODE_DTYPE` (40-byte records). ``brdf`` in lambert|ggx|disney.
    """

    DISPATCH = 4096  # receivers per compute dispatch (interrupt checks between dispatches)

    def __init__(self, ctx: Any, nodes: np.ndarray, m: int, *, solid_angle: str = "exact",
                 stop_multiple: float = 4.0, brdf: str = "lambert", masking: str = "height-correlated",
                 memory_budget: float = 1.0, splat_lambda: float = 4.0, lobe_samples: int = 16,
                 lobe_texels: float = 64.0, point_fallback: bool = True, disc_cone: float = 1.0) -> None:
        from . import gl

        self.ctx, self.m = ctx, int(m)
        self.keep_microbuffers = False  # debugging/tests: keep the last tile's micro-buffers (n, m, m, 4)
        self.last_microbuffers: np.ndarray | None = None
        self.brdf, self.masking = brdf, masking
        self.stop_multiple = float(stop_multiple)
        self.budget = float(memory_budget) * 2 ** 30
        self.max_ssbo = ctx.info.get("GL_MAX_SHADER_STORAGE_BLOCK_SIZE")
        nodes = np.ascontiguousarray(nodes)
        if nodes.dtype.itemsize != 40:
            raise ValueError("nodes must be 40-byte records")
        self.n_nodes = int(nodes.shape[0])
        nbytes = self.n_nodes * 40
        if self.max_ssbo and nbytes > self.max_ssbo:  # measured: Mesa llvmpipe reads a 200 MiB SSBO past its 128 MiB limit
            log.warning("%d nodes = %d B exceed GL_MAX_SHADER_STORAGE_BLOCK_SIZE (%d B, %s); binding the whole buffer "
                        "anyway (Mesa llvmpipe reads past the limit; if the image is wrong, prune more: --tc/--tn)",
                        self.n_nodes, nbytes, self.max_ssbo, gl.context_info(ctx)["renderer"])
        self.node_buf = ctx.buffer(nodes.tobytes())
        self.texels = texel_table(self.m, solid_angle)
        self.texel_buf = ctx.buffer(self.texels.tobytes())
        self.walk = gl.make_compute(ctx, "pbgi_walk.glsl", here=__file__,
                                    defines={"PBGI_LAMBDA": repr(float(splat_lambda)),
                                             "PBGI_POINT_FALLBACK": int(bool(point_fallback))})
        self.gather = gl.make_compute(ctx, "pbgi_gather.glsl", here=__file__)
        self._set(self.walk, m=self.m, stop_multiple=self.stop_multiple,
                  omega_pix=2 * math.pi / (self.m * self.m), n_nodes=self.n_nodes)
        self._set(self.gather, m=self.m, brdf_kind=BRDF_IDS[brdf], masking=MASK_IDS[masking],
                  lobe_samples=int(lobe_samples), lobe_texels=float(lobe_texels))
        self.iter_budget = walk_iteration_budget(ctx)
        self._set(self.walk, disc_cone=float(disc_cone))

    @staticmethod
    def _set(prog: Any, **kw: Any) -> None:
        for k, v in kw.items():
            try:
                prog[k].value = v
            except KeyError:  # optimised out
                pass

    def run(self, recv: Receivers, start_lists: StartLists | None = None,
            timings: Timings | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Radiance (P, 3) float32 leaving each receiver towards its eye, and stats."""
        ctx, m = self.ctx, self.m
        P = len(recv)
        t = timings or Timings()
        out = np.zeros((P, 3), np.float32)
        tile = tile_size(m, self.budget, self.max_ssbo, P)
        stats: dict[str, Any] = {"receivers": P, "tile_receivers": tile, "tiles": 0, "nodes_visited": 0,
                                 "microbuffer_bytes": tile * m * m * TEXEL_BYTES, "start_nodes": 0}
        if P == 0:
            return out, stats
        mb = ctx.buffer(reserve=tile * m * m * TEXEL_BYTES)
        bufs = {k: ctx.buffer(reserve=tile * 16) for k in ("a", "b", "c", "d", "out")}
        state = ctx.buffer(reserve=tile * 16)
        pending = ctx.buffer(reserve=4)
        dummy = ctx.buffer(reserve=16)
        empty_texel = np.array([0, 0, 0, 3.0e38], np.float32).tobytes()
        stats["walk_passes"] = 0
        # start lists bigger than this are walked in receiver sub-ranges (a mipmapped cut at
        # 1024² × 32² reaches ~100 MiB a tile, llvmpipe's largest SSBO is 128 MiB)
        sn_limit = int(min(self.max_ssbo or 2 ** 62, self.budget / 4))
        stats["start_list_limit_bytes"] = sn_limit
        stats["start_list_splits"] = 0
        try:
            for tlo in progress(range(0, P, tile), total=-(-P // tile), desc="relight tiles"):
                thi = min(P, tlo + tile)
                toffs = tsnodes = None
                if start_lists is not None:
                    with t.step("upload"):
                        toffs, tsnodes = start_lists(tlo, thi)
                        toffs = np.ascontiguousarray(toffs, np.int64)
                        tsnodes = np.ascontiguousarray(tsnodes, np.uint32)
                        if toffs.shape != (thi - tlo + 1,) or toffs[0] != 0 or toffs[-1] != tsnodes.size:
                            raise ValueError("start lists: offsets must be (n+1,) from 0 to len(nodes)")
                for lo, hi in _fitting_ranges(tlo, thi, toffs, sn_limit // 4):
                    stats["start_list_splits"] += 1
                    n = hi - lo
                    r = recv.slice(lo, hi)
                    with t.step("upload"):
                        bufs["a"].write(np.concatenate([r.position, r.roughness[:, None]], 1).astype(np.float32).tobytes())
                        bufs["b"].write(np.concatenate([r.normal, r.metallic[:, None]], 1).astype(np.float32).tobytes())
                        bufs["c"].write(np.concatenate([r.base_color, np.zeros((n, 1))], 1).astype(np.float32).tobytes())
                        bufs["d"].write(np.concatenate([r.view, np.zeros((n, 1))], 1).astype(np.float32).tobytes())
                        mb.clear(size=n * m * m * TEXEL_BYTES, chunk=empty_texel)
                        if toffs is not None:
                            a, b = toffs[lo - tlo], toffs[hi - tlo]
                            offs = (toffs[lo - tlo:hi - tlo + 1] - a).astype(np.uint32)
                            snodes = tsnodes[a:b]
                            off_buf = ctx.buffer(offs.tobytes())
                            sn_buf = ctx.buffer(snodes.tobytes() if snodes.size else b"\0" * 4)
                            stats["start_nodes"] += int(snodes.size)
                        else:
                            off_buf, sn_buf = dummy, dummy
                    self._walk_and_gather(n, bufs, mb, state, pending, off_buf, sn_buf, start_lists is not None, t, stats)
                    with t.step("readback"):
                        res = np.frombuffer(bufs["out"].read(size=n * 16), np.float32).reshape(n, 4)
                        out[lo:hi] = res[:, :3]
                        st = np.frombuffer(state.read(size=n * 16), np.uint32).reshape(n, 4)
                        stats["nodes_visited"] += int(st[:, 3].astype(np.int64).sum())
                        if self.keep_microbuffers:
                            self.last_microbuffers = np.frombuffer(mb.read(size=n * m * m * TEXEL_BYTES), np.float32).reshape(n, m, m, 4).copy()
                    if toffs is not None:
                        off_buf.release()
                        sn_buf.release()
                stats["tiles"] += 1
            stats["start_list_splits"] -= stats["tiles"]
        finally:
            for b in (mb, state, pending, dummy, *bufs.values()):
                b.release()
        err = ctx.error
        if err != "GL_NO_ERROR":
            raise RuntimeError(f"GL error after the PBGI gather: {err}")
        return out, stats

    def _walk_and_gather(self, n: int, bufs: dict, mb: Any, state: Any, pending: Any, off_buf: Any, sn_buf: Any,
                         use_lists: bool, t: Timings, stats: dict[str, Any]) -> None:
        """Walk n receivers (resumable passes) into their micro-buffers, then the Eq. 9 gather."""
        self.node_buf.bind_to_storage_buffer(0)
        mb.bind_to_storage_buffer(1)
        self.texel_buf.bind_to_storage_buffer(2)
        bufs["a"].bind_to_storage_buffer(3)
        bufs["b"].bind_to_storage_buffer(4)
        off_buf.bind_to_storage_buffer(5)
        sn_buf.bind_to_storage_buffer(6)
        state.bind_to_storage_buffer(7)
        bufs["c"].bind_to_storage_buffer(8)
        bufs["d"].bind_to_storage_buffer(9)
        bufs["out"].bind_to_storage_buffer(10)
        pending.bind_to_storage_buffer(11)
        self._set(self.walk, n_recv=n, use_lists=int(use_lists), iter_budget=self.iter_budget)
        self._set(self.gather, n_recv=n)
        with t.step("walk"):
            passes = 0
            while True:
                check_interrupt()
                pending.write(np.zeros(1, np.uint32).tobytes())
                self._set(self.walk, init=int(passes == 0))
                for first in range(0, n, self.DISPATCH):
                    self._set(self.walk, first=first)
                    self.walk.run(group_x=(min(self.DISPATCH, n - first) + 63) // 64)
                passes += 1
                left = int(np.frombuffer(pending.read(), np.uint32)[0])
                if left == 0:
                    break
            stats["walk_passes"] = max(stats["walk_passes"], passes)
        with t.step("gather"):
            for first in range(0, n, self.DISPATCH):
                self._set(self.gather, first=first)
                self.gather.run(group_x=(min(self.DISPATCH, n - first) + 63) // 64)
            self.ctx.finish()

    def release(self) -> None:
        for b in (self.node_buf, self.texel_buf):
            b.release()
        self.walk.release()
        self.gather.release()


# --------------------------------------------------------------------------- the stage action
def _camera(cfg: RelightConfig, scene: dict | None, scene_path: Any, view: str | None):
    from .gbuffer import Camera

    v: dict = {}
    if scene is not None and not cfg.eye:
        views = scene.get("views", {})
        name = view or "view1"
        if name not in views:
            raise InputError(scene_path, f"no view '{name}' (have: {', '.join(views) or 'none'})")
        v = views[name]
    if cfg.eye:
        eye, target = parse_vec3(cfg.eye, "eye"), parse_vec3(cfg.target, "target")
        up = parse_vec3(cfg.up, "up")
    elif v:
        try:
            eye, target, up = (np.asarray(v[k], np.float64).reshape(3) for k in ("eye", "target", "up"))
        except (KeyError, ValueError) as e:
            raise InputError(scene_path, f"view '{view}' lacks eye/target/up ({e})") from None
    else:
        raise ConfigError("relight needs a camera: --scene with --view, or --eye and --target")
    if np.linalg.norm(target - eye) <= 0:
        raise ConfigError("--eye and --target must differ")
    size = parse_size(cfg.size) if cfg.size else tuple(int(x) for x in v["size"]) if "size" in v else (512, 512)
    fov = cfg.fov if cfg.fov is not None else float(v.get("fov_deg", 45.0))
    return Camera(eye, target, up, fov, (int(size[0]), int(size[1])))


def _object(object_path: Any, scene: dict | None, scene_path: Any):
    """(path, to_world or None): --object, else scene.json's object; scene.json's to_world applies when
    the object is the scene's (same file name as its file/obj/ply entries)."""
    from pathlib import Path

    obj = (scene or {}).get("object") or {}
    names = {obj.get(k) for k in ("file", "obj", "ply") if obj.get(k)}
    if object_path is None:
        if not obj.get("file"):
            raise ConfigError("relight needs --object (or a scene.json with an object)")
        object_path = Path(scene_path).parent / obj["file"]
    to_world = obj.get("to_world") if Path(object_path).name in names else None
    return object_path, to_world


def choose_brdf(cfg: RelightConfig, parts: list[dict]) -> tuple[str, str]:
    """(brdf, reason). Lambert unless the object (after overrides) has something glossy."""
    if cfg.brdf:
        return cfg.brdf, "--brdf"
    glossy = any(p.get("mr_tex") is not None
                 or (cfg.metallic if cfg.metallic is not None else p["metallic"]) > 0
                 or (cfg.roughness if cfg.roughness is not None else p["roughness"]) < 1
                 for p in parts if p.get("pbr"))
    if glossy:
        return "disney", "the object has glossy metallic-roughness materials"
    return "lambert", "every material is diffuse (metallic 0, roughness 1 or no PBR material)"


def run_relight(bsh_path: Any, out_dir: Any, cfg: RelightConfig, object_path: Any = None, scene_path: Any = None,
                view: str | None = None, cloud_path: Any = None, preview: Any = None, ctx: Any = None) -> dict:
    """Render the object relit by the BSH: writes relit.exr (float32 RGBA, alpha = mask), relit.png
    (Reinhard with automatic key, optional bloom/vignette) and stats.json in ``out_dir``."""
    from pathlib import Path

    from . import display, gl, io
    from .gbuffer import place_parts, render_gbuffer

    t = Timings()
    t_start = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scene = io.read_json(scene_path) if scene_path is not None else None
    if scene is not None and not isinstance(scene, dict):
        raise InputError(scene_path, "not a scene.json object")
    cam = _camera(cfg, scene, scene_path, view)
    object_path, to_world = _object(object_path, scene, scene_path)
    with t.step("read"):
        parts = place_parts(io.read_object(object_path), to_world)
        bsh = io.read_npz(bsh_path, "pcrelight.bsh/1")
        nodes = nodes_from_bsh(bsh, str(bsh_path))
    log.info("read %s: %d part(s), %d triangles%s", object_path, len(parts), sum(len(p["faces"]) for p in parts),
             " (placed by scene.json to_world)" if to_world is not None else "")
    log.info("read %s: %d nodes (%.1f MiB)", bsh_path, len(nodes), nodes.nbytes / 2 ** 20)
    if cloud_path is not None:
        log.info("--cloud %s not read: the BSH holds everything PBGI needs", cloud_path)
    brdf_kind, why = choose_brdf(cfg, parts)
    log.info("BRDF %s (%s)%s", brdf_kind, why, "; glossy work skipped (no BRDF evaluation in the gather)"
             if brdf_kind == "lambert" else "")
    own_ctx = ctx is None
    if own_ctx:
        ctx = gl.create_context()
    fbo = gl.bind_dummy_framebuffer(ctx)
    try:
        info = gl.context_info(ctx)
        log.info("GL: %s / %s", info["vendor"], info["renderer"])
        W, H = cam.size
        with t.step("gbuffer"):
            gb = render_gbuffer(ctx, parts, cam)
        mask = gb["mask"]
        P = int(mask.sum())
        log.info("G-buffer %dx%d: %d covered pixels (%.1f %%); the %d others are never processed", W, H, P,
                 100.0 * P / (W * H), W * H - P)
        flat = np.flatnonzero(mask.reshape(-1))
        base = gb["base_color"].reshape(-1, 3)[flat]
        if cfg.albedo:
            base = np.broadcast_to(parse_vec3(cfg.albedo, "albedo").astype(np.float32), base.shape)
        met = gb["metallic"].reshape(-1)[flat] if cfg.metallic is None else np.full(P, cfg.metallic, np.float32)
        rgh = gb["roughness"].reshape(-1)[flat] if cfg.roughness is None else np.full(P, cfg.roughness, np.float32)
        recv = Receivers(gb["position"].reshape(-1, 3)[flat], gb["normal"].reshape(-1, 3)[flat],
                         gb["view"].reshape(-1, 3)[flat], np.ascontiguousarray(base, np.float32),
                         np.ascontiguousarray(met, np.float32), np.ascontiguousarray(rgh, np.float32))
        budget = cfg.memory_budget * 2 ** 30
        mip_stats: dict = {}
        start_lists = None
        gather_budget = budget
        g = Gatherer(ctx, nodes, cfg.microbuffer, solid_angle=cfg.solid_angle, stop_multiple=cfg.stop_multiple,
                     brdf=brdf_kind, masking=cfg.masking, memory_budget=cfg.memory_budget,
                     splat_lambda=cfg.splat_lambda, lobe_samples=cfg.lobe_samples, lobe_texels=cfg.lobe_texels,
                     disc_cone=cfg.disc_cone)
        if cfg.method in ("mipmapped", "hybrid"):
            try:
                from .pbgi_mipmap import make_start_lists
            except ImportError as e:
                raise NotImplementedStage("relight", f"--method {cfg.method} needs pipeline.pbgi_mipmap ({e})") from None
            gather_budget = budget * 0.75
            g.budget = gather_budget
            mcfg = {"microbuffer": cfg.microbuffer, "stop_multiple": cfg.stop_multiple, "omega_tr": cfg.omega_tr,
                    "memory_budget": int(budget)}
            start_lists, mip_stats = make_start_lists(ctx, recv.position, recv.normal, flat, (H, W), g.node_buf, mcfg,
                                                      cfg.method == "hybrid", tf_budget=int(budget * 0.25))
        rad, gstats = g.run(recv, start_lists, timings=t)
        g.release()
        fbo.release()
    finally:
        if own_ctx:
            ctx.release()
    bad = ~np.isfinite(rad)
    if bad.any():
        log.warning("%d non-finite radiance values set to 0", int(bad.sum()))
        rad[bad] = 0
    img = np.zeros((H * W, 4), np.float32)
    img[flat, :3] = rad
    img[flat, 3] = 1.0
    img = img.reshape(H, W, 4)
    with t.step("write"):
        io.write_image(out / "relit.exr", img)
        png = display.tonemap(img[..., :3], mask=mask if P else None, key=cfg.key, bloom_strength=cfg.bloom,
                              vignette_strength=cfg.vignette)
        io.write_png(out / "relit.png", png)
        if preview is not None:
            io.write_png(preview, png)
    stats = {
        "stage": "relight", "inputs": {"bsh": str(bsh_path), "object": str(object_path),
                                       "scene": None if scene_path is None else str(scene_path), "view": view},
        "config": cfg.as_dict(), "gl": info, "camera": {"eye": cam.eye.tolist(), "target": cam.target.tolist(),
                                                        "up": np.asarray(cam.up).tolist(), "fov_deg": cam.fov_deg,
                                                        "size": [W, H]},
        "method": cfg.method, "brdf": brdf_kind, "brdf_reason": why,
        "decisions": {"glossy_work_skipped": brdf_kind == "lambert", "pixels_off_object_skipped": W * H - P,
                      "to_world_applied": to_world is not None, "walk_iteration_budget": g.iter_budget},
        "pixels": W * H, "covered_pixels": P, "nodes": int(len(nodes)), "microbuffer": cfg.microbuffer,
        "memory_budget_bytes": int(budget), "gather_budget_bytes": int(gather_budget),
        "tiles": gstats["tiles"], "tile_receivers": gstats["tile_receivers"],
        "microbuffer_bytes": gstats["microbuffer_bytes"], "nodes_visited": gstats["nodes_visited"],
        "nodes_visited_per_pixel": gstats["nodes_visited"] / max(P, 1), "start_nodes": gstats["start_nodes"],
        "walk_passes": gstats.get("walk_passes", 0), "mipmapped": mip_stats,
        "start_list_limit_bytes": gstats.get("start_list_limit_bytes"), "start_list_splits": gstats.get("start_list_splits", 0),
        "time_s": t.as_dict(), "total_s": time.perf_counter() - t_start,
    }
    io.write_json(out / "stats.json", stats)
    log.info("relit %dx%d (%s, m=%d, %s): %d tiles, %.0f nodes visited a pixel, %.2f s", W, H, cfg.method,
             cfg.microbuffer, brdf_kind, gstats["tiles"], stats["nodes_visited_per_pixel"], stats["total_s"])
    return stats
