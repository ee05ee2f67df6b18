"""Importance-driven point projection (paper 001, Wang et al.): each receiver's micro-buffer is filled from point
samples of the cloud's clusters, drawn in proportion to each cluster's estimated contribution, instead of a walk
of the BSH (paper 000 §5.2).

Clusters (:func:`bsh_clusters`): the BSH nodes of the cut obtained by splitting the most populous cluster until
there are ``clusters`` (default 512, 001's count): the BSH is a median-split hierarchy, so this is 001's
"first 9 levels of a kd-tree" (clusters of near-equal point counts, each a spatially compact sub-tree) without a
second clustering of the cloud. Then a cluster whose brightest leaf outshines its median leaf more than
``CONTRAST``× is split further (the shipped room's sun, 107 points of radiance 1.4·10⁵ in a cluster of wall: a
sample of it painted its share of the cluster at the sun's radiance, single-pixel sparkles, 4×4-block RMS 28 %
against 4.8 % with the split).

Per receiver (``importance.comp.glsl``): the object's own clusters are splatted whole (every surfel); a cluster
whose root node the walk's stop rule would stop at (a far one: the sun, once split off) is splatted as that node,
as the walk does (without this cut, 28 % on the shipped view1 again); 2 random points of each other cluster give its
importance (001 Eq. 1: projected solid angle, × the BRDF's luminance towards the eye for a glossy receiver, Eq. 4;
scaled by the cluster's point count, since our clusters are not of equal size); :func:`assign_budget` (001 §3.2's
GPU-friendly assignment, exactly N_s = ``samples`` × clusters samples) gives each cluster its samples; the random
and the budgeted points are splatted with 001 Eq. 3's size over both draws (:func:`splat_side`, expected points
N_rd + N_s p_c) and the walk's depth key (distance + λ × the distance from the texel's ray). A point's area ΔA_s is
2 r_s² (``AREA_SCALE`` · π r_s²): the leaf splat radius is d₄/√2, d₄ its 4th neighbour's distance, so π r_s² is
1.57× the area of a point of a square grid (d₄²) and ~1.75× a Poisson sample's. 8 samples a cluster, not 001's 4
(the white furnace: −0.8 % against −4.8 % at 4).

The receiving object is in its own light (``OBJECT_SURFELS``): its surfels are nodes of the merged array
(:func:`pipeline.relight.surfels.merge_nodes`), every one splatted as the walk splats a leaf — its near-field rule
(``object_near``, ``object_reach``), horizon and back-face culls, disc or sphere, a glossy object's directional
radiance — the model of classic, mipmapped and hybrid, so the same references judge them (issue 45 §3); as
⌈⌉-rounded squares they overlapped past the object's silhouettes (the lamp room's view2 0.962 of ``full_*``, 0.972
now). Measured against ``full_*``: docs/relight.md "Importance-driven projection"; the room's points are still
squares, 2–3 % brighter than classic on the shipped views (the exhaustive projection +7 %: near squares overcover).

Micro-buffer: the shared m×m hemispherical (orthographic) layout of :mod:`pipeline.gather.walk` — not 001's
hemi-octahedral map — so the Eq. 9 gather, the emitters and the narrow-lobe VNDF sampling of
``eq9.comp.glsl`` are the classic gatherer's, unchanged, and an exhaustive projection compares texel by texel
with classic's micro-buffer. Eq. 3's Ω_texel is the texel table's solid angle of the texel hit.
Not done here: 001's image-space adaptive sampling (relight's ``--adaptive`` works for every gatherer) and its
bilateral post-filter.
Deterministic: the random numbers are a hash of (seed, the receiver's position, cluster, sample).
"""

from __future__ import annotations

import dataclasses
import heapq
import math
from typing import Any, Optional

import numpy as np

from ..bsh.format import GATHER_BINDINGS, LEAF, as_nodes, glsl_defines
from ..runtime import Timings, get_logger
from .base import BRDF_IDS, MASK_IDS, GatherParams, Receivers
from .walk import WalkGatherer

log = get_logger("relight")

def bsh_clusters(nodes: np.ndarray, n_clusters: int, contrast: float = 0.0,
                 extra: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cluster the BSH's leaves into sub-trees: starting from the root, split the cluster of most leaves into its
    two children until there are ``n_clusters`` (or every cluster is a leaf); then (``contrast`` > 0) split, up to
    ``extra`` more times, the clusters whose brightest leaf outshines their median leaf more than ``contrast``×
    (luminance), brightest first — a lamp or the sun with a bit of wall becomes its own cluster.

    Returns (cluster root node indices (C,) ascending, offsets (C+1,) uint32 into ``points``, points: the leaf
    node indices (N,) uint32 grouped by cluster). Nodes are depth-first with skip links (bsh_format): the sub-tree
    of i is [i, skip[i]), its left child i+1, its right child ``right``."""
    nd = as_nodes(nodes)
    leaf = nd["right"] == LEAF
    leaves = np.flatnonzero(leaf).astype(np.int64)
    if leaves.size == 0:
        raise ValueError("the BSH has no leaves")
    skip = nd["skip"].astype(np.int64)
    lum = nd["color"][leaves].astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])

    def span(i: int) -> tuple[int, int]:
        return int(np.searchsorted(leaves, i)), int(np.searchsorted(leaves, skip[i]))

    def count(i: int) -> int:
        lo, hi = span(i)
        return hi - lo

    heap = [(-count(0), 0)]
    done: list[int] = []
    while heap and len(heap) + len(done) < n_clusters:
        c, i = heapq.heappop(heap)
        if leaf[i]:
            done.append(i)
            continue
        for ch in (i + 1, int(nd["right"][i])):
            heapq.heappush(heap, (-count(ch), ch))
    roots = done + [i for _, i in heap]
    if contrast > 0 and extra > 0:
        def outshine(i: int) -> float:
            lo, hi = span(i)
            x = lum[lo:hi]
            return float(x.max() / max(np.median(x), 1e-30)) if hi - lo > 1 else 0.0

        cand = [(-outshine(i), i) for i in roots if not leaf[i]]
        cand = [q for q in cand if -q[0] > contrast]
        heapq.heapify(cand)
        roots = [i for i in roots if leaf[i] or outshine(i) <= contrast]
        splits = 0
        while cand and splits < extra:
            _, i = heapq.heappop(cand)
            splits += 1
            for ch in (i + 1, int(nd["right"][i])):
                o = outshine(ch) if not leaf[ch] else 0.0
                if o > contrast:
                    heapq.heappush(cand, (-o, ch))
                else:
                    roots.append(ch)
        roots += [i for _, i in cand]
    roots = np.sort(np.array(roots, np.int64))
    offs = np.searchsorted(leaves, roots)
    offs = np.append(offs, leaves.size).astype(np.uint32)
    return roots, offs, leaves.astype(np.uint32)


def assign_budget(pdf: np.ndarray, n_samples: int, u: np.ndarray) -> np.ndarray:
    """001 §3.2's GPU-friendly budget assignment: samples per cluster (C,) int64 summing to exactly ``n_samples``
    for any non-negative ``pdf`` (C,) with a positive sum (normalised here), ``u`` (C,) uniforms in [0, 1).

    The paper's carry form (f_k = N_s p_k + carry; ⌊f_k⌋ guaranteed, one more when u_k < its fraction; the
    over- or under-draw carried on) written cumulatively — f_k = N_s P_k − drawn so far, P_k the cumulative pdf,
    the same numbers in exact arithmetic — so that rounding cannot lose or add a sample: P is exactly 1 from the
    last cluster of positive pdf on. A cluster of zero pdf gets none (its fraction carries on). The shader
    (``importance.comp.glsl`` phase 1) is this function's twin in float32."""
    p = np.asarray(pdf, np.float64)
    total = float(p.sum())
    out = np.zeros(p.shape, np.int64)
    if not total > 0:
        return out
    cum = 0.0
    drawn = 0
    for k in range(p.size):
        cum += p[k]
        if p[k] <= 0:
            continue
        fk = n_samples * min(cum / total, 1.0) - drawn
        nk = int(np.floor(max(fk, 0.0)))
        if u[k] < fk - nk:
            nk += 1
        out[k] = nk
        drawn += nk
    return out


def splat_side(cluster_points: int, area: np.ndarray, cos_s: np.ndarray, dist: np.ndarray, expected: np.ndarray,
               omega_texel: np.ndarray, side_max: int) -> np.ndarray:
    """001 Eq. 3's splat: Ω_s = |C_k| ΔA_s / (N_s p_k) · |cos θ_s| / d² [sr] (``expected`` = N_s p_k, the
    cluster's expected samples; ``area`` ΔA_s [m²]; ``dist`` d [m]); the splat covers Ω_s / Ω_texel texels, as a
    square of side ⌈√(Ω_s / Ω_texel)⌉ clamped to [1, side_max] (the shader's ``splat_point``; rounding up, a splat
    never covers less than its share: fewer holes between the samples)."""
    om = cluster_points * np.asarray(area) / np.asarray(expected) * np.abs(cos_s) / np.asarray(dist) ** 2
    return np.clip(np.ceil(np.sqrt(om / omega_texel)), 1, side_max).astype(np.int64)


class ImportanceGatherer(WalkGatherer):
    """001's importance-driven projection into the shared micro-buffers, then the shared Eq. 9 gather."""

    OBJECT_SURFELS = True
    CLUSTERS = 512          # 001 §3.2
    CLUSTER_CUT = 1         # a far cluster splatted as its root node (the walk's stop rule), no samples
    CONTRAST = 64.0         # a cluster whose brightest leaf outshines its median more than this is split …
    CONTRAST_SPLITS = 256   # … up to this many times (bsh_clusters)
    SAMPLES = 8             # budgeted samples a cluster (N_s = SAMPLES × clusters; 001: 4 — 11.9 % 4×4 RMS on the
                            # shipped view1 against 6.0 % at 8, docs/relight.md)
    RANDOM = 2              # random points a cluster for its importance
    SPLAT_MAX = 8           # the largest splat side [texels] (a 32² buffer: 1/16 of its width)
    AREA_SCALE = 2.0 / math.pi

    def __init__(self, ctx: Any, nodes: np.ndarray, params: GatherParams, splat_radius: Optional[np.ndarray] = None,
                 emitters: Optional[np.ndarray] = None, clusters: Optional[int] = None, samples: Optional[int] = None,
                 exhaustive: bool = False, seed: Optional[int] = None,
                 object_dirs: Optional[np.ndarray] = None) -> None:
        from .. import gl

        params = dataclasses.replace(params, lobe_m=0)   # no lobe buffers: VNDF samples read the hemisphere buffer
        super().__init__(ctx, nodes, params, splat_radius=splat_radius, emitters=emitters, object_dirs=object_dirs)
        self.n_clusters_asked = int(clusters or self.CLUSTERS)
        self.samples = int(self.SAMPLES if samples is None else samples)
        self.exhaustive = bool(exhaustive)
        self.seed = int(params.seed if seed is None else seed) & 0xFFFFFFFF
        roots, offs, pts = bsh_clusters(nodes, self.n_clusters_asked, self.CONTRAST, self.CONTRAST_SPLITS)
        self.n_clusters = len(roots)
        self.n_budget = self.samples * self.n_clusters
        self.cluster_off_buf = ctx.buffer(np.concatenate([offs, roots.astype(np.uint32)]).tobytes())
        self.cluster_pts_buf = ctx.buffer(pts.tobytes())
        sizes = np.diff(offs.astype(np.int64))
        log.info("importance: %d clusters of %d–%d points (median %d), N_s = %d budgeted + %d random samples a "
                 "receiver%s", self.n_clusters, sizes.min(), sizes.max(), int(np.median(sizes)), self.n_budget,
                 self.RANDOM * self.n_clusters, " (exhaustive: every point)" if self.exhaustive else "")
        self.project = gl.make_compute(ctx, "importance.comp.glsl", here=__file__,
                                       defines={**glsl_defines(GATHER_BINDINGS), "PBGI_LAMBDA": repr(float(params.splat_lambda))})
        self._set(self.project, m=self.m, n_clusters=self.n_clusters, n_random=self.RANDOM, n_budget=self.n_budget,
                  seed=self.seed, exhaustive=int(self.exhaustive), iter_budget=self.iter_budget,
                  splat_max=self.SPLAT_MAX, stop_multiple=float(params.stop_multiple) if self.CLUSTER_CUT else 0.0,
                  omega_pix=params.omega_pix, disc_cone=float(params.disc_cone), area_scale=self.AREA_SCALE,
                  object_first=int(params.object_first) if params.object_first >= 0 else 0xFFFFFFFF,
                  object_near=float(params.object_near), object_reach=float(min(params.object_reach, 1e30)),
                  obj_dir_side=self.obj_dir_side, brdf_kind=BRDF_IDS[params.brdf], masking=MASK_IDS[params.masking],
                  pbgi_depth_scale=float(as_nodes(nodes)["radius"][0]) or 1.0)
        self._istate = self._imp = None
        self._cap = 0

    def run(self, recv: Receivers, pixels: np.ndarray | None = None, shape: tuple[int, int] | None = None,
            timings: Timings | None = None, view_dirs: np.ndarray | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """:meth:`WalkGatherer.run`, plus ``method_stats.importance``: clusters, budget, the budgeted samples drawn
        (min/max over the receivers that see anything: = budget), points splatted."""
        rad, stats = super().run(recv, pixels, shape, timings, view_dirs)
        st = stats.pop("_imp", {})
        stats["method_stats"] = {"importance": {
            "clusters": self.n_clusters, "samples_per_cluster": self.samples, "budget": self.n_budget,
            "random_per_cluster": self.RANDOM, "exhaustive": self.exhaustive, "seed": self.seed, **st}}
        return rad, stats

    def _buffers(self, n: int) -> None:
        if n > self._cap:
            for b in (self._istate, self._imp):
                if b is not None:
                    b.release()
            self._istate = self.ctx.buffer(reserve=n * 32)
            self._imp = self.ctx.buffer(reserve=max(n * self.n_clusters * 4, 4))
            self._cap = n

    def _walk_tile(self, n: int, bufs: dict, mb: Any, lobe_buf: Any, state: Any, pending: Any, off_buf: Any,
                   sn_buf: Any, use_lists: bool, lobe: bool, t: Timings, stats: dict[str, Any]) -> None:
        """Project n receivers' samples into their micro-buffers (resumable passes), then Eq. 9."""
        B = GATHER_BINDINGS
        self._buffers(n)
        self._bind(bufs, mb, lobe_buf, state, pending, self.cluster_off_buf, self.cluster_pts_buf)
        self._istate.bind_to_storage_buffer(B["ISTATE"])
        self._imp.bind_to_storage_buffer(B["IMP"])
        self._set(self.project, n_recv=n)
        with t.step("project"):
            passes = self._resumable(self.project, n, pending)
            ist = np.frombuffer(self._istate.read(size=n * 32), np.uint32).reshape(n, 2, 4)
        drawn, splats = ist[:, 1, 2].astype(np.int64), ist[:, 1, 3].astype(np.int64)
        im = stats.setdefault("_imp", {"budget_drawn_min": None, "budget_drawn_max": None, "points_splatted": 0,
                                       "receivers_seeing_nothing": 0})
        seen = np.frombuffer(ist[:, 1, 0].tobytes(), np.float32) > 0
        if seen.any():
            lo, hi = int(drawn[seen].min()), int(drawn[seen].max())
            im["budget_drawn_min"] = lo if im["budget_drawn_min"] is None else min(im["budget_drawn_min"], lo)
            im["budget_drawn_max"] = hi if im["budget_drawn_max"] is None else max(im["budget_drawn_max"], hi)
        im["points_splatted"] += int(splats.sum())
        im["receivers_seeing_nothing"] += int((~seen).sum()) if not self.exhaustive else 0
        stats["nodes_visited"] += int(splats.sum())
        stats["walk_passes"] = max(stats["walk_passes"], passes)
        self._gather(n, t)

    def release(self) -> None:
        for b in (self.cluster_off_buf, self.cluster_pts_buf, self._istate, self._imp):
            if b is not None:
                b.release()
        self.project.release()
        super().release()
