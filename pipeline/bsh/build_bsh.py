"""build-bsh (seed 000 §5.1, §5.4; DESIGN stage 6): the bounding sphere hierarchy of a point cloud.

Steps (timed separately):

1. **morton** — the points' bounding box is cubed (side = its largest extent, min corner kept) and
   cut into 2^bits cells an axis; each point gets the 64-bit Morton code of its cell
   (x in the highest bit of each triple).
2. **sort** — stable LSD radix argsort of the codes (numba), ties in input order.
3. **leaves**, **spacing** — one leaf per non-empty cell (voxel). A leaf holds the point-count-weighted
   (= equal-weight) means of its points' positions and colours; its normal cone is the exact
   minimum cone of its points' normals; its sphere is centred on the mean position with radius
   ``max(distance to its farthest point, splat radius)``. The splat radius is
   ``d4 / sqrt(2)``, d4 = the distance to the 4th-nearest other leaf centre among the 16 previous
   and 16 next leaves in Morton order (an upper bound of the true 4-NN distance): on a regular
   grid of spacing s, d4 = s and the discs of radius s/sqrt(2) cover the surface without gaps;
   on uniform random samples each splat covers about twice its share of area. Relight splats
   leaves with this radius, so a one-point leaf is not a zero-sized sphere. A cloud that is a
   single voxel has no neighbour: its radius is that of its points (0 if they coincide).
   **Isolated leaves** (``isolated``, default 2; :func:`pipeline.bsh.tree.shrink_isolated_leaves`, the same as
   :func:`pipeline.expansion.splats.shrink_isolated` on a grid of the leaves' codes): a leaf whose spacing
   exceeds 2 × the median spacing of its 16 nearest leaves samples an object smaller than the point
   spacing (a lamp) and takes that median / sqrt(2): its disc is its share of area, not the size of
   the far surface its 4th neighbour lies on (a lamp room's exact cloud relit 5.6× → 1.04×).
4. **karras** — inner nodes by Karras 2012 over the sorted leaf codes (one parallel task per
   inner node, common prefixes of (code, index) so duplicate codes are broken by index).
5. **bottom_up** — children before parents:
   * colour = mean of the node's points = children's colours weighted by their point counts.
     (The paper averages the two children plainly; as the cloud is sampled uniformly by area,
     the point-count weighting gives the area mean of the radiance, which a plain average of
     children of unequal size does not.)
   * sphere = the minimum sphere containing both children's spheres (closed form: the exact
     smallest enclosing ball of two balls, which is what Fischer–Gärtner 2003 returns for them).
     As the parent must contain its children, no conservative sphere is smaller. Centres are
     rounded to float32 first, then the radius is recomputed in float64 and rounded up to
     float32, so the *stored* parent contains the *stored* children exactly.
   * normal cone = the exact minimum cone (Welzl on the sphere) of the node's point normals on
     the first level above the leaves and for any node over at most ``exact_cone_max`` leaves
     (voxels: duplicated points change no cone); above, the exact minimum cone containing the
     two children's cones (its axis lies on the great circle through theirs), instead of the
     paper's four-border-vector approximation. A cone of half-angle ≥ π/2 culls nothing and is
     stored as the full sphere.
6. **prune_linearise** — depth-first pre-order (left child = next node); every top-most inner
   node passing §5.1's test becomes a leaf ("cluster") keeping its point range, mean colour,
   sphere (containing all its points) and cone (containing all its normals). Test: the mean
   (paper; ``prune_stat="max"``: the largest) linear-RGB distance of its points' colours to the
   node colour is < t_c, and the mean dot of its points' unit normals with the node's mean
   normal (their normalised sum) is > t_n. The command's ``--tc`` is a multiple of the cloud's median luminance
   (:func:`prune_threshold`: radiance × c builds the same tree); :func:`build_bsh` takes the absolute t_c.
7. **pack** — the 40-byte node of §5.4 with ``right`` and ``skip`` (stackless walk: visit i,
   go to i+1 to descend, to skip[i] to skip), the cone packed RGBA8 and widened so that the
   decoded cone contains the true one; and ``splat_radius`` (:func:`splat_radii`): the radius relight
   splats a node with, its sphere's radius capped at the area of its voxels' splats (sparse and mixed
   nodes and clusters shrink; the sphere stays the bound of the stop rule and the culls), that area
   taken at ``closed_share`` (1/8) for the part of a node whose normals point all round
   (:func:`closure_share`: a lamp shows a quarter of its area from any side, not its bounding sphere) when
   the node is brighter than ``closed_contrast`` (30) × the cloud's median luminance: a dark closed node (a
   roof beam) is an occluder first, and shrunk it let the sun through.
8. **emitters** (``emitters``, default compact; :func:`compact_bright`, :func:`split_emitters`) — the isolated
   voxel leaves that are leaves of the tree, and the leaves of small bright objects wherever they sit
   (brighter than ``closed_contrast`` × the median, within ``emitter_size`` typical splat radii of their
   centroid: a lamp of a few to twenty points, not the sun's disc or a sunlit floor), become ``emitters``
   (E, 12): relight's Eq. 9 adds each as its share of its object's area — a quarter of it from any side for
   the object's closed part, once to one side for its flat share |Σ n| / n (0 for isolated points) — where
   its micro-buffer holds nothing nearer; their leaves splat nothing and every node's colour counts their
   points black. A 4 cm lamp is far below a micro-buffer texel: splatted, it lit a whole texel or none, and
   receivers caught it or missed it. A compact object's emitter disc is its leaf's splat radius / sqrt(2)
   (the splat holds about twice a point's share, step 3). Lamp room (one lamp's 8 points were not
   isolated), exact cloud, view1 Lambert, m 24: mean 1.121 → 1.018, 4×4 block RMS 0.31 → 0.046
   (bench/README.md). Where a compact object's points and normals fit a sphere (:func:`sphere_fit`), its
   emitters share the sphere's area 4π r² (closed) instead, and a one-point object of the same radiance
   (nothing to fit) is taken for one more of those fixtures (lamp room 512²: bench/README.md).
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from . import tree as core
from .format import CONE_PACK_SLACK, DERIVED_KEYS, NODE_DTYPE
from ..color import luminance, radiance_scale
from ..config import StageConfig
from ..errors import InputError
from ..runtime import Timings, check_interrupt, get_logger

log = get_logger("build-bsh")

SCHEMA = "pcrelight.bsh/1"
SPLAT_K = 4          # splat radius from the distance to the 4th-nearest leaf (fixed in the kernel) …
SPLAT_WINDOW = 16    # … among 16 + 16 Morton neighbours
SPLAT_SCALE = 1.0 / math.sqrt(2.0)
MAX_EMITTERS = 16384  # Eq. 9 loops over every emitter per receiver (llvmpipe stops a loop after 65 535 iterations)
SHIFT2 = np.array([1 / math.pi, 1 / math.e, 1 / math.sqrt(50.0)])  # second Morton order's offset [cube sides]


@dataclass
class BuildBshConfig(StageConfig):
    """Options of build-bsh (seed 000 §5.1)."""

    bits: int = field(default=21, metadata={"help": "Morton bits per axis (1..21); 2^bits cells an axis over the cubed bounding box"})
    tc: float = field(default=0.08, metadata={
        "help": "pruning colour threshold t_c [× the cloud's median luminance (color.radiance_scale): a linear RGB "
                "distance in the cloud's own radiance unit, so that the BSH does not depend on that unit]; 0.08 is the "
                "former absolute 0.01 on the shipped sample (median 0.119)"})
    tn: float = field(default=0.98, metadata={"help": "pruning normal threshold t_n [mean dot product, -1..1]"})
    prune: bool = field(default=True, metadata={"help": "prune sub-trees of similar colour and normal into clusters (§5.1)"})
    prune_stat: str = field(default="mean", metadata={"help": "colour statistic compared with t_c: mean (paper) or max distance to the node colour", "choices": ("mean", "max")})
    exact_cone_max: int = field(default=64, metadata={"help": "nodes over at most this many leaves (voxels) get the exact minimum normal cone of their points"})
    preview_depth: int = field(default=6, metadata={"help": "tree depth of the spheres drawn in the preview"})
    isolated: float = field(default=2.0, metadata={
        "help": "a leaf whose spacing exceeds this × the median spacing of its 16 nearest leaves samples an object "
                "smaller than the point spacing (a lamp): its spacing becomes that median / sqrt(2), so its disc is "
                "its share of area, not twice it (0: off). A lamp room's exact cloud relit went from 5.6× / 7.7× to "
                "1.04× / 1.07× the path tracer; the small sample moved by < 0.1 % (bench/README.md)"})
    closed_contrast: float = field(default=30.0, metadata={
        "help": "--closed-share applies to nodes brighter than this × the cloud's median luminance (a lamp; small "
                "sample: 3.6, its walls < 3, lamps 30–1000); darker closed nodes (roof beams, columns) keep their splat "
                "and hide what lies behind them — shrunk, the beams let the sun through (16², stop 1: per-pixel error "
                "0.08 → 0.54; 0 = every node)"})
    emitters: str = field(default="compact", metadata={
        "help": "isolated: the isolated leaves (--isolated; objects below the point spacing, a lamp) leave the splat "
                "walk and are added by the final gather as compact objects (a quarter of their disc's area from any "
                "side), visible where the micro-buffer's depth lies behind them (a sub-texel splat lit a whole texel "
                "or none: the lamp room's block RMS); compact: those and the leaves of every small bright object "
                "(brighter than --closed-contrast × the median, its bright points within --emitter-size splat "
                "radii of their centre: a lamp of a few points; where its points and normals fit a sphere, its "
                "emitters hold the sphere's area 4π r², and a one-point object of the same radiance takes that "
                "area); none: "
                "they are splatted like every leaf", "choices": ("compact", "isolated", "none")})
    emitter_size: float = field(default=2.0, metadata={
        "help": "--emitters compact: largest radius of a bright object made emitters [typical splat radii: the "
                "median leaf spacing / sqrt(2)]; its bright points are linked within 3 of them (small sample: lamps "
                "1.3–1.5, the sun's disc 4.7, the sunlit floor 46)"})
    closed_share: float = field(default=0.125, metadata={
        "help": "share of its voxels' splat area a closed node (a lamp, a knob: normals all round) splats with: it "
                "shows a quarter of its area from any side and the leaf splats hold twice it, 1/8; a node is split into "
                "a flat part (|Σ a·n| / Σ a) splatted whole and a closed part splatted at this share (1: off). The "
                "small sample's exact cloud relit, view1 Lambert m 24: 1.040 → 1.018 (bench/README.md)"})

    def check(self) -> None:
        self._require(1 <= self.bits <= 21, "bits", "must be in 1..21")
        self._require(not math.isnan(self.tc) and self.tc >= 0, "tc", "must be ≥ 0")
        self._require(-1.0 <= self.tn <= 1.0, "tn", "must be in [-1, 1]")
        self._require(self.prune_stat in ("mean", "max"), "prune_stat", "must be mean or max")
        self._require(self.exact_cone_max >= 2, "exact_cone_max", "must be ≥ 2")
        self._require(self.preview_depth >= 0, "preview_depth", "must be ≥ 0")
        self._require(self.isolated == 0 or self.isolated >= 1, "isolated", "must be 0 (off) or ≥ 1")
        self._require(0 < self.closed_share <= 1, "closed_share", "must be in (0, 1]")
        self._require(self.emitters in ("compact", "isolated", "none"), "emitters", "must be compact, isolated or none")
        self._require(self.emitter_size > 0, "emitter_size", "must be > 0")
        self._require(self.closed_contrast >= 0, "closed_contrast", "must be ≥ 0")


# ----------------------------------------------------------------------------- pure functions
def check_inputs(points: np.ndarray, normals: np.ndarray, colors: np.ndarray, where: str = "<cloud>") -> np.ndarray:
    """Validate the arrays (InputError naming ``where``) and return float32 unit normals."""
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] == 0:
        raise InputError(where, f"points must be a non-empty (N,3) array, got shape {p.shape}")
    n = p.shape[0]
    for name, a in (("normals", normals), ("colors", colors)):
        if np.shape(a) != (n, 3):
            raise InputError(where, f"{name} must be ({n},3), got {np.shape(a)}")
    bad_p, bad_n, zero_n, bad_c, unit = core.check_normalise(
        np.ascontiguousarray(points, dtype=np.float32), np.ascontiguousarray(normals, dtype=np.float32),
        np.ascontiguousarray(colors, dtype=np.float32))
    for cnt, what in ((bad_p, "non-finite positions (NaN or Inf)"), (bad_n, "non-finite normals (NaN or Inf)"),
                      (zero_n, "zero-length normals"), (bad_c, "non-finite colours (NaN or Inf)")):
        if cnt:
            raise InputError(where, f"{cnt} points have {what}")
    return unit


def leaf_spacing(cen: np.ndarray, lo: np.ndarray, side: float) -> np.ndarray:
    """Approximate 4th-nearest-leaf distance of each leaf [m] (leaves in Morton order): see
    :func:`pipeline.bsh.tree.leaf_spacing`; the second Morton order is that of the centres
    shifted by ``SHIFT2 * side`` in a cube of side ``2 * side``."""
    L = cen.shape[0]
    if L < 2:
        return np.zeros(L)
    lo2 = np.asarray(lo, dtype=np.float64) - SHIFT2 * side
    # the centres are float32 values: the float32 kernel specialisation gives the same codes
    codes2 = core.morton_codes(cen.astype(np.float32), lo2, float(2 ** 21) / (2.0 * side), 21)
    perm2, _ = core.radix_argsort(codes2, 63)
    return core.leaf_spacing(cen, perm2, SPLAT_WINDOW)


def splat_radii(radius: np.ndarray, leaf_r2: np.ndarray) -> np.ndarray:
    """(M,) float32 splat radius of every BSH node [m]: ``min(radius, sqrt(leaf_r2))``, ``leaf_r2`` (M,) = Σ r² of
    the voxel leaves (step 3) holding the node's points — the disc relight's micro-buffers splat for the node
    (not a cloud point's disc: that is :func:`pipeline.expansion.splats.knn_splat_radii`).

    A voxel leaf splats with its radius (its splat disc covers about twice its points' share of area, step
    3); any larger node — inner node or pruned cluster — may cover at most the area of its voxels' splats
    together (π Σ r², again ≈ 2× its points' area). For a filled patch that is at least its bounding
    sphere's cross-section (no change); for a sparse or mixed node (a lamp or the sun with a bit of wall, a
    thin shaft, two patches far apart) the bounding sphere is several times its points' area, and
    splatting it whole gave its area-mean colour that much too much solid angle (measured on the shipped
    scene: bench/README.md, relight vs truth). ``radius`` stays the bound of the stop rule and the culls."""
    return np.minimum(radius.astype(np.float64), np.sqrt(np.maximum(leaf_r2, 0.0))).astype(np.float32)


def node_sums(values: np.ndarray, first: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Σ of ``values`` ((N,) or (N, k), per sorted point) over each node's points ``[first, first + count)``
    (prefix sums, float64)."""
    v = np.asarray(values, np.float64)
    s = core.range_sums(np.ascontiguousarray(v.reshape(v.shape[0], -1)), np.asarray(first, np.int64),
                        np.asarray(count, np.int64))
    return s.reshape((s.shape[0],) + v.shape[1:])


def closure_share(normals: np.ndarray, weight: np.ndarray, first: np.ndarray, count: np.ndarray,
                  closed_share: float) -> np.ndarray:
    """(M,) factor ``c + (1 − c)·closed_share`` on the splat area (Σ r² of the voxel leaves) of the nodes
    holding the sorted points ``[first, first + count)``.

    ``weight`` (N,) is each sorted point's share of its voxel's splat area; c = |Σ w·n| / Σ w ∈ [0, 1] is
    the node's flat share (1: a patch; 0: normals all round, a lamp or a knob). The flat part keeps its
    area (a splat shows a patch whole); the rest is taken as a closed surface, which shows a quarter of
    its area from any direction (Cauchy), while the leaf splats hold about twice its area: hence
    ``closed_share`` = 1/8. A node is splatted as one sphere only when it is small in the receiver's view
    (§5.3's stop rule); without the factor a lamp's node splats its bounding sphere, 5.9× the lamp's
    cross-section (test_bsh). build_bsh applies it to nodes brighter than ``closed_contrast`` × the cloud's
    median luminance only. Relit exact cloud, small sample, view1 Lambert m 24: 1.040 → 1.018 × the path
    tracer; its lamps (0.12 m spheres of ~12 points, 0.5 % of the light) 4.4× → 1.65× (bench/README.md)."""
    return core.closure_factor(np.ascontiguousarray(normals), np.ascontiguousarray(weight, np.float64),
                               np.asarray(first, np.int64), np.asarray(count, np.int64), float(closed_share))


def split_emitters(iso_leaf: np.ndarray, lfirst: np.ndarray, lcount: np.ndarray, lcen: np.ndarray, lrad: np.ndarray,
                   lcol: np.ndarray, lnsum: np.ndarray, C: np.ndarray, nfirst: np.ndarray,
                   ncount: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The emitter voxel leaves (``iso_leaf``: isolated, or of a small bright object) as emitters, and the
    node colours without them.

    Returns (emitters (E, 12) float32: centre xyz [m], disc radius [m], unit normal xyz, flat share (0 here;
    the caller sets it), radiance RGB, 0 — three std430 vec4 per emitter, the ``emitters`` array of
    bsh.npz; colour (M, 3) float32: each node's mean colour with its emitter points counted black, so
    relight's walk, which no longer splats them, and its emitter gather do not count them twice). The disc
    radius is ``lrad``'s (the leaf's share of area: after ``isolated``, or its splat radius / sqrt(2)); its
    normal the mean of its points' normals. ``C`` (N, 3) is the sorted points' colours."""
    j = np.flatnonzero(iso_leaf)
    ns = np.asarray(lnsum, np.float64)[j]
    ln = np.linalg.norm(ns, axis=1, keepdims=True)
    nrm = np.where(ln > 1e-12, ns / np.maximum(ln, 1e-300), np.array([[0.0, 0.0, 1.0]]))
    emit = np.zeros((len(j), 12), np.float32)
    emit[:, 0:3] = lcen[j]
    emit[:, 3] = lrad[j]
    emit[:, 4:7] = nrm
    emit[:, 8:11] = lcol[j]
    is_emit = np.repeat(np.asarray(iso_leaf, bool), lcount)
    # summed again without them (not subtracted from ``color``: a lamp 10⁴ × the wall cancels in float32)
    col = core.masked_mean_colour(np.ascontiguousarray(C), is_emit, np.asarray(nfirst, np.int64),
                                  np.asarray(ncount, np.int64))
    return emit, col


def compact_bright(cen: np.ndarray, spacing: np.ndarray, lum: np.ndarray, thresh: float, size: float,
                   nsum: np.ndarray | None = None, count: np.ndarray | None = None,
                   link: float = 3.0, col: np.ndarray | None = None,
                   same_colour: float = 0.05) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """((L,) bool, (L,) flat share, (L,) fitted area [m²]): the leaves of small bright objects. Leaves brighter than ``thresh``
    (luminance) are linked when closer than ``link`` × s (s = the median of ``spacing`` × SPLAT_SCALE, the
    typical splat radius [m]); a connected group whose leaves all lie within ``size`` × s of its centroid
    is a compact object (a lamp of a few points), whatever its points' spacing: the walk's splats of such an
    object light a whole micro-buffer texel or none. Flat share of each leaf's object: |Σ n| / points over
    the object (``nsum`` (L, 3): the leaves' normal sums, ``count``: their points; 0 without them) — ≈ 0
    for a lamp, 1 for a small flat patch. Fitted area: each leaf's share (by points) of its object's
    surface 4π r² where the object's leaves fit a sphere (:func:`sphere_fit`: centre c, radius r with each leaf
    at c + r n, within ``size`` × s); 0 where they do not (one leaf, one-sided normals, not on a sphere) and
    the caller keeps the leaves' own share of area. The lamp room's six 4 cm lamps (1–8 points) got 0.33–2.1×
    their area from the points' own shares, fitted 0.89–1.02× (3–8 points); the shipped sample's (7–19 points)
    1.03–1.21× and 0.98–1.00× (bench/README.md). A fitted object's flat share is 0.
    With ``col`` (L, 3: the leaves' radiance), an object that cannot be fitted (a lamp of one point) whose
    radiance is within ``same_colour`` (relative RGB distance) of fitted ones, whose leaves lie within their
    radius and whose point count is a likely Poisson draw of their area (P(N ≤ its count) ≥ 1 % at the cloud's
    typical share of area a point, π s² / 2: a 4 cm lamp in a 0.05 m grid expects 10 points, and one point there
    is something smaller) is taken for one more of those fixtures: the median of their areas (0 = off)."""
    out = np.zeros(len(lum), bool)
    flat = np.zeros(len(lum))
    area = np.zeros(len(lum))
    b = np.flatnonzero(lum > thresh)
    if len(b) == 0 or len(spacing) == 0:
        return out, flat, area
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    s = float(np.median(spacing)) * SPLAT_SCALE
    pb = np.asarray(cen, np.float64)[b]
    pr = cKDTree(pb).query_pairs(link * s, output_type="ndarray")
    g = coo_matrix((np.ones(len(pr)), (pr[:, 0], pr[:, 1])), shape=(len(b), len(b)))
    n, lab = connected_components(g, directed=False)
    cnt = np.bincount(lab, minlength=n)
    c = np.stack([np.bincount(lab, weights=pb[:, k], minlength=n) for k in range(3)], 1) / cnt[:, None]
    far = np.zeros(n)
    np.maximum.at(far, lab, np.linalg.norm(pb - c[lab], axis=1))
    out[b] = far[lab] <= size * s
    if nsum is not None and count is not None:
        ns = np.asarray(nsum, np.float64)[b]
        sn = np.stack([np.bincount(lab, weights=ns[:, k], minlength=n) for k in range(3)], 1)
        pts = np.bincount(lab, weights=np.asarray(count, np.float64)[b], minlength=n)
        flat[b] = np.clip(np.linalg.norm(sn, axis=1) / np.maximum(pts, 1.0), 0.0, 1.0)[lab]
        w = np.asarray(count, np.float64)[b]
        ln = np.linalg.norm(ns, axis=1, keepdims=True)
        r, ok = sphere_fit(pb, ns / np.maximum(ln, 1e-300), w, lab, n)
        ok &= (far <= size * s) & (r <= size * s) & (cnt >= 2)
        W = np.bincount(lab, weights=w, minlength=n)
        A = np.where(ok, 4.0 * math.pi * r * r, 0.0)
        if col is not None and same_colour > 0 and ok.any():
            cg = np.stack([np.bincount(lab, weights=w * np.asarray(col, np.float64)[b, k], minlength=n)
                           for k in range(3)], 1) / np.maximum(W, 1e-300)[:, None]
            from scipy.stats import poisson

            fit_g = np.flatnonzero(ok)
            share = math.pi * s * s / 2.0                   # a point's typical share of area [m²]
            for g in np.flatnonzero(~ok & (far <= size * s)):
                near = fit_g[np.linalg.norm(cg[fit_g] - cg[g], axis=1) <= same_colour * np.linalg.norm(cg[fit_g], axis=1)]
                if len(near) and far[g] <= np.median(r[near]):
                    a = float(np.median(A[near]))
                    if poisson.cdf(W[g], a / share) >= 0.01:
                        A[g] = a
        sel = (A > 0)[lab]
        area[b[sel]] = A[lab[sel]] * w[sel] / W[lab[sel]]
        flat[b[sel]] = 0.0                                   # a sphere is closed
    return out, flat, area


def sphere_fit(p: np.ndarray, nrm: np.ndarray, w: np.ndarray, lab: np.ndarray, n: int,
               min_spread: float = 0.1, max_residual: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """((n,) radius [m], (n,) bool accepted): for each group ``lab`` (0..n−1) of points ``p`` [m] with unit
    normals ``nrm`` and weights ``w``, the sphere (centre c, radius r) with each point at c + r n in the
    weighted least-squares sense (closed form: r = Σw n·(p − p̄) / (W (1 − |n̄|²)), p̄, n̄ the weighted means).
    Accepted where the normals spread (1 − |n̄|² ≥ ``min_spread``: not one-sided, a flat patch's are
    parallel), r > 0 and the points' RMS distance from c + r n is ≤ ``max_residual`` × r (they lie on it).
    The radius returned is the points' RMS distance from c: the same on a smooth sphere, and on a faceted
    one (face normals: r is the faces' distance, less the points' offsets along them) 1–2 % nearer its area."""
    W = np.bincount(lab, weights=w, minlength=n)
    Wd = np.maximum(W, 1e-300)
    pm = np.stack([np.bincount(lab, weights=w * p[:, k], minlength=n) for k in range(3)], 1) / Wd[:, None]
    nm = np.stack([np.bincount(lab, weights=w * nrm[:, k], minlength=n) for k in range(3)], 1) / Wd[:, None]
    spread = 1.0 - np.einsum("ij,ij->i", nm, nm)
    num = np.bincount(lab, weights=w * np.einsum("ij,ij->i", nrm, p - pm[lab]), minlength=n)
    r = num / np.maximum(W * spread, 1e-300)
    c = pm - r[:, None] * nm
    res = np.bincount(lab, weights=w * np.sum((p - c[lab] - r[lab, None] * nrm) ** 2, axis=1), minlength=n)
    ok = (spread >= min_spread) & (r > 0) & (res / Wd <= (max_residual * r) ** 2)
    rc = np.sqrt(np.bincount(lab, weights=w * np.sum((p - c[lab]) ** 2, axis=1), minlength=n) / Wd)
    return np.where(ok, rc, 0.0), ok


def prune_threshold(colors: np.ndarray, tc: float) -> tuple[float, float]:
    """(t_c as a linear-RGB distance, the radiance unit it is taken in): ``tc`` × the cloud's median luminance
    (:func:`pipeline.color.radiance_scale`). The §5.1 test compares absolute colour distances; measured in the
    cloud's own unit it prunes the same nodes whatever that unit is. An absolute 0.01 pruned a cloud × 10⁻⁶ (or
    × 10⁻³) to a few clusters and relit it 0.56 relative RMS off the expected image, and × 2 already moved it by
    0.25 % (issue 28; :func:`build_bsh` itself still takes an absolute ``tc``)."""
    ref = radiance_scale(colors)
    return float(tc) * ref, ref


def cube_box(points: np.ndarray) -> tuple[np.ndarray, float]:
    """(min corner float64 (3,), cube side [m]) of the points' bounding box, cubed; side 1 for a
    cloud of identical points (every point then falls in cell 0)."""
    p = np.asarray(points)
    ok = p.dtype in (np.float32, np.float64) and p.ndim == 2 and p.shape[0] > 0 and p.shape[1] == 3
    mn, mx = core.bounds(np.ascontiguousarray(p)) if ok else (None, None)   # p.min / p.max (axis 0), in parallel …
    if not ok or not (np.all(mn != 0) and np.all(mx != 0)):                 # … but for the sign of a zero
        mn, mx = p.min(axis=0), p.max(axis=0)
    lo = mn.astype(np.float64)
    hi = mx.astype(np.float64)
    side = float(np.max(hi - lo))
    if not side > 0:
        side = 1.0
    return lo, side


def build_bsh(points: np.ndarray, normals: np.ndarray, colors: np.ndarray, *, bits: int = 21,
              tc: float = 0.01, tn: float = 0.98, prune: bool = True, prune_stat: str = "mean",
              exact_cone_max: int = 64, where: str = "<cloud>", isolated: float = 2.0, closed_share: float = 0.125,
              emitters: str = "compact", closed_contrast: float = 30.0, emitter_size: float = 2.0,
              timings: Timings | None = None) -> dict[str, Any]:
    """Build the BSH of a cloud (points [m], normals, linear-radiance colours; (N,3) each).

    Returns the arrays of ``pcrelight.bsh/1`` (see :data:`pipeline.schemas.SCHEMAS`) plus a
    ``stats`` dict (counts, depth). Deterministic: no randomness is involved."""
    t = timings if timings is not None else Timings()
    nrm = check_inputs(points, normals, colors, where)
    pts = np.ascontiguousarray(points, dtype=np.float32)
    col = np.ascontiguousarray(colors, dtype=np.float32)
    n = pts.shape[0]
    with t.step("morton"):
        lo, side = cube_box(pts)
        scale = float(2 ** bits) / side
        codes = core.morton_codes(pts, lo, scale, bits)
    with t.step("sort"):
        order, scodes = core.radix_argsort(codes, 3 * bits)
    check_interrupt()
    with t.step("leaves"):
        P, Nn, C = core.gather_sorted(pts, nrm, col, order)
        flag = np.empty(n, dtype=bool)
        flag[0] = True
        np.not_equal(scodes[1:], scodes[:-1], out=flag[1:])
        lfirst = np.flatnonzero(flag).astype(np.int64)
        L = lfirst.shape[0]
        lcount = np.diff(np.append(lfirst, n)).astype(np.int64)
        lcodes = scodes[lfirst]
        T = 2 * L - 1
        cen = np.empty((T, 3))
        rad = np.empty(T)
        ncol = np.empty((T, 3))
        nsum = np.empty((T, 3))
        m2 = np.empty(T)
        md_ub = np.empty(T)
        xd_ub = np.empty(T)
        cone = np.empty((T, 4))
        core.leaf_attributes(P, Nn, C, lfirst, lcount, cen, rad, ncol, nsum, m2, md_ub, xd_ub, cone)
    with t.step("spacing"):
        spacing = leaf_spacing(cen[L - 1:], lo, side)
        spacing0 = spacing
        spacing, n_isolated = core.shrink_isolated_leaves(cen[L - 1:], lcodes, spacing, isolated, 16, bits, lo, side)
        iso_leaf = spacing != spacing0
        bright_thresh = closed_contrast * float(np.median(luminance(C, np.float64)))
        if emitters == "compact":
            compact, flat, fit_area = compact_bright(cen[L - 1:], spacing0, luminance(ncol[L - 1:], np.float64),
                                                     bright_thresh, emitter_size, nsum[L - 1:], lcount,
                                                     col=ncol[L - 1:])
            fitted = fit_area > 0                   # isolated or not: the object's leaves fit a sphere
            compact &= ~iso_leaf | fitted
        else:
            compact, flat, fit_area, fitted = np.zeros(L, bool), np.zeros(L), np.zeros(L), np.zeros(L, bool)
        lr = np.maximum(rad[L - 1:], spacing * SPLAT_SCALE)
        rad[L - 1:] = (lr * core.UP32).astype(np.float32)
        # each point's share of its voxel's splat area (r² / points in the voxel), prefix-summed in Morton order
        share = core.point_share(rad[L - 1:], lcount)
    check_interrupt()
    with t.step("karras"):
        left, right, rlo, rhi = core.karras_build(lcodes)
        dfs = core.dfs_order(left, right, L)
    check_interrupt()
    with t.step("cones"):
        exact = core.exact_cones(left, right, rlo, rhi, lfirst, lcount, Nn, int(exact_cone_max), cone)
    check_interrupt()
    with t.step("bottom_up"):
        first, count = core.bottom_up(left, right, rlo, rhi, dfs, L, lfirst, lcount, cen, rad, ncol, nsum, m2,
                                      md_ub, xd_ub, cone, exact)
    check_interrupt()
    with t.step("prune_linearise"):
        ids, rgt, skip, clus, depth = core.linearise(
            left, right, L, count, first, ncol, nsum, m2, md_ub, xd_ub, C, bool(prune),
            float(min(tc, 1e300)), float(tn), prune_stat == "max")
    with t.step("pack"):
        M = ids.shape[0]
        words = np.zeros((M, 10), dtype=np.uint32)
        center, radius, color, normal, child, nfirst, ncount, cax, chalf = core.assemble(
            ids, rgt, skip, cen, rad, ncol, nsum, first, count, cone, CONE_PACK_SLACK,
            words, words.view(np.float32))
        nodes = words.view(NODE_DTYPE).reshape(M)
        inner = rgt >= 0
        # the closure factor (closure_share) on inner nodes only (a voxel leaf is a disc: back-face culling shows
        # its side), and only bright ones (a lamp): a dark closed node (a roof beam) keeps its splat and hides
        # what lies behind it
        lum = luminance(color, np.float64)
        closed = inner & (lum > bright_thresh)
        splat = splat_radii(radius, core.splat_area(Nn, share, nfirst, ncount, closed, float(closed_share)))
        n_closed = int(np.count_nonzero(core.closure_factor(Nn, np.diff(share), nfirst[closed], ncount[closed],
                                                            closed_share) < 0.99)) if closed.any() else 0
        emit = np.zeros((0, 12), np.float32)
        # isolated voxels that are leaves of the tree (not pruned into a cluster of look-alikes), and those of
        # small bright objects wherever they are (a lamp point pruned into a dark cluster by the mean colour
        # test would light the whole cluster's disc)
        is_leaf_start = np.zeros(n + 1, bool)       # (np.isin(lfirst, those nfirst), in O(N))
        is_leaf_start[nfirst[~inner & ~clus.astype(bool)]] = True
        iso_emit = (iso_leaf & is_leaf_start[lfirst]) | compact
        n_iso_emit = int(iso_emit.sum())
        if n_iso_emit > MAX_EMITTERS:                # the brightest ones; the rest stay splatted leaves
            j = np.flatnonzero(iso_emit)
            keep = j[np.argsort(-luminance(ncol[L - 1:][j], np.float64), kind="stable")[:MAX_EMITTERS]]
            iso_emit = np.zeros_like(iso_emit)
            iso_emit[keep] = True
        if emitters != "none" and iso_emit.any():
            # an isolated leaf's disc is its share of area (step 3); a compact object's leaf splats twice it
            # (a sphere-fitted object's leaves: their share of its surface, 4π r²)
            erad = np.where(fitted, np.sqrt(fit_area / math.pi),
                            np.where(compact, rad[L - 1:] * np.float32(SPLAT_SCALE), rad[L - 1:]))
            emit, color = split_emitters(iso_emit, lfirst, lcount, cen[L - 1:], erad, ncol[L - 1:],
                                         nsum[L - 1:], C, nfirst, ncount)
            emit[:, 7] = np.where(compact & ~fitted, flat, 0.0)[iso_emit]   # flat share (isolated points, spheres: 0)
            whole = core.range_counts(np.repeat(iso_emit, lcount), nfirst, ncount) == ncount   # all its points are emitters'
            splat = np.where(whole, np.float32(0.0), splat).astype(np.float32)   # they splat nothing
            color[whole] = 0.0
            nodes["color"] = color
    stats = {
        "n_points": int(n), "n_voxels": int(L), "n_multi_point_voxels": int(np.count_nonzero(lcount > 1)),
        "n_nodes_full": int(2 * L - 1), "n_nodes": int(M), "n_clusters": int(clus.sum()),
        "n_leaves": int(np.count_nonzero(~inner)), "depth": int(depth.max()),
        "bbox_min": lo.tolist(), "cube_side": side, "voxel_size": side / 2 ** bits,
        "splat_radius_median": float(np.median(spacing * SPLAT_SCALE)),
        "n_splat_capped": int(np.count_nonzero(splat < radius)),
        "n_isolated": n_isolated,
        "n_closed": n_closed,
        "n_emitters": int(len(emit)), "n_emitter_candidates": n_iso_emit,
        "n_compact": int(np.count_nonzero(compact & iso_emit)),
        "n_sphere_fit": int(np.count_nonzero(fitted & iso_emit)),
    }
    return {
        "nodes": nodes, "center": center, "radius": radius, "splat_radius": splat, "color": color, "emitters": emit,
        "cone_axis": cax, "cone_half_angle": chalf, "child": child,
        "first": nfirst, "count": ncount,
        "order": order.astype(np.int64), "normal": normal, "depth": depth.astype(np.int32),
        "cluster": clus.astype(np.uint8), "bbox_min": lo.astype(np.float64),
        "cube_side": np.float64(side), "voxel_size": np.float64(side / 2 ** bits),
        "bits": np.int32(bits), "n_voxels": np.int64(L), "n_nodes_full": np.int64(2 * L - 1),
        "stats": stats,
    }


# ----------------------------------------------------------------------------- output
# bsh.npz members written without compression: float data that deflate shrinks by a fifth to a third at
# 4–10 × the time of writing them (3 M points: 25 s of a 48 s build, bench/bsh_scale.csv)
STORED_KEYS = frozenset({"nodes", "splat_radius", "emitters"})


ZIP_LIMIT = 2 ** 31   # above this (a member's size or an offset) write_bsh falls back to zipfile (ZIP64)
_DOS_DATE = (0 << 9) | (1 << 5) | 1   # 1980-01-01, 00:00:00 (io.write_npz's fixed timestamp)


def _npy_header(a: np.ndarray) -> bytes:
    """The ``.npy`` header ``numpy.lib.format.write_array`` writes before the data of the array ``a`` (format
    1.0, or 2.0 when the header does not fit 1.0, as numpy chooses)."""
    import io as _io

    fmt = np.lib.format
    for write in (fmt.write_array_header_1_0, fmt.write_array_header_2_0):
        buf = _io.BytesIO()
        try:
            write(buf, fmt.header_data_from_array_1_0(a))
            return buf.getvalue()
        except ValueError:  # header too long for format 1.0
            continue
    raise ValueError(f"no .npy header format fits an array of shape {a.shape}")


def _npy_bytes(a: np.ndarray) -> np.ndarray:
    """The data bytes of the C-contiguous array ``a`` as a uint8 view (no copy; a 0-d array: a copy)."""
    return np.frombuffer(a.tobytes(), np.uint8) if a.ndim == 0 else a.reshape(-1).view(np.uint8)


def _deflate_member(a: np.ndarray) -> tuple[bytes, int, int]:
    """(raw deflate stream at level 1, CRC-32, uncompressed size) of ``a``'s ``.npy`` bytes; zlib and crc32 release
    the GIL on large buffers, so members compress in parallel threads."""
    import zlib

    head, data = _npy_header(a), _npy_bytes(a)
    comp = zlib.compressobj(1, zlib.DEFLATED, -15)
    out = comp.compress(head) + comp.compress(data) + comp.flush()
    return out, zlib.crc32(data, zlib.crc32(head)), len(head) + a.nbytes


def write_bsh(path: str | os.PathLike, arrays: dict[str, Any]) -> None:
    """Write bsh.npz (pcrelight.bsh/1): :func:`pipeline.io.write_npz` (same validation, atomic write, fixed
    timestamps, sorted keys: byte-deterministic) but without the members the node records hold
    (:data:`pipeline.bsh.format.DERIVED_KEYS`: ``io.read_npz`` puts them back, the same bytes), with deflate
    level 1 instead of 6 and the members of ``STORED_KEYS`` stored.

    The deflated members are compressed by a pool of threads (one per CPU, at most 4) while the stored ones are
    written; the zip is laid out here (local headers, central directory; what ``zipfile`` writes, without its
    data descriptors). A file that would pass 2 GiB is written by ``zipfile`` instead (ZIP64), one member at
    a time."""
    import struct
    import zlib
    from concurrent.futures import ThreadPoolExecutor

    from ..io import atomic_path, check_arrays

    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    check_arrays(path, SCHEMA, arrays)
    arrays["schema"] = np.asarray(SCHEMA)
    arrays = {k: (a if a.flags.c_contiguous else a.copy(order="C")) for k, a in arrays.items()
              if k not in DERIVED_KEYS}
    # (np.ascontiguousarray would turn a 0-d array into shape (1,))
    if sum(a.nbytes + 4096 for a in arrays.values()) >= ZIP_LIMIT:
        write_bsh_zipfile(path, arrays)
        return
    keys = sorted(arrays)
    with atomic_path(path) as tmp, ThreadPoolExecutor(max_workers=max(1, min(4, os.cpu_count() or 1))) as pool:
        jobs = {k: pool.submit(_deflate_member, arrays[k]) for k in keys if k not in STORED_KEYS}
        central = []
        with open(tmp, "wb") as f:
            for key in keys:
                name = (key + ".npy").encode()
                a = arrays[key]
                if key in STORED_KEYS:
                    head, data = _npy_header(a), _npy_bytes(a)
                    crc, size = zlib.crc32(data, zlib.crc32(head)), len(head) + a.nbytes
                    method, csize, parts = 0, size, (head, data)
                else:
                    comp, crc, size = jobs.pop(key).result()
                    method, csize, parts = 8, len(comp), (comp,)
                offset = f.tell()
                f.write(struct.pack("<4s5H3L2H", b"PK\x03\x04", 20, 0, method, 0, _DOS_DATE, crc, csize, size,
                                    len(name), 0) + name)
                for part in parts:
                    f.write(part)
                central.append(struct.pack("<4s6H3L5H2L", b"PK\x01\x02", 20 | 3 << 8, 20, 0, method, 0, _DOS_DATE,
                                           crc, csize, size, len(name), 0, 0, 0, 0, 0o644 << 16, offset) + name)
            cd_start = f.tell()
            cd = b"".join(central)
            f.write(cd + struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, len(keys), len(keys), len(cd), cd_start, 0))


def write_bsh_zipfile(path: str | os.PathLike, arrays: dict[str, np.ndarray]) -> None:
    """:func:`write_bsh` through ``zipfile`` (ZIP64 where needed), members streamed one after the other (those of
    ``DERIVED_KEYS`` left out)."""
    import zipfile

    from ..io import atomic_path

    with atomic_path(path) as tmp:
        with zipfile.ZipFile(tmp, "w", compresslevel=1) as zf:
            for key in sorted(set(arrays) - set(DERIVED_KEYS)):
                a = arrays[key]
                info = zipfile.ZipInfo(key + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.compress_type = zipfile.ZIP_STORED if key in STORED_KEYS else zipfile.ZIP_DEFLATED
                info.external_attr = 0o644 << 16
                # ZipFile.open takes the member's level, not the archive's (3.13 renamed the attribute)
                setattr(info, "compress_level" if hasattr(info, "compress_level") else "_compresslevel", 1)
                # streamed (write_array writes 16 MiB pieces): no copy of the array in memory
                with zf.open(info, "w", force_zip64=a.nbytes > 2 ** 30) as f:
                    np.lib.format.write_array(f, a, allow_pickle=False)


# ----------------------------------------------------------------------------- preview
def render_preview(path: str | os.PathLike, points: np.ndarray, colors: np.ndarray, bsh: dict[str, Any],
                   depth: int, max_points: int = 60000) -> int:
    """PNG: the cloud (tone-mapped colours, at most ``max_points`` shown) in front (XY) and top
    (XZ) orthographic views, with the spheres of the cut at ``depth`` (nodes of that depth plus
    the shallower leaves) drawn as circles. Returns the number of spheres drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Circle

    from ..display import tonemap
    from ..io import save_figure

    n = points.shape[0]
    sel = np.arange(n) if n <= max_points else np.linspace(0, n - 1, max_points).astype(np.int64)
    rgb = tonemap(colors[sel][None, :, :].astype(np.float32))[0]
    d = bsh["depth"]
    leaf = bsh["child"][:, 0] < 0
    cut = np.flatnonzero((d == depth) | (leaf & (d < depth)))
    fig, axs = plt.subplots(1, 2, figsize=(12, 6))
    for ax, (i, j, name) in zip(axs, ((0, 1, "front (x, y)"), (0, 2, "top (x, z)"))):
        ax.scatter(points[sel, i], points[sel, j], s=0.5, c=np.clip(rgb, 0, 1), linewidths=0)
        circles = [Circle((bsh["center"][k, i], bsh["center"][k, j]), bsh["radius"][k]) for k in cut]
        ax.add_collection(PatchCollection(circles, facecolor="none", edgecolor="tab:red", linewidth=0.6, alpha=0.8))
        ax.set_aspect("equal")
        ax.autoscale_view()
        ax.set_title(f"{name}: {len(cut)} spheres at depth {depth}")
        ax.set_xlabel("xyz"[i] + " [m]")
        ax.set_ylabel("xyz"[j] + " [m]")
    fig.tight_layout()
    save_figure(path, fig)
    return len(cut)


# ----------------------------------------------------------------------------- action
def run_build_bsh(cloud_path: str | os.PathLike, out_path: str | os.PathLike, cfg: BuildBshConfig,
                  preview: str | os.PathLike | None = None) -> dict[str, Any]:
    """Read the cloud, build the BSH, write ``out_path`` (pcrelight.bsh/1), ``<stem>.json`` beside
    it and the preview PNG when asked. Returns the report.

    Python's cyclic garbage collector is paused meanwhile: the build makes no reference cycles, and the
    collections that numba's cache loads set off walk every live object (0.1–0.2 CPU s at 3 M points)."""
    import gc

    enabled = gc.isenabled()
    gc.disable()
    try:
        return _run_build_bsh(cloud_path, out_path, cfg, preview)
    finally:
        if enabled:
            gc.enable()


def _run_build_bsh(cloud_path: str | os.PathLike, out_path: str | os.PathLike, cfg: BuildBshConfig,
                   preview: str | os.PathLike | None) -> dict[str, Any]:
    """:func:`run_build_bsh`'s body."""
    from ..io import read_cloud, write_json

    cfg.check()
    t = Timings()
    t0 = time.perf_counter()
    with t.step("read"):
        cloud = read_cloud(cloud_path)
    tc, unit = prune_threshold(cloud.colors, cfg.tc)
    res = build_bsh(cloud.points, cloud.normals, cloud.colors, bits=cfg.bits, tc=tc, tn=cfg.tn,
                    prune=cfg.prune, prune_stat=cfg.prune_stat, exact_cone_max=cfg.exact_cone_max,
                    where=str(cloud_path), timings=t, isolated=cfg.isolated,
                    closed_share=cfg.closed_share, emitters=cfg.emitters, closed_contrast=cfg.closed_contrast,
                    emitter_size=cfg.emitter_size)
    st = res.pop("stats")
    log.info("%d points → %d voxels (%d with several points) at %d bits (voxel %.3g m)",
             st["n_points"], st["n_voxels"], st["n_multi_point_voxels"], cfg.bits, st["voxel_size"])
    st["tc_absolute"] = tc
    st["radiance_unit"] = unit
    if cfg.prune:
        log.info("pruning (t_c=%g%s, t_n=%g, %s colour distance): %d nodes → %d nodes, %d clusters",
                 tc, f" = {cfg.tc:g} × the median luminance {unit:.4g}", cfg.tn,
                 cfg.prune_stat, st["n_nodes_full"], st["n_nodes"], st["n_clusters"])
    else:
        log.info("pruning off: %d nodes", st["n_nodes"])
    log.info("%d of %d nodes are closed in part (a lamp, a knob): splat area × (flat share + "
             "%.3g × the rest)", st["n_closed"], st["n_nodes"], cfg.closed_share)
    if cfg.isolated > 0:
        log.info("%d of %d leaves isolated (spacing > %.2g × their 16 nearest leaves' median: objects below the point "
                 "spacing): disc = their share of area", st["n_isolated"], st["n_voxels"], cfg.isolated)
    log.info("%d emitters (--emitters %s; %d leaves of small bright objects among the candidates, %d of them on a "
             "fitted sphere: its area 4π r²): added by relight's final gather, not splatted", st["n_emitters"],
             cfg.emitters, st["n_compact"], st["n_sphere_fit"])
    if cfg.emitters != "none" and st["n_emitter_candidates"] > st["n_emitters"]:
        log.warning("%d emitter candidates, more than %d: the brightest %d are emitters, the others stay splatted "
                    "(a noisy scan? see --isolated, --emitters)", st["n_emitter_candidates"], MAX_EMITTERS, MAX_EMITTERS)
    log.info("splat radius capped at the area of the node's voxel splats for %d of %d nodes", st["n_splat_capped"],
             st["n_nodes"])
    log.info("depth %d, %d leaves; times %s", st["depth"], st["n_leaves"],
             ", ".join(f"{k} {v:.3f}s" for k, v in t.as_dict().items()))
    with t.step("write"):
        write_bsh(out_path, res)
    n_prev = None
    if preview is not None:
        with t.step("preview"):
            n_prev = render_preview(preview, cloud.points, cloud.colors, res, cfg.preview_depth)
        log.info("preview %s: %d spheres at depth %d", preview, n_prev, cfg.preview_depth)
    report = {
        "stage": "build-bsh", "inputs": {"cloud": str(cloud_path)}, "output": str(out_path),
        "preview": None if preview is None else str(preview), "config": cfg.as_dict(),
        "counts": st, "preview_spheres": n_prev,
        "decisions": {
            "leaf": "one leaf per non-empty voxel; equal-weight mean of position, colour; exact minimum normal cone",
            "leaf_radius": f"max(farthest point, d{SPLAT_K}/sqrt(2)); d{SPLAT_K} among ±{SPLAT_WINDOW} Morton neighbours",
            "colour": "point-count-weighted mean of children (= mean of the node's points)",
            "sphere": "minimum sphere of the two children's spheres, float32-conservative",
            "splat_radius": "min(sphere radius, sqrt(sum of r^2 over the voxel leaves of the node's points))",
            "cone": f"exact minimum cone of point normals on level 1 and for nodes over ≤ {cfg.exact_cone_max} leaves, exact cone merge above (≥ π/2: the sphere)",
            "pruning": ("off" if not cfg.prune else
                        f"{cfg.prune_stat} colour distance < {tc:.6g}"
                        + f" ({cfg.tc:g} × the median luminance {unit:.6g})"
                        + f" and mean normal dot > {cfg.tn}"),
        },
        "timings_s": t.as_dict(),
    }
    write_json(Path(out_path).with_suffix(".json"), report)
    log.info("build-bsh done in %.2f s → %s", time.perf_counter() - t0, out_path)
    return report
