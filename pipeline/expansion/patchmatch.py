"""patchmatch (seed 000 §4.1): expand the LDR cube-map faces to HDR.

``--method pmatch`` (default): generalized PatchMatch (Barnes, Shechtman, Goldman, Finkelstein 2010,
"The generalized PatchMatch correspondence algorithm") between every face S_i and photo_ldr, SSD
patch distance; the nearest-neighbour field (NNF) transfers the HDR values of photo.exr (same size
as photo_ldr, so the NNF's position indexes both).  ``--method landis|banterle|rhee`` expands the
faces with the inverse tone-mapping operators of :mod:`pipeline.expansion.itmo` instead — same outputs.

Outputs (folder OUT, contract with reproject)
---------------------------------------------
* ``face_{i:03d}.exr``: channels R, G, B (expanded HDR; multiply by ``scale`` of renderings.npz to
  get the cloud's units) and Q (quality).  **Q = mean squared difference per patch pixel and per
  channel between the source patch and the best target patch, both in sRGB-encoded [0, 1] LDR
  units** (``--space linear``: linear [0, 1] units), i.e. SSD / (3 · number of covered source pixels
  in the patch); so 0 ≤ Q ≤ 1.  Q = 0 for the operator methods; Q = 1e30 where nothing was matched
  (pixels without coverage, and with ``--only-over`` the covered pixels that are not overexposed,
  which keep their LDR colour / scale).
* ``renderings.npz`` (``pcrelight.renderings/1``): method, scale (α for pmatch since
  photo_ldr = clamp(α·photo, 0, 1); 1 for the operators), count, q_norm, matched_fraction,
  max_luminance; for pmatch also fit_fraction, fit_median_q, fit_ok (below); the photo and exposure.npz it
  read (``photo``/``exposure``: paths relative to the folder, with their SHA-256), which reproject takes
  when it is not given them.  ``report.json``: decisions, counts, timings, ``photo_fit``.

Does the photo fit? (pmatch)
-------------------------
The Q of every matched pixel, pooled over the faces: the fraction with Q ≤ ``fit_q`` (0.02) and the
median Q.  Measured (tiny and small ground truth, 128² faces): the room's own photo 63–73 % and
0.009–0.013 (also with a photo of another make-scene seed, which is the same room from a slightly
different pose); photos of something else (scikit-image's astronaut and coffee, linearised) 27 %
and 0.08–0.10.  With 64² faces the margin is thinner (tiny: own 52 % / 0.019, astronaut 30 % /
0.051): use faces of 128² or more (the demo uses 256²).  Below ``min_fit_fraction`` (45 %) or above ``max_fit_median_q`` (0.03): a WARNING
naming the figures; ``--strict`` makes it an error (exit 1, before renderings.npz is written).

The matcher
-----------
NNF per source pixel: target centre (x, y) in photo pixels (continuous, pixel centres at i + 0.5),
rotation θ and scale s: the source offset d maps to the target point c + s·R(θ)·d, sampled
bilinearly (edge-clamped).  Random initialisation over the whole photo, θ ∈ [−max_rotation,
max_rotation], log-uniform s ∈ [min_scale, max_scale].  Each iteration runs a **row pass** (every row
scanned left→right on even iterations, right→left on odd ones, rows in parallel) then a **column
pass** (top→bottom / bottom→top, columns in parallel).  At each pixel: *propagation* from the
previous pixel in scan order with the neighbour's transform (c_n + s_n R(θ_n)(p − n), accepted on
ties so coherent fields flood through flat saturated regions), then *random search* around the
current best with radius w·β^k (w = max photo side, β = ``beta``) in position and the same fraction
of the rotation and log-scale ranges, until the position radius is below 1 px.  Patches are
compared with early termination (a partial SSD above the best is dropped).

Coarse-to-fine (``--levels``, default 3): face and photo are halved (2×2 box; the face weighted by its
coverage) down to ``levels`` levels; the coarsest level starts from the random field, each finer level
from the parent's field up-sampled (the child keeps the parent's rotation/scale, its centre moved by
s·R(θ) of its offset) and searches locally (first radius 8 px).  Since a candidate is only accepted
when it is at least as good, the coarse level's context decides between equally good fine patches —
which matters for saturated (all-white) patches, which match every saturated photo region at SSD 0.

HDR transfer (``--vote``, default): patch voting (Wexler et al. 2007): the value of pixel p is the mean,
over the active patches covering p, of photo.exr at the point where each patch's transform sends p;
``--no-vote``: photo.exr at the pixel's own NNF centre (bilinear), as the paper describes.  Voting
averages the photo's noise (path-traced fireflies) where the field is coherent.

Determinism: within a pass the rows (or columns) are independent, each is scanned sequentially, and
every random number comes from a SplitMix64 hash of (seed, pixel index, iteration, pass, draw):
the result does not depend on thread scheduling — the same seed gives identical outputs.

Faces are mirror images of the camera's view (render-cubemaps: the GL cube-map convention); they are
flipped left-right before matching and the result flipped back (``--no-unmirror`` to disable).

Several photos (issue 25): when exposure.npz holds a set, each face is matched against every kept photo
(photo i's target clamp(α·k_i·photo_i), seed + 15485863·i) and a pixel keeps the match of lowest Q, its HDR value
in the reference photo's units (× k_i); the photos are those given (all of the set's) or the ones it records.

Model only what the scene requires: with ``--only-over`` (default) only the overexposed pixels
(LDR luminance > t_l), dilated by a margin of ``margin`` pixels for context and propagation, are
matched — the others are never projected by reproject.  A face without such pixels is skipped (log
line, report field); no face at all → outputs with count = 0.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numba import njit, prange

from . import itmo
from ..color import T_L, apply_exposure, luminance, srgb_encode
from ..config import StageConfig
from ..errors import ConfigError, InputError
from ..runtime import Timings, check_interrupt, get_logger, progress
from ..io.workspace import FaceFolder, read_face, write_faces

log = get_logger("patchmatch")

METHODS = ("pmatch", "landis", "banterle", "rhee")
Q_NONE = 1e30
Q_NORM = ("mean squared difference per covered patch pixel and channel, {space} [0,1] LDR units "
          "(SSD / (3 n)); 0 for operators; 1e30 = not matched")


@dataclass
class PatchmatchConfig(StageConfig):
    method: str = field(default="pmatch", metadata={
        "help": "pmatch = generalized PatchMatch against the photo; landis|banterle|rhee = inverse tone mapping",
        "choices": METHODS})
    iterations: int = field(default=5, metadata={"help": "PatchMatch iterations (each: a row and a column pass)"})
    patch_size: int = field(default=7, metadata={"help": "patch side [pixels, odd]"})
    vote: bool = field(default=True, metadata={
        "help": "HDR transfer by patch voting (mean over the patches covering a pixel) instead of the centre pixel"})
    levels: int = field(default=3, metadata={
        "help": "pyramid levels (coarse-to-fine; 1 = single-scale PatchMatch)"})
    beta: float = field(default=0.5, metadata={"help": "random-search radius ratio between draws (Barnes: 0.5)"})
    max_rotation: float = field(default=math.pi, metadata={"help": "rotation search range ±[radians]"})
    min_scale: float = field(default=0.25, metadata={"help": "smallest patch scale target/source [photo px per face px]"})
    max_scale: float = field(default=4.0, metadata={"help": "largest patch scale target/source [photo px per face px]"})
    space: str = field(default="srgb", metadata={
        "help": "space of the patch SSD: srgb (sRGB-encoded, perceptual) or linear", "choices": ("srgb", "linear")})
    only_over: bool = field(default=True, metadata={
        "help": "match only overexposed pixels (luminance > t_l) and a margin around them"})
    t_l: float = field(default=T_L, metadata={"help": "overexposure threshold on LDR luminance (the paper: 0.9)"})
    margin: int = field(default=8, metadata={"help": "dilation of the overexposed mask [pixels]"})
    unmirror: bool = field(default=True, metadata={
        "help": "flip faces left-right before matching (GL cube-map faces are mirror images)"})
    max_luminance: float = field(default=0.0, metadata={
        "help": "ITMO peak output [LDR units]; 0 = α·max Y(photo) from --photo/--exposure"})
    fit_q: float = field(default=0.02, metadata={
        "help": "photo fit: a matched pixel fits when its Q is ≤ this (Q as in the face EXRs)"})
    min_fit_fraction: float = field(default=0.45, metadata={
        "help": "photo fit: least fraction of the matched pixels that fit (measured with 128² faces: 0.63–0.73 for the room's own photo, 0.27 for photos of something else; 64² faces: 0.52 own, 0.30 other)"})
    max_fit_median_q: float = field(default=0.03, metadata={
        "help": "photo fit: largest median Q of the matched pixels (measured with 128² faces: 0.009–0.013 own photo, 0.08–0.10 another; 64²: 0.019 own, 0.051 other)"})
    strict: bool = field(default=False, metadata={
        "help": "a photo that does not fit the cloud's cube maps is an error (exit 1), not a warning"})

    def check(self) -> None:
        self._require(self.method in METHODS, "method", f"must be one of {METHODS}")
        self._require(0 <= self.iterations <= 1000, "iterations", "must be in [0, 1000]")
        self._require(self.patch_size >= 1 and self.patch_size % 2 == 1 and self.patch_size <= 63,
                      "patch_size", "must be odd, 1…63")
        self._require(1 <= self.levels <= 8, "levels", "must be in [1, 8]")
        self._require(0.0 < self.beta < 1.0, "beta", "must be in (0, 1)")
        self._require(0.0 <= self.max_rotation <= math.pi, "max_rotation", "must be in [0, π]")
        self._require(0.0 < self.min_scale <= 1.0, "min_scale", "must be in (0, 1]")
        self._require(self.max_scale >= 1.0, "max_scale", "must be ≥ 1")
        self._require(self.space in ("srgb", "linear"), "space", "must be srgb or linear")
        self._require(0.0 <= self.t_l < 1.0, "t_l", "must be in [0, 1)")
        self._require(self.margin >= 0, "margin", "must be ≥ 0")
        self._require(self.max_luminance == 0.0 or self.max_luminance >= 1.0, "max_luminance",
                      "must be 0 (auto) or ≥ 1")
        for n in ("fit_q", "max_fit_median_q"):
            self._require(getattr(self, n) > 0, n, "must be > 0")
        self._require(0.0 <= self.min_fit_fraction <= 1.0, "min_fit_fraction", "must be in [0, 1]")


# ===================================================================== numba kernels
_M64 = np.uint64(0xFFFFFFFFFFFFFFFF)


@njit(cache=True, inline="always")
def _splitmix(x):
    x = (x + np.uint64(0x9E3779B97F4A7C15))
    z = x
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@njit(cache=True, inline="always")
def _key(seed, pixel, it, pas):
    h = _splitmix(np.uint64(seed))
    h = _splitmix(h ^ np.uint64(pixel))
    h = _splitmix(h ^ np.uint64(it))
    return _splitmix(h ^ np.uint64(pas))


@njit(cache=True, inline="always")
def _u01(key, k):
    """k-th uniform in [0, 1) of the stream ``key``."""
    return float(_splitmix(key + np.uint64(k) * np.uint64(0xD1B54A32D192ED03)) >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@njit(cache=True, inline="always")
def _bilinear(T, x, y, c):
    """Sample T (H, W, C) at continuous (x, y) (pixel centres at i + 0.5), edge-clamped."""
    H, W = T.shape[0], T.shape[1]
    fx = x - 0.5
    fy = y - 0.5
    if fx < 0.0:
        fx = 0.0
    if fy < 0.0:
        fy = 0.0
    if fx > W - 1.0:
        fx = W - 1.0
    if fy > H - 1.0:
        fy = H - 1.0
    x0 = int(fx)
    y0 = int(fy)
    x1 = min(x0 + 1, W - 1)
    y1 = min(y0 + 1, H - 1)
    ax = fx - x0
    ay = fy - y0
    return ((T[y0, x0, c] * (1 - ax) + T[y0, x1, c] * ax) * (1 - ay)
            + (T[y1, x0, c] * (1 - ax) + T[y1, x1, c] * ax) * ay)


@njit(cache=True)
def patch_distance(S, M, T, px, py, tx, ty, theta, scale, half, cnt, best):
    """Normalised SSD between the source patch at pixel (px, py) and the target patch centred at the
    continuous point (tx, ty) with rotation theta and scale: sum over covered source pixels
    (M > 0) of the squared channel differences / (3 cnt).  Returns inf as soon as the partial sum
    exceeds ``best`` (early termination)."""
    H, W = S.shape[0], S.shape[1]
    cs = scale * math.cos(theta)
    sn = scale * math.sin(theta)
    limit = best * 3.0 * cnt
    acc = 0.0
    for dy in range(-half, half + 1):
        sy = py + dy
        if sy < 0 or sy >= H:
            continue
        for dx in range(-half, half + 1):
            sx = px + dx
            if sx < 0 or sx >= W or M[sy, sx] == 0:
                continue
            X = tx + cs * dx - sn * dy
            Y = ty + sn * dx + cs * dy
            for c in range(3):
                d = S[sy, sx, c] - _bilinear(T, X, Y, c)
                acc += d * d
        if acc > limit:
            return np.inf
    return acc / (3.0 * cnt)


@njit(cache=True)
def _clampc(v, lo, hi):
    return lo if v < lo else (hi if v > hi else v)


@njit(cache=True)
def _visit(S, M, A, T, cnt, nnf, dist, x, y, nx, ny, seed, it, pas, half, beta, rot, lsmin, lsmax, radius0):
    """Propagation from neighbour (nx, ny) (if active) then random search at pixel (x, y)."""
    H, W = S.shape[0], S.shape[1]
    Wt, Ht = T.shape[1], T.shape[0]
    c = cnt[y, x]
    if 0 <= nx < W and 0 <= ny < H and A[ny, nx] != 0:
        th = nnf[ny, nx, 2]
        sc = nnf[ny, nx, 3]
        ddx = x - nx
        ddy = y - ny
        cx = nnf[ny, nx, 0] + sc * (math.cos(th) * ddx - math.sin(th) * ddy)
        cy = nnf[ny, nx, 1] + sc * (math.sin(th) * ddx + math.cos(th) * ddy)
        cx = _clampc(cx, 0.5, Wt - 0.5)
        cy = _clampc(cy, 0.5, Ht - 0.5)
        d = patch_distance(S, M, T, x, y, cx, cy, th, sc, half, c, dist[y, x] * (1 + 1e-12) + 1e-300)
        if d <= dist[y, x]:
            nnf[y, x, 0] = cx
            nnf[y, x, 1] = cy
            nnf[y, x, 2] = th
            nnf[y, x, 3] = sc
            dist[y, x] = d
    key = _key(seed, y * W + x, it, pas)
    r = radius0
    k = 0
    lrange = lsmax - lsmin
    while r >= 1.0:
        frac = r / radius0
        cx = _clampc(nnf[y, x, 0] + r * (2.0 * _u01(key, k) - 1.0), 0.5, Wt - 0.5)
        cy = _clampc(nnf[y, x, 1] + r * (2.0 * _u01(key, k + 1) - 1.0), 0.5, Ht - 0.5)
        th = nnf[y, x, 2]
        if rot > 0.0:
            th = th + frac * rot * (2.0 * _u01(key, k + 2) - 1.0)
            if th > rot:
                th = rot if rot < math.pi else th - 2 * math.pi
            if th < -rot:
                th = -rot if rot < math.pi else th + 2 * math.pi
        ls = math.log(nnf[y, x, 3])
        if lrange > 0.0:
            ls = _clampc(ls + frac * lrange * (2.0 * _u01(key, k + 3) - 1.0), lsmin, lsmax)
        sc = math.exp(ls)
        d = patch_distance(S, M, T, x, y, cx, cy, th, sc, half, c, dist[y, x])
        if d < dist[y, x]:
            nnf[y, x, 0] = cx
            nnf[y, x, 1] = cy
            nnf[y, x, 2] = th
            nnf[y, x, 3] = sc
            dist[y, x] = d
        r *= beta
        k += 4


@njit(cache=True, parallel=True)
def _sweep(S, M, A, T, cnt, nnf, dist, seed, it, forward, vertical, half, beta, rot, lsmin, lsmax, radius0):
    """One propagation sweep: rows (``vertical`` False, pass 0) or columns (True, pass 1) in parallel,
    each scanned forward (propagating from the previous pixel) or backward."""
    H, W = S.shape[0], S.shape[1]
    lines = W if vertical else H
    length = H if vertical else W
    step = -1 if forward else 1
    v = 1 if vertical else 0          # integer arithmetic: numba's parfors mistype if-expressions here
    for j in prange(lines):
        for i in range(length):
            k = i if forward else length - 1 - i
            x = v * j + (1 - v) * k
            y = v * k + (1 - v) * j
            if A[y, x] == 0:
                continue
            _visit(S, M, A, T, cnt, nnf, dist, x, y, x + (1 - v) * step, y + v * step, seed, it, v, half, beta,
                   rot, lsmin, lsmax, radius0)


@njit(cache=True, parallel=True)
def _init(S, M, A, T, cnt, nnf, dist, seed, half, rot, lsmin, lsmax):
    H, W = S.shape[0], S.shape[1]
    Wt, Ht = T.shape[1], T.shape[0]
    for y in prange(H):
        for x in range(W):
            if A[y, x] == 0:
                dist[y, x] = np.inf
                continue
            key = _key(seed, y * W + x, 0xFFFFFFFF, 2)
            nnf[y, x, 0] = _u01(key, 0) * Wt
            nnf[y, x, 1] = _u01(key, 1) * Ht
            nnf[y, x, 2] = rot * (2.0 * _u01(key, 2) - 1.0)
            nnf[y, x, 3] = math.exp(lsmin + (lsmax - lsmin) * _u01(key, 3))
            dist[y, x] = patch_distance(S, M, T, x, y, nnf[y, x, 0], nnf[y, x, 1], nnf[y, x, 2],
                                        nnf[y, x, 3], half, cnt[y, x], np.inf)


@njit(cache=True, parallel=True)
def _init_given(S, M, A, T, cnt, nnf, dist, half):
    H, W = S.shape[0], S.shape[1]
    for y in prange(H):
        for x in range(W):
            dist[y, x] = np.inf if A[y, x] == 0 else patch_distance(
                S, M, T, x, y, nnf[y, x, 0], nnf[y, x, 1], nnf[y, x, 2], nnf[y, x, 3], half, cnt[y, x], np.inf)


@njit(cache=True, parallel=True)
def _covered_count(M, A, half):
    H, W = M.shape
    out = np.zeros((H, W), np.int32)
    for y in prange(H):
        for x in range(W):
            if A[y, x] == 0:
                continue
            n = 0
            for dy in range(-half, half + 1):
                for dx in range(-half, half + 1):
                    sy = y + dy
                    sx = x + dx
                    if 0 <= sy < H and 0 <= sx < W and M[sy, sx] != 0:
                        n += 1
            out[y, x] = n
    return out


def generalized_patchmatch(source: np.ndarray, target: np.ndarray, mask: np.ndarray | None = None,
                           active: np.ndarray | None = None, iterations: int = 5, patch_size: int = 7,
                           beta: float = 0.5, max_rotation: float = math.pi, min_scale: float = 0.5,
                           max_scale: float = 2.0, seed: int = 0, callback=None, init: np.ndarray | None = None,
                           search_radius: float | None = None):
    """Generalized PatchMatch from ``source`` (H, W, 3) to ``target`` (Ht, Wt, 3), float, same space.

    mask: (H, W) source pixels that carry colour (coverage; others do not enter any SSD);
    active: (H, W) pixels to match (default = mask; must be ⊆ mask).
    Returns (nnf (H, W, 4) float64 [x, y, θ, s] — target centre in pixels with centres at i + 0.5 —,
    dist (H, W) normalised SSD, inf where not active).  ``callback(it, nnf, dist)`` after each iteration.
    ``init``: a starting NNF (H, W, 4) instead of the random one (a candidate is only ever accepted
    when it is at least as good, so a perfect starting match stays at distance 0).
    ``search_radius``: first random-search radius [target pixels] (default: the target's longer side).
    """
    S = np.ascontiguousarray(source[..., :3], dtype=np.float64)
    T = np.ascontiguousarray(target[..., :3], dtype=np.float64)
    H, W = S.shape[:2]
    M = np.ones((H, W), np.uint8) if mask is None else np.ascontiguousarray(mask, dtype=np.uint8)
    A = M.copy() if active is None else (np.asarray(active, dtype=bool) & (M > 0)).astype(np.uint8)
    half = patch_size // 2
    cnt = _covered_count(M, A, half)
    nnf = np.zeros((H, W, 4), np.float64)
    nnf[..., 3] = 1.0
    dist = np.full((H, W), np.inf)
    lsmin, lsmax = math.log(min_scale), math.log(max_scale)
    radius0 = float(max(T.shape[0], T.shape[1])) if search_radius is None else float(search_radius)
    seed = int(seed) & 0xFFFFFFFFFFFFFFFF
    if init is None:
        _init(S, M, A, T, cnt, nnf, dist, np.uint64(seed), half, max_rotation, lsmin, lsmax)
    else:
        nnf[:] = init
        _init_given(S, M, A, T, cnt, nnf, dist, half)
    for it in range(iterations):
        check_interrupt()
        fwd = it % 2 == 0
        for vertical in (False, True):
            _sweep(S, M, A, T, cnt, nnf, dist, np.uint64(seed), it, fwd, vertical, half, beta, max_rotation,
                   lsmin, lsmax, radius0)
        if callback is not None:
            callback(it, nnf, dist)
    return nnf, dist


def _down2(img: np.ndarray, weight: np.ndarray | None = None) -> np.ndarray:
    """2×2 box down-sampling (edge-padded to even size); with ``weight`` a weighted mean (0 where
    the block has no weight)."""
    H, W = img.shape[:2]
    pad = ((0, H % 2), (0, W % 2)) + ((0, 0),) * (img.ndim - 2)
    x = np.pad(img, pad, mode="edge")
    if weight is None:
        return 0.25 * (x[0::2, 0::2] + x[1::2, 0::2] + x[0::2, 1::2] + x[1::2, 1::2])
    w = np.pad(weight.astype(np.float64), pad[:2], mode="edge")
    ws = w[0::2, 0::2] + w[1::2, 0::2] + w[0::2, 1::2] + w[1::2, 1::2]
    xw = x * w[..., None]
    num = xw[0::2, 0::2] + xw[1::2, 0::2] + xw[0::2, 1::2] + xw[1::2, 1::2]
    return np.where(ws[..., None] > 0, num / np.maximum(ws, 1e-300)[..., None], 0.0)


def _any2(mask: np.ndarray) -> np.ndarray:
    H, W = mask.shape
    m = np.pad(mask.astype(bool), ((0, H % 2), (0, W % 2)), mode="constant")
    return m[0::2, 0::2] | m[1::2, 0::2] | m[0::2, 1::2] | m[1::2, 1::2]


def upsample_nnf(nnf_c: np.ndarray, H: int, W: int, Ht: int, Wt: int) -> np.ndarray:
    """NNF of a 2× coarser level → (H, W, 4) initial NNF: each fine pixel takes its coarse parent's
    transform, its centre moved by s·R(θ) of its offset from the parent's centre (in fine pixels)."""
    ys, xs = np.mgrid[0:H, 0:W]
    yc = np.minimum(ys // 2, nnf_c.shape[0] - 1)
    xc = np.minimum(xs // 2, nnf_c.shape[1] - 1)
    par = nnf_c[yc, xc]
    dx = xs + 0.5 - (2 * xc + 1)
    dy = ys + 0.5 - (2 * yc + 1)
    th, sc = par[..., 2], par[..., 3]
    out = np.empty((H, W, 4))
    out[..., 0] = np.clip(2 * par[..., 0] + sc * (np.cos(th) * dx - np.sin(th) * dy), 0.5, Wt - 0.5)
    out[..., 1] = np.clip(2 * par[..., 1] + sc * (np.sin(th) * dx + np.cos(th) * dy), 0.5, Ht - 0.5)
    out[..., 2] = th
    out[..., 3] = sc
    return out


def pyramid_patchmatch(source: np.ndarray, target: np.ndarray, mask: np.ndarray | None = None,
                       active: np.ndarray | None = None, levels: int = 3, iterations: int = 5,
                       patch_size: int = 7, min_side: int = 16, seed: int = 0, refine_radius: float = 8.0, **kw):
    """Coarse-to-fine :func:`generalized_patchmatch`: both images are halved ``levels − 1`` times
    (fewer when a side would drop below ``min_side``), the coarsest level starts from the random
    field, each finer level from the up-sampled field of the level above (a candidate is accepted
    only if at least as good, so the context of the coarse level decides between equally good —
    e.g. saturated — patches); below the coarsest level the random search starts at
    ``refine_radius`` pixels (the parent's uncertainty), not at the whole photo.  Same arguments and
    result as :func:`generalized_patchmatch`."""
    S = np.asarray(source[..., :3], dtype=np.float64)
    T = np.asarray(target[..., :3], dtype=np.float64)
    M = np.ones(S.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    A = M.copy() if active is None else (np.asarray(active, bool) & M)
    pyr = [(S, M, A, T)]
    while len(pyr) < levels:
        S_, M_, A_, T_ = pyr[-1]
        if min(S_.shape[0], S_.shape[1], T_.shape[0], T_.shape[1]) // 2 < min_side:
            break
        pyr.append((_down2(S_, M_), _any2(M_), _any2(A_), _down2(T_)))
    nnf = dist = None
    for lev in range(len(pyr) - 1, -1, -1):
        S_, M_, A_, T_ = pyr[lev]
        init = None if nnf is None else upsample_nnf(nnf, S_.shape[0], S_.shape[1], T_.shape[0], T_.shape[1])
        nnf, dist = generalized_patchmatch(S_, T_, M_, A_, iterations, patch_size, seed=seed + 7919 * lev,
                                           init=init, search_radius=None if init is None else refine_radius, **kw)
    return nnf, dist


@njit(cache=True, parallel=True)
def _transfer(P, nnf, A, out):
    H, W = A.shape
    for y in prange(H):
        for x in range(W):
            if A[y, x] == 0:
                continue
            for c in range(3):
                out[y, x, c] = _bilinear(P, nnf[y, x, 0], nnf[y, x, 1], c)


@njit(cache=True, parallel=True)
def _vote(P, nnf, A, half, out):
    H, W = A.shape
    for y in prange(H):
        for x in range(W):
            if A[y, x] == 0:
                continue
            n = 0
            acc0 = 0.0
            acc1 = 0.0
            acc2 = 0.0
            for dy in range(-half, half + 1):
                qy = y - dy
                if qy < 0 or qy >= H:
                    continue
                for dx in range(-half, half + 1):
                    qx = x - dx
                    if qx < 0 or qx >= W or A[qy, qx] == 0:
                        continue
                    th = nnf[qy, qx, 2]
                    sc = nnf[qy, qx, 3]
                    X = nnf[qy, qx, 0] + sc * (math.cos(th) * dx - math.sin(th) * dy)
                    Y = nnf[qy, qx, 1] + sc * (math.sin(th) * dx + math.cos(th) * dy)
                    acc0 += _bilinear(P, X, Y, 0)
                    acc1 += _bilinear(P, X, Y, 1)
                    acc2 += _bilinear(P, X, Y, 2)
                    n += 1
            out[y, x, 0] = acc0 / n
            out[y, x, 1] = acc1 / n
            out[y, x, 2] = acc2 / n


def vote(photo_hdr: np.ndarray, nnf: np.ndarray, active: np.ndarray, patch_size: int) -> np.ndarray:
    """Patch voting (Wexler et al. 2007; the NNF reconstruction of PatchMatch): the HDR value of
    pixel p is the mean, over every active pixel q whose patch covers p, of the photo at the point
    where q's transform sends p (c_q + s_q R(θ_q)(p − q)).  (H, W, 3) float32; 0 where inactive.
    Averages out the photo's noise where the field is coherent; equals :func:`transfer` when the
    field is an exact similarity and the photo is linear."""
    P = np.ascontiguousarray(photo_hdr[..., :3], dtype=np.float64)
    out = np.zeros(nnf.shape[:2] + (3,), np.float64)
    _vote(P, np.ascontiguousarray(nnf), np.ascontiguousarray(active, dtype=np.uint8), patch_size // 2, out)
    return out.astype(np.float32)


def transfer(photo_hdr: np.ndarray, nnf: np.ndarray, active: np.ndarray) -> np.ndarray:
    """HDR values of the photo at the NNF's centres (bilinear), (H, W, 3) float32; 0 where inactive."""
    P = np.ascontiguousarray(photo_hdr[..., :3], dtype=np.float64)
    out = np.zeros(nnf.shape[:2] + (3,), np.float64)
    _transfer(P, np.ascontiguousarray(nnf), np.ascontiguousarray(active, dtype=np.uint8), out)
    return out.astype(np.float32)


# ===================================================================== per-face expansion
def to_space(rgb: np.ndarray, space: str) -> np.ndarray:
    x = np.clip(np.asarray(rgb, dtype=np.float64), 0.0, 1.0)
    return srgb_encode(x, np.float64) if space == "srgb" else x


def active_mask(rgb: np.ndarray, coverage: np.ndarray, cfg: PatchmatchConfig) -> np.ndarray:
    """Pixels to match: covered & (all, or overexposed dilated by cfg.margin)."""
    cov = coverage > 0
    if not cfg.only_over:
        return cov
    over = cov & (luminance(rgb, np.float64) > cfg.t_l)
    if cfg.margin > 0 and over.any():
        from scipy.ndimage import binary_dilation

        over = binary_dilation(over, structure=np.ones((3, 3), bool), iterations=cfg.margin)
    return over & cov


def expand_face_pmatch(face_rgb, coverage, photo_ldr_s, photo_hdr, alpha, cfg: PatchmatchConfig, seed: int):
    """One face: (hdr (H, W, 3) in photo units, q (H, W), active count, nnf)."""
    act = active_mask(face_rgb, coverage, cfg)
    H, W = coverage.shape
    hdr = (np.clip(face_rgb, 0, None) / alpha).astype(np.float32)
    hdr[coverage <= 0] = 0.0
    q = np.full((H, W), Q_NONE, np.float32)
    if not act.any():
        return hdr, q, 0, None
    S = to_space(face_rgb, cfg.space)
    M = (coverage > 0)
    if cfg.unmirror:
        S, M, act_m = S[:, ::-1], M[:, ::-1], act[:, ::-1]
    else:
        act_m = act
    nnf, dist = pyramid_patchmatch(S, photo_ldr_s, M, act_m, cfg.levels, cfg.iterations, cfg.patch_size,
                                   seed=seed, beta=cfg.beta, max_rotation=cfg.max_rotation,
                                   min_scale=cfg.min_scale, max_scale=cfg.max_scale)
    vals = vote(photo_hdr, nnf, act_m, cfg.patch_size) if cfg.vote else transfer(photo_hdr, nnf, act_m)
    if cfg.unmirror:
        vals, dist, nnf = vals[:, ::-1], dist[:, ::-1], nnf[:, ::-1]
    hdr[act] = vals[act]
    q[act] = dist[act].astype(np.float32)
    return hdr, q, int(act.sum()), nnf


def expand_face_itmo(face_rgb, coverage, method, max_luminance):
    cov = coverage > 0
    out = itmo.apply(method, np.where(cov[..., None], face_rgb, 0.0), max_luminance=max_luminance)
    out[~cov] = 0.0
    q = np.where(cov, 0.0, Q_NONE).astype(np.float32)
    return out.astype(np.float32), q


def photo_fit(q: np.ndarray, cfg: PatchmatchConfig) -> dict:
    """Does the photo show the scanned scene?  From the Q of every matched face pixel (pooled over
    the faces): the fraction with Q ≤ ``fit_q`` and the median Q, against ``min_fit_fraction`` and
    ``max_fit_median_q``.  ``ok`` and ``problems`` (one phrase per failed figure); with no matched
    pixel there is nothing to judge (ok, figures None)."""
    q = np.asarray(q, np.float64)
    if q.size == 0:
        return dict(fit_fraction=None, median_q=None, matched=0, ok=True, problems=[])
    frac, med = float(np.mean(q <= cfg.fit_q)), float(np.median(q))
    problems = []
    if frac < cfg.min_fit_fraction:
        problems.append(f"only {100 * frac:.1f}% of the {q.size} matched pixels have Q ≤ {cfg.fit_q:g} "
                        f"(at least {100 * cfg.min_fit_fraction:.0f}% expected)")
    if med > cfg.max_fit_median_q:
        problems.append(f"median Q {med:.3g} > {cfg.max_fit_median_q:g}")
    return dict(fit_fraction=frac, median_q=med, matched=int(q.size), ok=not problems, problems=problems)


# ===================================================================== the action
def run_patchmatch(cubemaps, photo, photo_ldr, exposure, out, cfg: PatchmatchConfig, preview=None) -> dict:
    """Read DIR (cameras.npz + faces) [+ photo.exr, photo_ldr.exr, exposure.npz]; write OUT (faces with
    R,G,B,Q; renderings.npz; report.json); ``preview``: PNG contact sheet of the expanded faces."""
    from .. import io

    cfg.check()
    t = Timings()
    cubemaps, out = FaceFolder(cubemaps), FaceFolder(out)
    cams_path = cubemaps.cameras
    with t.step("read"):
        if not cubemaps.path.is_dir():
            raise InputError(cubemaps.path, "no such folder (expected render-cubemaps output)")
        cams = io.read_npz(cams_path, "pcrelight.cameras/1")
        F = int(cams["K"].shape[0])
        alpha = None
        given = [] if photo is None else [photo] if isinstance(photo, (str, Path)) else list(photo)
        if len(given) > 1 or any(Path(p).is_dir() for p in given):
            from .photo_set import expand_photos

            given = expand_photos(given)
        photo = given[0] if len(given) == 1 else None if not given else photo
        pset = None
        if exposure is not None:
            ex = io.read_npz(exposure, "pcrelight.exposure/1")
            alpha = float(ex["alpha"])
            if not (np.isfinite(alpha) and alpha > 0):
                raise InputError(exposure, f"alpha must be finite and > 0, got {alpha}")
            from .photo_set import read_set

            n_set = len(np.atleast_1d(ex["photos"])) if "photos" in ex else 0
            if n_set and given and len(given) != n_set:
                log.warning("%d photo(s) given, %s records a set of %d: the recorded ones are used", len(given),
                            exposure, n_set)
            pset = read_set(ex, exposure, given if len(given) == n_set else None)
            if pset is not None:
                pset = [c for c in pset if c.kept]
                photo = pset[0].path
        if pset is None and len(given) > 1:
            raise InputError(exposure, "records one photo (an expose-match of one photo), several --photo given: "
                                       "run expose-match on the set")
        P = None
        if photo is not None:
            P = io.read_image(photo)
            if P.shape[2] < 3:
                raise InputError(photo, f"expected an RGB image, got {P.shape[2]} channel(s)")
            P = P[..., :3]
            if not np.all(np.isfinite(P)):
                raise InputError(photo, "photo has non-finite pixels (NaN or Inf)")
            P = np.maximum(P, 0.0)
    log.info("read %s: %d faces in %d view(s)", cams_path, F, int(cams["eye"].shape[0]))
    method = cfg.method
    report: dict = dict(stage="patchmatch", method=method, config=cfg.as_dict(),
                        inputs=dict(cubemaps=str(cubemaps.path), photo=str(photo) if photo else None,
                                    photo_ldr=str(photo_ldr) if photo_ldr else None,
                                    exposure=str(exposure) if exposure else None),
                        q_norm=Q_NORM.format(space=cfg.space), faces=[])
    max_lum = 0.0
    if method == "pmatch":
        if P is None or alpha is None:
            raise ConfigError("--method pmatch needs --photo (photo.exr) and --exposure (exposure.npz)")
        if photo_ldr is not None:
            L = io.read_image(photo_ldr)[..., :3]
            if L.shape[:2] != P.shape[:2]:
                raise InputError(photo_ldr, f"size {L.shape[1]}x{L.shape[0]} differs from the photo's "
                                            f"{P.shape[1]}x{P.shape[0]}")
            ldr_src = "photo_ldr.exr"
        else:
            L = apply_exposure(P, alpha)
            ldr_src = "Eq. 1 of photo with exposure.npz's alpha (no --photo-ldr)"
        log.info("photo %dx%d, α = %.6g; target = %s", P.shape[1], P.shape[0], alpha, ldr_src)
        T = to_space(L, cfg.space)
        scale = alpha
        targets = [(P, T, alpha, 1.0)]
        if pset is not None and len(pset) > 1:
            for c in pset[1:]:
                Pc = np.maximum(io.read_image(c.path)[..., :3], 0.0)
                if not np.all(np.isfinite(Pc)):
                    raise InputError(c.path, "photo has non-finite pixels (NaN or Inf)")
                targets.append((Pc, to_space(apply_exposure(Pc, alpha * c.k), cfg.space), alpha * c.k, c.k))
            log.info("%d photos: each face matched against each; a pixel takes the photo whose patch matches best "
                     "(lowest Q), in the reference photo's units (× k_i)", len(targets))
    else:
        if cfg.max_luminance > 0:
            max_lum = cfg.max_luminance
            how = "--max-luminance"
        elif P is not None and alpha is not None:
            max_lum = itmo.photo_peak(P, alpha)
            how = "α·max Y(photo)"
        else:
            raise ConfigError(f"--method {method} needs --max-luminance or --photo and --exposure "
                              "(its peak α·max Y(photo) sets the operator's output range)")
        if method == "rhee":
            log.info("ITMO rhee (seed 002: fixed gain 10·L^10 + 1.8; no peak parameter)")
        else:
            log.info("ITMO %s with peak output %.4g LDR units (%s)", method, max_lum, how)
        report["max_luminance"] = max_lum
        scale = 1.0
    out.path.mkdir(parents=True, exist_ok=True)
    matched_fraction = np.zeros(F, np.float64)
    matched_q: list[np.ndarray] = []
    sheets = []
    for i in progress(range(F), total=F, desc="patchmatch faces"):
        with t.step("read"):
            face = read_face(cubemaps, i, ["R", "G", "B", "A"])
            rgb, cov = face[..., :3].astype(np.float64), face[..., 3]
            if not np.all(np.isfinite(rgb)):
                raise InputError(cubemaps.face(i), "face has non-finite colours")
        covered = int((cov > 0).sum())
        over = int(((cov > 0) & (luminance(rgb, np.float64) > cfg.t_l)).sum())
        finfo = dict(face=i, covered=covered, overexposed=over)
        if method == "pmatch":
            if cfg.only_over and over == 0:
                hdr = (np.clip(rgb, 0, None) / alpha).astype(np.float32)
                hdr[cov <= 0] = 0
                q = np.full(cov.shape, Q_NONE, np.float32)
                finfo.update(skipped="no overexposed pixel", matched=0)
                log.info("face %03d: %d covered, no overexposed pixel — skipped", i, covered)
            else:
                with t.step("patchmatch"):
                    hdr, q, n_act, _ = expand_face_pmatch(rgb, cov, T, P, alpha, cfg, cfg.seed * 1000003 + i)
                    for n, (Pn, Tn, an, kn) in enumerate(targets[1:], start=1):   # the set's other photos
                        hn, qn, _, _ = expand_face_pmatch(rgb, cov, Tn, Pn, an, cfg, cfg.seed * 1000003 + i + 15485863 * n)
                        better = qn < q
                        hdr[better], q[better] = hn[better] * np.float32(kn), qn[better]
                finfo.update(matched=n_act, q_median=float(np.median(q[q < Q_NONE])) if n_act else None)
                log.info("face %03d: %d covered, %d overexposed, %d matched, median Q %.4g", i, covered, over,
                         n_act, finfo["q_median"] or 0.0)
            matched_fraction[i] = float(((q < Q_NONE) & (cov > 0)).sum()) / max(covered, 1)
            matched_q.append(q[(q < Q_NONE) & (cov > 0)])
        else:
            with t.step("itmo"):
                hdr, q = expand_face_itmo(rgb, cov, method, max_lum)
            finfo.update(matched=covered)
            matched_fraction[i] = 1.0 if covered else 0.0
        with t.step("write"):
            write_faces(out, [np.dstack([hdr, q]).astype(np.float32)], i, ["R", "G", "B", "Q"])
        if preview and i < 6:
            sheets.append(np.dstack([hdr * scale, (cov > 0).astype(np.float32)]))
        report["faces"].append(finfo)
    fit_keys = {}
    if method == "pmatch":
        fit = photo_fit(np.concatenate(matched_q) if matched_q else np.zeros(0), cfg)
        report["photo_fit"] = fit
        if fit["matched"]:
            fit_keys = dict(fit_fraction=np.float64(fit["fit_fraction"]), fit_median_q=np.float64(fit["median_q"]),
                            fit_ok=np.int32(fit["ok"]))
            log.info("photo fit: %.1f%% of %d matched pixels with Q ≤ %g, median Q %.4g → %s", 100 * fit["fit_fraction"],
                     fit["matched"], cfg.fit_q, fit["median_q"], "the photo fits" if fit["ok"] else "DOES NOT FIT")
        if not fit["ok"]:
            msg = (f"the photo does not fit the cloud's cube maps ({'; '.join(fit['problems'])}): "
                   "is it a photo of this scene?")
            if cfg.strict:
                raise InputError(photo, msg + " (--strict)")
            log.warning("%s: %s; the expansion goes on (--strict makes this an error)", photo, msg)
    used = {}  # the photo and exposure read here, recorded for reproject (run by hand, it is told neither)
    for name, given in (("photo", photo), ("exposure", exposure)):
        if given is not None:
            rel, digest = io.file_ref(given, out.path)
            used.update({name: np.asarray(rel), f"{name}_sha256": np.asarray(digest)})
    with t.step("write"):
        io.write_npz(out.renderings, "pcrelight.renderings/1", method=np.asarray(method),
                     scale=np.float64(scale), count=np.int32(F), q_norm=np.asarray(Q_NORM.format(space=cfg.space)),
                     matched_fraction=matched_fraction, max_luminance=np.float64(max_lum), **fit_keys, **used)
        if preview and sheets:
            h, w = sheets[0].shape[:2]
            canvas = np.zeros((2 * h, 3 * w, 4), np.float32)
            for k, s in enumerate(sheets):
                if s.shape[:2] == (h, w):
                    canvas[(k // 3) * h:(k // 3 + 1) * h, (k % 3) * w:(k % 3 + 1) * w] = s
            io.write_preview(preview, canvas)
    report.update(count=F, scale=scale, timings=t.as_dict(),
                  outputs=dict(folder=str(out.path), renderings=str(out.renderings)))
    if F == 0:
        log.info("no faces in %s (no overexposed point to expand): empty renderings", cubemaps.path)
        report["skipped"] = "no faces"
    io.write_json(out.report, report)
    log.info("wrote %d face(s) to %s (method %s, scale %.6g) in %.2f s", F, out.path, method, scale, t.total)
    return report
