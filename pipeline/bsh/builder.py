"""The BSH builder behind build-bsh (seed 000 §5.1, §5.4): check the cloud, build the tree (the kernels of
:mod:`pipeline.bsh.tree`), the leaves' splat radii, the emitters and the pruned, packed 40-byte nodes. The whole
contract: :mod:`pipeline.bsh.build_bsh`'s docstring. Pure functions on arrays; the stage's I/O is there."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from . import tree as core
from .format import CONE_PACK_SLACK, NODE_DTYPE, UP32
from ..color import luminance, radiance_scale
from ..errors import InputError
from ..runtime import Timings, check_interrupt, get_logger

log = get_logger("build-bsh")

SCHEMA = "pcrelight.bsh/1"
LEAF_SPLAT_K = 4          # splat radius from the distance to the 4th-nearest leaf (fixed in the kernel) …
LEAF_SPLAT_WINDOW = 16    # … among 16 + 16 Morton neighbours
LEAF_SPLAT_SCALE = 1.0 / math.sqrt(2.0)
MAX_EMITTERS = 16384  # Eq. 9 loops over every emitter per receiver (llvmpipe stops a loop after 65 535 iterations)
SHIFT2 = np.array([1 / math.pi, 1 / math.e, 1 / math.sqrt(50.0)])  # second Morton order's offset [cube sides]


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
    return core.leaf_spacing(cen, perm2, LEAF_SPLAT_WINDOW)


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
    (luminance) are linked when closer than ``link`` × s (s = the median of ``spacing`` × LEAF_SPLAT_SCALE, the
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

    s = float(np.median(spacing)) * LEAF_SPLAT_SCALE
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


def grid_origin(lo: np.ndarray, side: float, bits: int) -> np.ndarray:
    """The Morton grid's origin [m]: the cubed box's min corner ``lo`` less half a cell, so that cell k spans
    ``lo + (k − ½, k + ½) × side / 2^bits``. A plane at a multiple of a cell from the corner (the walls and ceiling
    of a box room at round coordinates: y = 5 in a 16 m cube is cell 655 360 exactly) then lies mid-cell instead of
    on a boundary that float32 rounding moves it across; at 21 bits a float32 coordinate is only ~⅛ cell fine, and
    a ceiling crossing a major boundary (655 360 → 655 359: every low bit flips) regroups the tree round it. The
    lamp room × 10⁻³ (bench/relight/scale_lamps*.csv): relative RMS 8.3·10⁻³ → 1.3·10⁻⁴, with ``--emitters none``
    0.59 → 9.5·10⁻⁵. The top face's points (q = 2^bits) are clipped into the last cell, as before."""
    return np.asarray(lo, np.float64) - 0.5 * float(side) / float(2 ** bits)


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
        grid = grid_origin(lo, side, bits)
        codes = core.morton_codes(pts, grid, scale, bits)
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
        spacing, n_isolated = core.shrink_isolated_leaves(cen[L - 1:], lcodes, spacing, isolated, 16, bits, grid, side)
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
        lr = np.maximum(rad[L - 1:], spacing * LEAF_SPLAT_SCALE)
        rad[L - 1:] = (lr * UP32).astype(np.float32)
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
                            np.where(compact, rad[L - 1:] * np.float32(LEAF_SPLAT_SCALE), rad[L - 1:]))
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
        "splat_radius_median": float(np.median(spacing * LEAF_SPLAT_SCALE)),
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
