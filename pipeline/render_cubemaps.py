"""render-cubemaps (seed 000 §4.1): LDR cloud → cube maps of point splats with depth + cameras.npz.

Conventions (shared with :mod:`pipeline.reproject` and documented in ``cameras.npz``)
------------------------------------------------------------------------------------
* One viewpoint ``eye`` (metres) gives 6 faces in the order +X −X +Y −Y +Z −Z (``face`` 0…5).
  Each face is a right-handed pinhole camera looking down its −Z axis with +Y up (OpenGL camera
  space), rotated as OpenGL renders cube-map faces (``lookAt`` table: +X: up −Y; −X: up −Y;
  +Y: up +Z; −Y: up −Z; +Z: up −Y; −Z: up −Y).  ``world_to_camera`` = [R | −R·eye].
* Pixels: for camera coordinates (x, y, z) with depth d = −z > 0,
  ``[u, v, 1]ᵀ ∝ K · [x, y, −z]ᵀ`` i.e. u = K00·x/d + K02, v = K11·y/d + K12, in pixel units
  whose (0, 0) is the corner of the first pixel of the file (pixel centres at i + 0.5);
  u indexes columns, v indexes **rows in file order**.  The row index grows with camera +Y, i.e.
  row 0 is the GL framebuffer's bottom row = the cube-map texture's t = 0 row, so each EXR is
  exactly the OpenGL cube-map face image (s along columns, t along rows; Table 8.19 of the GL
  spec) and can be uploaded with glTexImage2D as is.  As with every GL cube map, a face viewed
  top-down is the *mirror image* of what the camera sees (side faces: world +Y at the top row,
  but left and right swapped).
* A face is 90° square: K = [[W/2, 0, W/2], [0, H/2, H/2], [0, 0, 1]].
* Face EXR channels: R, G, B (linear LDR colour of the nearest splat), A (coverage 0/1),
  Z (depth d of the nearest splat's centre along the view axis, metres; 0 where empty).

Splatting (numba, deterministic)
--------------------------------
Every point is a screen-aligned disc (a GL point sprite) of world radius
``r = splat_scale · mean distance to its splat_k nearest neighbours`` (local spacing; the defaults
k = 16, scale 1.25 left no hole in uniformly random samples of a plane at 64²…1024², while k = 8,
scale 1 left 0.3–0.6 % of the pixels empty); its pixel radius is ρ_max = f·r/d (f = W/2), capped at
``max_splat_px``; the pixel holding the centre is always covered.  The depth test uses the splat as
a sphere (a "depth sprite": depth d − r·sqrt(1 − ρ²/ρ_max²) at screen distance ρ from its centre),
so where splats of one surface overlap the pixel goes to the nearest centre, not to whichever
came first; ties → smaller point index.  The Z channel stores the winning splat's *centre* depth d.
Faces are rendered in parallel (one face per thread), deterministic.  ``renderer = gl`` draws
the same splats as GL point sprites (splat.vert/frag.glsl through pipeline/gl.py: sprite of side
2ρ_max + 2 px, fragments outside the disc discarded except the centre pixel, gl_FragDepth = sphere
depth / far, GL_LESS in index order, a guard band of max_splat_px so sprites centred outside a face
still reach it).  Measured on this 2-core machine under a load of ~10 (llvmpipe, one cube map, two runs): 20k
points 256²/1024²: numba 0.25–0.26/2.05–2.06 s, GL 0.39–0.53/1.99–2.40 s; 200k points: numba
0.33–0.39/4.49–5.03 s, GL 1.16–1.27/4.44–4.67 s; the two agree on 99.995–99.999 % of the pixels
(the rest: near-ties on GL's 24-bit depth).  numba
stays the default here (no GPU; exact float32 ties, tested against a brute-force reference); the
probe renders of the automatic viewpoints always use numba.

Facing (``facing_test``, default on): a point whose normal faces away from the eye (n·(eye − p) ≤ 0)
is not counted as seen — a surface seen from behind (e.g. a roof seen from above, outside the
scene) is not a view of it.  ``backface_cull`` (default off) also stops drawing such splats; off,
every splat is opaque from both sides, as a thin single-layer surface (a drape) is.

Visibility (coverage here, and the same test in reproject, whose parameters are stored in
cameras.npz): a point is *seen* by a face when it faces the eye, its nearest pixel is covered and
its depth d ≤ Z·(1 + depth_tol) + radius_tol·r (Z the depth channel there, r its splat radius: a
neighbour's splat of the same surface may win the point's own pixel at grazing angles).

Stray points: Open3D's statistical outlier removal (``outlier_neighbors``, ``outlier_std``) flags
points far from the others (scanner strays, 50 m away: their spacing radius is tens of metres, so
their depth sprites would cover whole faces, and they stretch the bounding box the viewpoint search
fills).  Flagged points do not set the bounding volumes of the viewpoint search (the box, hence the
lattice, the clearance and the in-box test of the normal candidates) and are drawn with at most the
median splat radius; they are still drawn and counted, since on clean clouds the test also flags
isolated real points — at the default 10 σ, 13 of the 200 000 points of the small ground truth,
all of them on the small bright sun (3 σ: 426, 66 overexposed), none of the tiny one's.  Counts
are logged and reported (``outliers``).  A coverage of the overexposed points below ``coverage``
is a WARNING, automatic viewpoints or not.

Automatic viewpoints (when ``viewpoints`` is empty)
---------------------------------------------------
Candidates: (a) the cell centres of a lattice of about ``grid``³ cells filling the bounding box,
kept when their nearest point is ≥ ``clearance`` away (default: 3 % of the box diagonal, at least 2
median splat radii); (b) in front of ``normal_seeds`` random overexposed points, p + h·n(p) for
h = 1, 2, 4, 8 × base (base = max(median radius, 1 % of the diagonal)), kept when their nearest
point is ≥ max(h/2, median radius) away — this reaches narrow spaces (a light shaft) the lattice
misses.  For each candidate a cheap ``probe_size``² cube map of (a random subset of at most
``probe_points`` of, radii × sqrt(N/subset)) the cloud is splatted; a candidate whose cube map is
covered on less than ``min_enclosure`` (90 %) of its pixels is outside the (closed) scene and is
dropped (all are kept, with a warning, if none passes).  Each overexposed point (LDR luminance >
t_l; a random subset of at most ``probe_targets``) is seen by the visibility test above with
tolerance ``probe_tol``.  Greedy selection: repeatedly take the candidate that sees the most
not-yet-covered overexposed points (ties → lowest candidate index) until the covered fraction ≥
``coverage`` or ``max_views`` views or no candidate adds a point.  The coverage actually reached by
the full-resolution cube maps is logged and reported (``coverage``; a warning when below target).

Model only what the scene requires: a cloud without overexposed points gets no cube map
(``cameras.npz`` with F = V = 0, a log line and ``skipped`` in the report).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numba import njit, prange

from .color import luminance
from .config import StageConfig, sub_seed
from .errors import ConfigError
from .runtime import Timings, check_interrupt, get_logger, progress
from .workspace import FaceFolder, write_faces

log = get_logger("render-cubemaps")

FACE_NAMES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")
# (forward, up) per face: the OpenGL cube-map rendering table.
_FACE_DIRS = (
    ((1, 0, 0), (0, -1, 0)),
    ((-1, 0, 0), (0, -1, 0)),
    ((0, 1, 0), (0, 0, 1)),
    ((0, -1, 0), (0, 0, -1)),
    ((0, 0, 1), (0, -1, 0)),
    ((0, 0, -1), (0, -1, 0)),
)


@dataclass
class RenderCubemapsConfig(StageConfig):
    size: int = field(default=1024, metadata={"help": "cube-map face size [pixels] (square faces)"})
    renderer: str = field(default="numba", metadata={
        "help": "numba: CPU disc splatter; gl: GL point sprites (pipeline/gl.py; same rules, 24-bit depth ties)",
        "choices": ("numba", "gl")})
    viewpoints: list[list[float]] = field(default_factory=list, metadata={
        "help": "cube-map centres [m] as x,y,z triples (TOML: [[x,y,z], ...]); empty = choose automatically"})
    max_views: int = field(default=6, metadata={"help": "most viewpoints chosen automatically"})
    coverage: float = field(default=0.95, metadata={
        "help": "automatic viewpoints stop once this fraction of the overexposed points is seen [0..1]"})
    t_l: float = field(default=0.9, metadata={"help": "overexposure threshold on LDR luminance (CIE Y, linear)"})
    splat_scale: float = field(default=1.25, metadata={
        "help": "splat radius = splat_scale × mean distance to the splat_k nearest neighbours"})
    splat_k: int = field(default=16, metadata={"help": "neighbours for the local point spacing"})
    max_splat_px: float = field(default=32.0, metadata={"help": "cap of a splat's radius [pixels]"})
    near: float = field(default=1e-3, metadata={"help": "near plane: points closer than this are not drawn [m]"})
    depth_tol: float = field(default=0.02, metadata={
        "help": "relative depth tolerance of the visibility test (seen if d ≤ Z·(1+tol) + radius_tol·r)"})
    grid: int = field(default=6, metadata={"help": "candidate viewpoints: a lattice of about grid³ cells in the bounding box"})
    clearance: float = field(default=0.0, metadata={
        "help": "lattice candidates closer than this to a point are rejected [m]; 0 = max(3% of the box diagonal, 2 median splat radii)"})
    probe_size: int = field(default=64, metadata={"help": "face size of the visibility probe renders [pixels]"})
    probe_points: int = field(default=50_000, metadata={"help": "most points splatted by a probe render"})
    probe_targets: int = field(default=20_000, metadata={"help": "most overexposed points counted by the probe"})
    probe_tol: float = field(default=0.05, metadata={"help": "relative depth tolerance of the probe visibility"})
    radius_tol: float = field(default=1.0, metadata={
        "help": "visibility also accepts d ≤ Z·(1+tol) + radius_tol × the point's splat radius"})
    normal_seeds: int = field(default=64, metadata={
        "help": "extra candidates in front of this many random overexposed points (p + h·n, h = 1,2,4,8 × base); 0 = lattice only"})
    min_enclosure: float = field(default=0.9, metadata={
        "help": "automatic candidates must see surfaces on this fraction of their cube map (inside the scene)"})
    backface_cull: bool = field(default=False, metadata={
        "help": "do not draw splats whose normal faces away from the eye (off: every splat is opaque both ways, e.g. drapes)"})
    facing_test: bool = field(default=True, metadata={
        "help": "a point whose normal faces away from the eye is not counted as seen (coverage, reproject)"})
    outlier_neighbors: int = field(default=20, metadata={
        "help": "statistical outlier test (Open3D): neighbours of the mean-distance test; 0 = off"})
    outlier_std: float = field(default=10.0, metadata={
        "help": "statistical outlier test: a point whose mean neighbour distance exceeds the cloud's mean by this many "
                "standard deviations does not set the viewpoint search's bounding box and is drawn with at most the median splat radius"})

    def check(self) -> None:
        self._require(self.size >= 8, "size", "must be ≥ 8")
        self._require(self.renderer in ("numba", "gl"), "renderer", "must be numba or gl")
        self._require(self.max_views >= 1, "max_views", "must be ≥ 1")
        self._require(0.0 < self.coverage <= 1.0, "coverage", "must be in (0, 1]")
        self._require(0.0 <= self.t_l < 1.0, "t_l", "must be in [0, 1) (LDR luminance; patchmatch's rule)")
        self._require(self.splat_scale > 0, "splat_scale", "must be > 0")
        self._require(self.splat_k >= 1, "splat_k", "must be ≥ 1")
        self._require(self.max_splat_px >= 0.5, "max_splat_px", "must be ≥ 0.5")
        self._require(self.near > 0, "near", "must be > 0")
        self._require(self.depth_tol >= 0, "depth_tol", "must be ≥ 0")
        self._require(self.grid >= 1, "grid", "must be ≥ 1")
        self._require(self.clearance >= 0, "clearance", "must be ≥ 0")
        self._require(self.probe_size >= 4, "probe_size", "must be ≥ 4")
        self._require(self.probe_points >= 1, "probe_points", "must be ≥ 1")
        self._require(self.probe_targets >= 1, "probe_targets", "must be ≥ 1")
        self._require(self.probe_tol >= 0, "probe_tol", "must be ≥ 0")
        self._require(self.radius_tol >= 0, "radius_tol", "must be ≥ 0")
        self._require(self.normal_seeds >= 0, "normal_seeds", "must be ≥ 0")
        self._require(0 <= self.min_enclosure <= 1, "min_enclosure", "must be in [0, 1]")
        self._require(self.outlier_neighbors >= 0, "outlier_neighbors", "must be ≥ 0")
        self._require(self.outlier_std > 0, "outlier_std", "must be > 0")
        vp = [tuple(v) if isinstance(v, (list, tuple)) else (v,) for v in self.viewpoints]
        if vp and all(len(v) == 1 for v in vp):  # the CLI gives "x,y,z;x,y,z" as a flat list
            flat = [v[0] for v in vp]
            if len(flat) % 3:
                raise ConfigError(f"--viewpoints: {len(flat)} numbers is not a list of x,y,z triples")
            vp = [tuple(flat[i:i + 3]) for i in range(0, len(flat), 3)]
        self.viewpoints = [list(map(float, v)) for v in vp]
        for v in self.viewpoints:
            if len(v) != 3 or not all(math.isfinite(float(x)) for x in v):
                raise ConfigError(f"--viewpoints: each viewpoint must be 3 finite numbers x,y,z, got {v!r}")


# ----------------------------------------------------------------------------- cameras
def face_rotations() -> np.ndarray:
    """(6,3,3) world→camera rotations (rows = camera x, y, z axes in world coordinates)."""
    out = np.zeros((6, 3, 3))
    for i, (fwd, up) in enumerate(_FACE_DIRS):
        f = np.asarray(fwd, float)
        u = np.asarray(up, float)
        z = -f
        x = np.cross(u, z)
        out[i] = np.stack([x, u, z])
    return out


def cube_cameras(eyes: np.ndarray, size: int) -> dict[str, np.ndarray]:
    """The arrays of ``cameras.npz`` (schema pcrelight.cameras/1) for cube maps at ``eyes`` (V,3)."""
    eyes = np.asarray(eyes, dtype=np.float64).reshape(-1, 3)
    v = len(eyes)
    rot = face_rotations()
    f = size / 2.0
    K = np.array([[f, 0.0, size / 2.0], [0.0, f, size / 2.0], [0.0, 0.0, 1.0]])
    w2c = np.zeros((v * 6, 4, 4))
    for vi in range(v):
        for fi in range(6):
            m = np.eye(4)
            m[:3, :3] = rot[fi]
            m[:3, 3] = -rot[fi] @ eyes[vi]
            w2c[vi * 6 + fi] = m
    return {
        "K": np.repeat(K[None], v * 6, axis=0),
        "world_to_camera": w2c,
        "resolution": np.full((v * 6, 2), size, dtype=np.int32),
        "view": np.repeat(np.arange(v, dtype=np.int32), 6),
        "face": np.tile(np.arange(6, dtype=np.int32), v),
        "eye": eyes,
    }


def project(points: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project world points (N,3) with one camera: returns (u, v, d) float64 — pixel coordinates in
    the file's column/row order (see the module docstring) and depth d = −z_cam (≤ 0: behind)."""
    p = np.asarray(points, dtype=np.float64)
    c = p @ w2c[:3, :3].T + w2c[:3, 3]
    d = -c[:, 2]
    q = np.stack([c[:, 0], c[:, 1], d], axis=1) @ np.asarray(K, dtype=np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        u = q[:, 0] / q[:, 2]
        v = q[:, 1] / q[:, 2]
    return u, v, d


def visible_pixels(points: np.ndarray, K: np.ndarray, w2c: np.ndarray, depth: np.ndarray,
                   cover: np.ndarray, rel_tol: float, normals: np.ndarray | None = None,
                   abs_tol: np.ndarray | float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Visibility of points in one rendered face: (seen bool (N,), row (N,), col (N,)).

    A point is seen when it is in front of the camera, faces it (n·(eye − p) > 0, when ``normals``
    are given), its nearest pixel (floor of u, v) lies in the image and is covered, and its depth
    d ≤ Z·(1 + rel_tol) + abs_tol with Z the depth channel there (abs_tol: scalar or per point,
    e.g. the point's splat radius: a neighbour's splat may win the point's own pixel).
    """
    h, w = depth.shape
    u, v, d = project(points, K, w2c)
    ok = (d > 0) & np.isfinite(u) & np.isfinite(v)
    col = np.full(len(d), -1, dtype=np.int64)
    row = np.full(len(d), -1, dtype=np.int64)
    col[ok] = np.floor(u[ok]).astype(np.int64)
    row[ok] = np.floor(v[ok]).astype(np.int64)
    ok &= (col >= 0) & (col < w) & (row >= 0) & (row < h)
    if normals is not None:
        eye = -w2c[:3, :3].T @ w2c[:3, 3]
        ok &= np.einsum("ij,ij->i", np.asarray(normals, dtype=np.float64), eye - np.asarray(points, dtype=np.float64)) > 0
    seen = np.zeros(len(d), dtype=bool)
    idx = np.nonzero(ok)[0]
    z = depth[row[idx], col[idx]]
    a = cover[row[idx], col[idx]] > 0
    tol = np.broadcast_to(np.asarray(abs_tol, dtype=np.float64), d.shape)[idx]
    seen[idx] = a & (d[idx] <= z * (1.0 + rel_tol) + tol)
    return seen, row, col


# ----------------------------------------------------------------------------- splatting
def splat_radii(points: np.ndarray, k: int = 16, scale: float = 1.25, query: np.ndarray | None = None) -> np.ndarray:
    """World splat radius per point: scale × mean distance to its k nearest neighbours [m]
    (the point itself excluded); only for the points ``query`` (indices) when given."""
    from scipy.spatial import cKDTree

    n = len(points)
    if n < 2:
        return np.full(n if query is None else len(query), 1e-3, dtype=np.float32)
    k = min(k, n - 1)
    q = points if query is None else points[query]
    m = len(q)
    d, _ = cKDTree(points).query(q, k=k + 1, workers=-1)
    r = d[:, 1:].reshape(m, k).mean(axis=1) * scale
    pos = r[r > 0]
    fallback = float(np.median(pos)) if pos.size else 1e-3
    r = np.where(r > 0, r, fallback)  # duplicate points: use the typical spacing
    return r.astype(np.float32)


def isolated_spacing(cen: np.ndarray, spacing: np.ndarray, ratio: float, k: int = 16) -> tuple[np.ndarray, int]:
    """(spacing [m], points changed): a point (a BSH leaf, or a cloud point with its splat radius) whose
    spacing exceeds ``ratio`` × the median spacing of its ``k`` nearest ones gets that median / sqrt(2);
    ``ratio`` 0 returns the input.  Used by build-bsh (leaf discs) and reproject (the registered photo's
    occluder discs, and which points read the photo's local peak).

    Why: the splat radius d4/sqrt(2) gives a disc of about twice a point's share of area on a sampled
    surface, where neighbouring discs overlap and the micro-buffer's depth test counts each place once.
    A sphere smaller than the point spacing (a 4 cm lamp among 9 cm spacing) gets 2–3 points whose 4th
    neighbour lies on a far surface: discs of that size, and nothing overlaps them.  With the disc equal
    to the point's share (its neighbours' median disc / 2) the back-culled discs of m points on a sphere
    add up, in expectation, to its cross-section: m · share · E[max(0, cos)] = 4πR² / 4."""
    if ratio <= 0 or len(spacing) <= 1:
        return spacing, 0
    from scipy.spatial import cKDTree

    k = min(k, len(spacing) - 1)
    _, nb = cKDTree(cen).query(cen, k=k + 1, workers=-1)
    med = np.median(spacing[nb[:, 1:]], axis=1)
    iso = spacing > ratio * med
    return np.where(iso, med / math.sqrt(2.0), spacing), int(np.count_nonzero(iso))


@njit(cache=True, inline="always")
def _splat_into(fi, i, px, py, pz, radius, rots, fx, fy, cx, cy, width, height, near, max_px, zbuf, dbuf, ibuf):
    """Splat point i (eye-relative position px, py, pz) into face fi; False when it misses it."""
    d = -(rots[fi, 2, 0] * px + rots[fi, 2, 1] * py + rots[fi, 2, 2] * pz)
    if d <= near:
        return False
    xc = rots[fi, 0, 0] * px + rots[fi, 0, 1] * py + rots[fi, 0, 2] * pz
    yc = rots[fi, 1, 0] * px + rots[fi, 1, 1] * py + rots[fi, 1, 2] * pz
    u = fx * xc / d + cx
    v = fy * yc / d + cy
    rp = fx * radius / d
    if rp > max_px:
        rp = max_px
    if u + rp < 0.0 or v + rp < 0.0 or u - rp >= width or v - rp >= height:
        return False
    c0 = max(int(math.floor(u - rp)), 0)
    c1 = min(int(math.floor(u + rp)), width - 1)
    w0 = max(int(math.floor(v - rp)), 0)
    w1 = min(int(math.floor(v + rp)), height - 1)
    uc = int(math.floor(u))
    vc = int(math.floor(v))
    rp2 = rp * rp
    for row in range(w0, w1 + 1):
        dy = row + 0.5 - v
        for col in range(c0, c1 + 1):
            dx = col + 0.5 - u
            rho2 = (dx * dx + dy * dy) / rp2
            if rho2 > 1.0 and not (row == vc and col == uc):
                continue
            ze = np.float32(d - radius * math.sqrt(max(0.0, 1.0 - rho2)))
            zb = zbuf[fi, row, col]
            if ze < zb or (ze == zb and i < ibuf[fi, row, col]):
                zbuf[fi, row, col] = ze
                dbuf[fi, row, col] = d
                ibuf[fi, row, col] = i
    return True


@njit(parallel=True, cache=True)
def _splat_kernel(points, radii, normals, cull, rots, eyes, fx, fy, cx, cy, width, height, near, max_px,
                  zbuf, dbuf, ibuf):
    """Cube maps (faces 6v…6v+5 = +X −X +Y −Y +Z −Z of view v, one eye each, f = W/2), per face
    (F,H,W): zbuf = depth of the nearest sphere-splat surface, dbuf = that splat's centre depth,
    ibuf = its point index (−1 empty).  One face per thread.  A point is splatted into the face of
    its major axis, and into the others only when its disc may leave that face (minor/major + ρ/f
    ≥ 1) — exactly what splatting every point into every face gives, with ~6× less work."""
    nf = rots.shape[0]
    n = points.shape[0]
    for fi in prange(nf):
        k = fi % 6
        ex = eyes[fi, 0]; ey = eyes[fi, 1]; ez = eyes[fi, 2]
        for i in range(n):
            px = points[i, 0] - ex
            py = points[i, 1] - ey
            pz = points[i, 2] - ez
            ax = abs(px); ay = abs(py); az = abs(pz)
            if ax >= ay and ax >= az:
                fm = 0 if px > 0 else 1
                m = ax; s1 = ay; s2 = az
            elif ay >= az:
                fm = 2 if py > 0 else 3
                m = ay; s1 = ax; s2 = az
            else:
                fm = 4 if pz > 0 else 5
                m = az; s1 = ax; s2 = ay
            if fm != k:
                if m <= near:
                    continue  # its depth along every face axis is ≤ m ≤ near: drawn nowhere
                e = min(fx * radii[i] / m, max_px) / fx
                if s1 / m + e < 1.0 - 1e-9 and s2 / m + e < 1.0 - 1e-9:
                    continue  # the disc stays inside its major face
            if cull and normals[i, 0] * px + normals[i, 1] * py + normals[i, 2] * pz >= 0.0:
                continue  # back-facing: the eye is behind the point's surface
            _splat_into(fi, i, px, py, pz, radii[i], rots, fx, fy, cx, cy, width, height, near, max_px,
                        zbuf, dbuf, ibuf)


def splat_faces(points: np.ndarray, radii: np.ndarray, K: np.ndarray, w2c: np.ndarray,
                width: int, height: int, near: float = 1e-3, max_px: float = 32.0,
                normals: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Depth-tested disc splats of ``points`` into the F = 6V faces of V cube maps (as
    :func:`cube_cameras` lays them out: intrinsics ``K``, size width × height); with ``normals``,
    back-facing points (n·(eye − p) ≤ 0) are culled.
    Returns (depth (F,H,W) float32, 0 where empty; index (F,H,W) int32, −1 empty).
    Depths are compared in float32 (ties → lower index)."""
    w2c = np.asarray(w2c, dtype=np.float64).reshape(-1, 4, 4)
    if len(w2c) % 6:
        raise ValueError(f"splat_faces renders whole cube maps: {len(w2c)} faces is not a multiple of 6")
    rots = np.ascontiguousarray(w2c[:, :3, :3])
    eyes = np.ascontiguousarray(-np.einsum("fji,fj->fi", rots, w2c[:, :3, 3]))  # eye = −Rᵀt
    nf = len(w2c)
    zbuf = np.full((nf, height, width), np.inf, dtype=np.float32)
    dbuf = np.zeros((nf, height, width), dtype=np.float32)
    ibuf = np.full((nf, height, width), -1, dtype=np.int32)
    cull = normals is not None
    nrm = np.ascontiguousarray(normals if cull else np.zeros((1, 3)), dtype=np.float64)
    _splat_kernel(np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(radii, dtype=np.float64),
                  nrm, cull, rots, eyes, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                  int(width), int(height), float(near), float(max_px), zbuf, dbuf, ibuf)
    return dbuf, ibuf


def splat_faces_gl(points: np.ndarray, radii: np.ndarray, K: np.ndarray, w2c: np.ndarray,
                   width: int, height: int, near: float = 1e-3, max_px: float = 32.0,
                   normals: np.ndarray | None = None, ctx: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """The GL route of :func:`splat_faces` (point sprites, splat.vert/frag.glsl): same disc, centre
    pixel and sphere-depth rules, depth test GL_LESS in drawing order (ties → lower index) on a
    24-bit depth buffer of sphere depth / far — so near-ties may resolve differently from the
    float32 numba route.  Back-face culling is not implemented here (``normals`` must be None)."""
    import moderngl

    from . import gl

    if normals is not None:
        raise NotImplementedError("the GL splatter has no back-face culling; use the numba route")
    w2c = np.asarray(w2c, dtype=np.float64).reshape(-1, 4, 4)
    own = ctx is None
    if own:
        ctx = gl.create_context()
    try:
        margin = int(math.ceil(max_px)) + 2
        full = (width + 2 * margin, height + 2 * margin)
        prog = gl.make_program(ctx, vertex="splat.vert.glsl", fragment="splat.frag.glsl", here=__file__)
        pts = np.ascontiguousarray(points, dtype=np.float32)
        rad = np.ascontiguousarray(radii, dtype=np.float32)
        vbo = ctx.buffer(np.concatenate([pts, rad[:, None]], axis=1).astype(np.float32).tobytes())
        vao = ctx.vertex_array(prog, [(vbo, "3f 1f", "in_pos", "in_radius")])
        t_id = ctx.texture(full, 1, dtype="i4")
        t_d = ctx.texture(full, 1, dtype="f4")
        depth = ctx.depth_texture(full)
        fbo = ctx.framebuffer(color_attachments=[t_id, t_d], depth_attachment=depth)
        fbo.use()
        ctx.enable(moderngl.DEPTH_TEST | moderngl.PROGRAM_POINT_SIZE)
        ctx.depth_func = "<"
        eyes = -np.einsum("fji,fj->fi", w2c[:, :3, :3], w2c[:, :3, 3])
        lo, hi = pts.min(axis=0).astype(np.float64), pts.max(axis=0).astype(np.float64)
        corners = np.array([[(lo, hi)[b >> k & 1][k] for k in range(3)] for b in range(8)])
        far = float(np.linalg.norm(corners[None] - eyes[:, None], axis=2).max()) * 1.01 + 1.0  # ≥ every depth
        prog["f"].value = float(K[0, 0])
        prog["size"].value = (float(width), float(height))
        prog["margin"].value = float(margin)
        prog["near"].value = float(near)
        prog["max_px"].value = float(max_px)
        prog["far"].value = far
        zs = np.zeros((len(w2c), height, width), dtype=np.float32)
        ids = np.full((len(w2c), height, width), -1, dtype=np.int32)
        for fi in range(len(w2c)):
            prog["R"].write(np.ascontiguousarray(w2c[fi, :3, :3].T, dtype=np.float32).tobytes())  # column-major
            prog["eye"].value = tuple(float(x) for x in eyes[fi])
            fbo.clear(depth=1.0)
            t_id.write(np.full(full[0] * full[1], -1, dtype=np.int32).tobytes())  # "empty" = −1
            vao.render(moderngl.POINTS)
            vp = (margin, margin, width, height)
            ids[fi] = np.frombuffer(fbo.read(viewport=vp, components=1, attachment=0, dtype="i4"),
                                    dtype=np.int32).reshape(height, width)
            zs[fi] = np.frombuffer(fbo.read(viewport=vp, components=1, attachment=1, dtype="f4"),
                                   dtype=np.float32).reshape(height, width)
        zs[ids < 0] = 0.0
        for obj in (vao, vbo, fbo, t_id, t_d, depth, prog):
            obj.release()
        return zs, ids
    finally:
        if own:
            ctx.release()


def render_view(points: np.ndarray, colors: np.ndarray, radii: np.ndarray, eye: np.ndarray, size: int,
                near: float = 1e-3, max_px: float = 32.0, normals: np.ndarray | None = None,
                gl_ctx: Any = None) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """One cube map at ``eye``: faces (6, size, size, 5) float32 = R,G,B,A,Z and its cameras
    (numba splatter, or the GL route when a moderngl context ``gl_ctx`` is given)."""
    cams = cube_cameras(np.asarray(eye).reshape(1, 3), size)
    if gl_ctx is not None:
        z, idx = splat_faces_gl(points, radii, cams["K"][0], cams["world_to_camera"], size, size, near, max_px,
                                normals, ctx=gl_ctx)
    else:
        z, idx = splat_faces(points, radii, cams["K"][0], cams["world_to_camera"], size, size, near, max_px, normals)
    out = np.empty((6, size, size, 5), dtype=np.float32)
    hit = idx >= 0
    out[..., :3] = np.take(np.asarray(colors, dtype=np.float32), np.maximum(idx, 0), axis=0)
    out[..., :3] *= hit[..., None]
    out[..., 3] = hit
    out[..., 4] = z
    return out, cams


# ----------------------------------------------------------------------------- stray points
def statistical_inliers(points: np.ndarray, neighbors: int = 20, std_ratio: float = 3.0) -> np.ndarray:
    """(N,) bool: the points Open3D's statistical outlier removal keeps (mean distance to the
    ``neighbors`` nearest points ≤ the cloud's mean of that distance + ``std_ratio`` standard
    deviations).  Stray scan points far from the room would otherwise stretch the bounding box the
    viewpoint search fills; ``neighbors`` = 0 or fewer points than that → all True."""
    n = len(points)
    if neighbors <= 0 or n <= neighbors:
        return np.ones(n, dtype=bool)
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    _, ind = pc.remove_statistical_outlier(nb_neighbors=int(neighbors), std_ratio=float(std_ratio))
    keep = np.zeros(n, dtype=bool)
    keep[np.asarray(ind, dtype=np.int64)] = True
    return keep


# ----------------------------------------------------------------------------- viewpoints
def candidate_viewpoints(points: np.ndarray, grid: int, clearance: float, box: np.ndarray | None = None) -> np.ndarray:
    """Cell centres of a lattice of about grid³ cubic-ish cells filling the bounding box of ``box``
    (default ``points``; cells per axis ∝ the box's extent, at least 1), kept where the nearest point
    is ≥ clearance away."""
    from scipy.spatial import cKDTree

    box = points if box is None else box
    lo = box.min(axis=0).astype(np.float64)
    hi = box.max(axis=0).astype(np.float64)
    ext = np.maximum(hi - lo, 1e-9)
    cell = float(np.prod(ext)) ** (1 / 3) / grid
    counts = [max(1, int(round(e / cell))) for e in ext]
    axes = [lo[a] + (np.arange(counts[a]) + 0.5) / counts[a] * (hi[a] - lo[a]) for a in range(3)]
    c = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    d, _ = cKDTree(points).query(c, k=1, workers=-1)
    return c[d >= clearance]


def normal_candidates(points: np.ndarray, normals: np.ndarray, seeds: np.ndarray, base: float,
                      min_clear: float, box: np.ndarray | None = None) -> np.ndarray:
    """Candidates in front of overexposed points: p + h·n(p) for h ∈ {1, 2, 4, 8}·base, kept where
    the nearest point is ≥ max(h/2, min_clear) away (free space around the offset position)."""
    from scipy.spatial import cKDTree

    if len(seeds) == 0:
        return np.zeros((0, 3))
    hs = base * np.array([1.0, 2.0, 4.0, 8.0])
    c = (points[seeds][:, None, :] + hs[None, :, None] * normals[seeds][:, None, :]).reshape(-1, 3)
    need = np.maximum(np.tile(hs, len(seeds)) / 2.0, min_clear)
    d, _ = cKDTree(points).query(c, k=1, workers=-1)
    box = points if box is None else box
    lo, hi = box.min(0), box.max(0)
    inside = ((c >= lo) & (c <= hi)).all(axis=1)
    return c[(d >= need) & inside]


def probe_visibility(cands: np.ndarray, points: np.ndarray, radii: np.ndarray, normals: np.ndarray | None,
                     targets: np.ndarray, t_radii: np.ndarray, t_normals: np.ndarray | None, size: int,
                     rel_tol: float, radius_tol: float, near: float, max_px: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Probe renders: ((C, M) bool — target m seen from candidate c in a size² cube map of
    ``points``; (C,) the fraction of the cube map's pixels covered, i.e. how enclosed c is)."""
    out = np.zeros((len(cands), len(targets)), dtype=bool)
    enclosed = np.zeros(len(cands))
    chunk = 16
    for c0 in range(0, len(cands), chunk):
        check_interrupt()
        cams = cube_cameras(cands[c0:c0 + chunk], size)
        z, idx = splat_faces(points, radii, cams["K"][0], cams["world_to_camera"], size, size, near, max_px, normals)
        cover = idx >= 0
        for f in range(len(z)):
            seen, _, _ = visible_pixels(targets, cams["K"][f], cams["world_to_camera"][f], z[f], cover[f], rel_tol,
                                        t_normals, radius_tol * t_radii)
            out[c0 + f // 6] |= seen
            enclosed[c0 + f // 6] += cover[f].mean() / 6.0
    return out, enclosed


def greedy_select(vis: np.ndarray, target: float, max_views: int) -> tuple[list[int], list[float]]:
    """Greedy set cover: indices of chosen candidates and the covered fraction after each pick."""
    m = vis.shape[1]
    covered = np.zeros(m, dtype=bool)
    chosen: list[int] = []
    fracs: list[float] = []
    if m == 0:
        return chosen, fracs
    while len(chosen) < max_views and covered.mean() < target:
        gain = vis[:, ~covered].sum(axis=1)
        best = int(np.argmax(gain))  # ties → lowest index
        if gain[best] == 0:
            break
        chosen.append(best)
        covered |= vis[best]
        fracs.append(float(covered.mean()))
    return chosen, fracs


def choose_viewpoints(points: np.ndarray, radii: np.ndarray, over: np.ndarray, cfg: RenderCubemapsConfig,
                      normals: np.ndarray | None = None, inliers: np.ndarray | None = None
                      ) -> tuple[np.ndarray, dict[str, Any]]:
    """Automatic viewpoints (module docstring). ``inliers`` (N,) bool: the points that set the bounding
    box, the lattice and the clearance (default all; see :func:`statistical_inliers`).
    Returns (eyes (V,3), info for the report)."""
    rng = np.random.default_rng(sub_seed(cfg.seed))
    box = points if inliers is None else points[inliers]
    diag = float(np.linalg.norm(box.max(0) - box.min(0)))
    clearance = cfg.clearance if cfg.clearance > 0 else max(0.03 * diag, 2.0 * float(np.median(radii)))
    cands = candidate_viewpoints(points, cfg.grid, clearance, box)
    n_grid = len(candidate_viewpoints(points, cfg.grid, -1.0, box))
    info: dict[str, Any] = {"grid": cfg.grid, "clearance_m": clearance, "candidates_grid": n_grid,
                            "candidates_free": int(len(cands))}
    if cfg.normal_seeds > 0 and normals is not None:
        oi = np.nonzero(over)[0]
        seeds = np.sort(rng.choice(oi, min(cfg.normal_seeds, len(oi)), replace=False))
        min_clear = float(np.median(radii))
        nc = normal_candidates(points, normals, seeds, max(min_clear, 0.01 * diag), min_clear, box)
        info["candidates_normal"] = int(len(nc))
        cands = np.concatenate([cands, nc])
        info["candidates_free"] = int(len(cands))
    if len(cands) == 0:
        c = 0.5 * (box.min(0) + box.max(0))
        log.warning("no candidate viewpoint is %.3g m away from the points; using the box centre", clearance)
        info["fallback"] = "bounding-box centre (no free-space candidate)"
        return c[None].astype(np.float64), info
    n = len(points)
    if n > cfg.probe_points:
        sub = np.sort(rng.choice(n, cfg.probe_points, replace=False))
        ppts, prad = points[sub], radii[sub] * math.sqrt(n / cfg.probe_points)
        pnrm = None if normals is None or not cfg.backface_cull else normals[sub]
    else:
        ppts, prad, pnrm = points, radii, (normals if cfg.backface_cull else None)
    oidx = np.nonzero(over)[0]
    if len(oidx) > cfg.probe_targets:
        oidx = np.sort(rng.choice(oidx, cfg.probe_targets, replace=False))
    vis, enclosed = probe_visibility(cands, ppts, prad, pnrm, points[oidx], radii[oidx],
                                     None if normals is None or not cfg.facing_test else normals[oidx],
                                     cfg.probe_size, cfg.probe_tol,
                                     cfg.radius_tol, cfg.near, cfg.max_splat_px)
    inside = enclosed >= cfg.min_enclosure
    if not inside.any():
        log.warning("no candidate sees surfaces over ≥ %.0f%% of its cube map (best %.0f%%): keeping all %d",
                    100 * cfg.min_enclosure, 100 * enclosed.max(), len(cands))
        inside[:] = True
    info["candidates_enclosed"] = int(inside.sum())
    keep = np.nonzero(inside)[0]
    chosen, fracs = greedy_select(vis[keep], cfg.coverage, cfg.max_views)
    if not chosen:
        chosen = [int(np.argmax(vis[keep].sum(1)))]
        fracs = [float(vis[keep][chosen[0]].mean())]
    chosen = [int(keep[c]) for c in chosen]
    info.update({"probe_targets": int(len(oidx)), "chosen_candidates": chosen, "probe_coverage_after_each": fracs,
                 "enclosure_of_chosen": [float(enclosed[c]) for c in chosen]})
    return cands[chosen], info


# ----------------------------------------------------------------------------- preview
def cross_layout(faces: np.ndarray) -> np.ndarray:
    """Six (S,S,C) faces in +X −X +Y −Y +Z −Z order → the standard OpenGL cube-map horizontal
    cross (3S, 4S, C): middle row −X +Z +X −Z, +Y above and −Y below +Z, faces drawn as stored
    (file row 0 at the top), so edges meet (the whole cross is the mirror image of the scene, as
    every GL cube-map cross)."""
    s = faces.shape[1]
    c = faces.shape[3]
    out = np.zeros((3 * s, 4 * s, c), dtype=faces.dtype)
    place = {1: (1, 0), 4: (1, 1), 0: (1, 2), 5: (1, 3), 2: (0, 1), 3: (2, 1)}
    for f, (r, q) in place.items():
        out[r * s:(r + 1) * s, q * s:(q + 1) * s] = faces[f]
    return out


SOURCE_COLOURS = np.array([[0.35, 0.35, 0.35], [0.1, 0.8, 0.1], [0.15, 0.35, 1.0]], dtype=np.float32)


def preview_cloud(path: str | Path, cloud: Any, eye: np.ndarray | None = None, size: int = 192) -> None:
    """PNG preview of a cloud: a cube-map cross from ``eye`` (default the box centre), tone-mapped
    colours on top; below, the point kinds: grey kept LDR, green projected, blue Poisson, red invalid."""
    from . import io

    pts = cloud.points.astype(np.float64)
    if eye is None:
        eye = 0.5 * (pts.min(0) + pts.max(0))
    sel = np.arange(len(pts))
    if len(pts) > 300_000:  # a preview: a fixed subset (every k-th point), radii grown to match
        sel = sel[:: int(math.ceil(len(pts) / 300_000))]
    radii = splat_radii(pts[sel]).astype(np.float64)
    pts = pts[sel]
    cloud = cloud.subset(sel)
    cams = cube_cameras(np.asarray(eye).reshape(1, 3), size)
    z, idx = splat_faces(pts, radii, cams["K"][0], cams["world_to_camera"], size, size)
    hit = idx >= 0
    faces = np.zeros((6, size, size, 4), dtype=np.float32)
    faces[..., :3][hit] = cloud.colors[idx[hit]]
    faces[..., 3] = hit
    top = cross_layout(faces)
    from .display import reinhard

    rgb = reinhard(top[..., :3], mask=top[..., 3] > 0)
    kind = np.zeros(len(pts), dtype=np.int64) if cloud.source is None else cloud.source.astype(np.int64).clip(0, 2)
    kcol = SOURCE_COLOURS[kind]
    if cloud.valid is not None:
        kcol[cloud.valid == 0] = (1.0, 0.1, 0.1)
    kf = np.zeros((6, size, size, 4), dtype=np.float32)
    kf[..., :3][hit] = kcol[idx[hit]]
    kf[..., 3] = hit
    bottom = cross_layout(kf)
    img = np.concatenate([rgb * top[..., 3:], bottom[..., :3]], axis=0)
    io.write_png(path, io.srgb_encode(img))


# ----------------------------------------------------------------------------- action
def visibility_params(cfg: RenderCubemapsConfig) -> dict[str, np.ndarray]:
    """The optional cameras.npz keys that let reproject repeat this stage's visibility test."""
    return {"splat_k": np.int32(cfg.splat_k), "splat_scale": np.float64(cfg.splat_scale),
            "backface_cull": np.int32(cfg.backface_cull), "facing_test": np.int32(cfg.facing_test),
            "depth_tol": np.float64(cfg.depth_tol),
            "radius_tol": np.float64(cfg.radius_tol)}


def overexposed_mask(colors: np.ndarray, t_l: float) -> np.ndarray:
    """Points whose LDR luminance (CIE Y of linear RGB) exceeds t_l."""
    return luminance(colors) > t_l


def read_overexposed(cloud: str | Path, t_l: float, t: Timings) -> tuple[Any, np.ndarray]:
    """Read an LDR cloud (timed as "read") and its overexposed mask, logging the count."""
    from . import io

    with t.step("read"):
        c = io.read_cloud(cloud)
    over = overexposed_mask(c.colors, t_l)
    log.info("%d overexposed points (LDR luminance > %g)", int(over.sum()), t_l)
    return c, over


def run_render_cubemaps(cloud: str | Path, out_dir: str | Path, cfg: RenderCubemapsConfig,
                        preview: str | Path | None = None) -> dict[str, Any]:
    """Read the LDR cloud, choose/take viewpoints, splat the cube maps, write ``out_dir``:
    cameras.npz, face_XXX.exr (R,G,B,A,Z), report.json; a cross PNG when ``preview`` is given."""
    from . import io

    t = Timings()
    t0 = time.perf_counter()
    folder = FaceFolder(out_dir)
    c, over = read_overexposed(cloud, cfg.t_l, t)
    n, n_over = len(c), int(over.sum())
    report: dict[str, Any] = {"input": str(cloud), "points": n, "overexposed": n_over, "t_l": cfg.t_l,
                              "config": cfg.as_dict(), "renderer": "numba disc splats (CPU)"}
    folder.path.mkdir(parents=True, exist_ok=True)

    def drop_stale(n_faces: int) -> None:
        # faces of an earlier run beyond this one's would mislead patchmatch; removed only once this run's faces
        # and cameras.npz are written (each file stays the old one or a complete new one if the stage is killed)
        for old in folder.stored_faces():
            try:
                if int(old.stem.split("_")[-1]) >= n_faces:
                    old.unlink()
            except ValueError:
                old.unlink()

    if n_over == 0:
        log.info("no overexposed point: nothing to expand, no cube map rendered (cameras.npz with 0 faces)")
        cams = cube_cameras(np.zeros((0, 3)), cfg.size)
        io.write_npz(folder.cameras, "pcrelight.cameras/1", **cams)
        drop_stale(0)
        report.update({"skipped": "no overexposed point", "views": 0, "faces": 0, "coverage": None,
                       "timings": t.as_dict(), "seconds": time.perf_counter() - t0})
        io.write_json(folder.report, report)
        return report
    report["skipped"] = None
    with t.step("outliers"):
        inl = statistical_inliers(c.points, cfg.outlier_neighbors, cfg.outlier_std)
    n_out, n_out_over = int((~inl).sum()), int((~inl & over).sum())
    report["outliers"] = {"removed": n_out, "removed_overexposed": n_out_over,
                          "neighbors": cfg.outlier_neighbors, "std_ratio": cfg.outlier_std}
    with t.step("radii"):
        pts = c.points.astype(np.float64)
        radii = splat_radii(pts, cfg.splat_k, cfg.splat_scale).astype(np.float64)
        if n_out:  # an isolated point's spacing radius is huge: its depth sprite would cover the room
            radii[~inl] = np.minimum(radii[~inl], float(np.median(radii[inl])))
    log.info("statistical outlier removal (%d neighbours, %g σ): %d of %d points (%d overexposed) left out of "
             "the viewpoint search's bounding box and drawn with at most the median splat radius",
             cfg.outlier_neighbors, cfg.outlier_std, n_out, n, n_out_over)
    nrm_all = c.normals.astype(np.float64)
    nrm = nrm_all if cfg.backface_cull else None            # drawing
    nrm_vis = nrm_all if cfg.facing_test else None          # visibility
    log.info("splat radii: median %.4g m (k=%d, scale %g)", float(np.median(radii)), cfg.splat_k, cfg.splat_scale)
    with t.step("viewpoints"):
        if cfg.viewpoints:
            eyes = np.asarray(cfg.viewpoints, dtype=np.float64).reshape(-1, 3)
            report["viewpoint_mode"] = "config"
            log.info("%d viewpoints from the config", len(eyes))
        else:
            eyes, info = choose_viewpoints(pts, radii, over, cfg, nrm_all, inliers=inl)
            report["viewpoint_mode"] = "automatic"
            report["automatic"] = info
            log.info("automatic viewpoints: %d of %d candidates (%d in free space, %d enclosed; probe coverage %s)",
                     len(eyes), info["candidates_grid"], info["candidates_free"], info.get("candidates_enclosed", 0), ", ".join(f"{x:.3f}" for x in info.get("probe_coverage_after_each", [])))
    cams = cube_cameras(eyes, cfg.size)
    oidx = np.nonzero(over)[0]
    covered = np.zeros(len(oidx), dtype=bool)
    gl_ctx = None
    if cfg.renderer == "gl":
        from . import gl

        if cfg.backface_cull:
            raise ConfigError("--renderer gl has no back-face culling; use --no-backface-cull or --renderer numba")
        gl_ctx = gl.create_context()
        report["renderer"] = f"GL point sprites ({gl.context_info(gl_ctx)['renderer']})"
        log.info("rendering with GL point sprites on %s", gl.context_info(gl_ctx)["renderer"])
    per_view = []
    crosses = []
    for vi, eye in progress(list(enumerate(eyes)), total=len(eyes), desc="cube maps"):
        with t.step("splat"):
            faces, vc = render_view(pts, c.colors, radii, eye, cfg.size, cfg.near, cfg.max_splat_px, nrm, gl_ctx)
        with t.step("coverage"):
            before = int(covered.sum())
            for f in range(6):
                seen, _, _ = visible_pixels(pts[oidx], vc["K"][f], vc["world_to_camera"][f], faces[f, :, :, 4],
                                            faces[f, :, :, 3], cfg.depth_tol, None if nrm_vis is None else nrm_vis[oidx],
                                            cfg.radius_tol * radii[oidx])
                covered |= seen
        with t.step("write"):
            write_faces(folder, faces, vi * 6, ["R", "G", "B", "A", "Z"])
        per_view.append({"eye": eye.tolist(), "new_overexposed_seen": int(covered.sum()) - before,
                         "pixel_coverage": float(faces[..., 3].mean())})
        if preview is not None:  # at most 256 px a face in the preview
            step = max(1, cfg.size // 256)
            crosses.append(cross_layout(faces[:, ::step, ::step, :4]))
    if gl_ctx is not None:
        gl_ctx.release()
    coverage = float(covered.mean())
    log.info("%d cube maps (%d faces, %d²): %.1f%% of the overexposed points seen", len(eyes), 6 * len(eyes),
             cfg.size, 100 * coverage)
    if coverage < cfg.coverage:
        log.warning("only %.1f%% of the overexposed points are seen by the cube maps (target %.1f%%, %s); "
                    "Poisson will fill the rest", 100 * coverage, 100 * cfg.coverage,
                    f"{len(eyes)} viewpoint(s) from the config" if cfg.viewpoints else f"max_views={cfg.max_views}")
    io.write_npz(folder.cameras, "pcrelight.cameras/1", **cams, **visibility_params(cfg))
    drop_stale(6 * len(eyes))
    if preview is not None:
        img = np.concatenate(crosses, axis=0)
        io.write_preview(preview, img)
    report.update({"views": int(len(eyes)), "faces": int(6 * len(eyes)), "viewpoints": eyes.tolist(),
                   "coverage": coverage, "per_view": per_view, "timings": t.as_dict(),
                   "seconds": time.perf_counter() - t0})
    io.write_json(folder.report, report)
    log.info("render-cubemaps done in %.2f s", time.perf_counter() - t0)
    return report
