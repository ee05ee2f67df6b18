"""The micro-buffer walk and the Eq. 9 gather shared by every PBGI gatherer (paper 000 §5.2–§5.4).

Per tile of receivers: the walk (``walk.comp.glsl``) fills each receiver's micro-buffer from a list of
start nodes (classic: [root]; mipmapped/hybrid: the cut of :mod:`pipeline.gather.cut`), then the final
gather Eq. 9 (``eq9.comp.glsl``) integrates it against the BRDF.

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

import functools
import math
import time
from typing import Any, Callable, Optional

import numpy as np

from ..bsh.format import GATHER_BINDINGS, NODE_BYTES, as_nodes, cone_trig_table, glsl_defines
from ..runtime import Timings, check_interrupt, get_logger, progress
from .base import BRDF_IDS, MASK_IDS, GatherParams, Receivers

log = get_logger("relight")

TEXEL_BYTES = 16  # vec4 float32 (R, G, B, depth)


@functools.lru_cache(maxsize=16)
def texel_table(m: int, mode: str = "exact", nq: int = 64) -> np.ndarray:
    """(m·m, 4) float32 per texel (u, v) at row v·m + u: (x, y, Ω, proj).

    (x, y): tangent-plane coordinates of the texel's unit representative direction (z = √(1−x²−y²));
    Ω: solid angle [sr]; proj = ∫ cos dω over the texel [sr]. ``exact``: Ω = ∬ dx dy / z over
    texel ∩ unit disc, proj = area(texel ∩ disc), direction = normalised mean direction — integrated in
    y in closed form (arcsin) and in x by Gauss–Legendre split at the rim's kinks (ΣΩ = 2π and
    Σproj = π to 1e-6). ``paper``: Eq. 5, Ω = 2π/m² for texels whose centre is inside the disc,
    direction = centre, proj = Ω·z_centre. Ω = 0 marks an unused texel. Cached (every gatherer of a relight
    asks for the same m): the array is read-only.
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
        return _read_only(out.reshape(m * m, 4).astype(np.float32))
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
    return _read_only(out.reshape(m * m, 4).astype(np.float32))


def _read_only(a: np.ndarray) -> np.ndarray:
    """``a`` made read-only (a cached result shared by its callers)."""
    a.flags.writeable = False
    return a


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



StartLists = Callable[[int, int], tuple[np.ndarray, np.ndarray]]


def fitting_ranges(lo: int, hi: int, offs: np.ndarray | None, max_nodes: int):
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


def tile_size(m: int, memory_budget_bytes: float, max_ssbo: int | None, n_recv: int, lobe_m: int = 0) -> int:
    """Receivers per tile so that tile × (m² + lobe_m²) × 16 B ≤ the budget (and each buffer ≤ the GL's
    largest SSBO)."""
    per = (m * m + lobe_m * lobe_m) * TEXEL_BYTES
    cap = int(memory_budget_bytes // per)
    if max_ssbo:
        cap = min(cap, int(max_ssbo // (max(m, lobe_m) ** 2 * TEXEL_BYTES)))
    return max(1, min(cap, max(n_recv, 1)))


NODE_TEX_SHIFT = 12  # the node texture is 2¹² texels wide (walk.comp.glsl PBGI_NODE_TEX)


def node_texels(nodes: np.ndarray, splat_radius: np.ndarray, shift: int = NODE_TEX_SHIFT) -> np.ndarray:
    """(H, 2^shift, 4) uint32: the RGBA32UI texels of walk.comp.glsl's node texture (PBGI_NODE_TEX), node i at
    texels 3i, 3i+1, 3i+2 (row-major) = (centre.xyz, radius), (right, skip, cone, splat radius [m]),
    (colour.rgb, 0), float32 fields as their bits."""
    nd = as_nodes(nodes)
    M = len(nd)
    w = 1 << shift
    out = np.empty((-(-3 * M // w) * w, 4), np.uint32)    # filled in place (a 3 M-point BSH's is 290 MB)
    out[3 * M:] = 0
    t = out[:3 * M].reshape(M, 3, 4)
    t[:, 0, :3] = nd["center"].view(np.uint32)                # float32 fields as their bits
    t[:, 0, 3] = nd["radius"].view(np.uint32)
    t[:, 1, 0], t[:, 1, 1], t[:, 1, 2] = nd["right"], nd["skip"], nd["cone"]
    t[:, 1, 3] = np.ascontiguousarray(splat_radius, np.float32).view(np.uint32)
    t[:, 2, :3] = nd["color"].view(np.uint32)
    t[:, 2, 3] = 0
    return out.reshape(-1, w, 4)


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


class WalkGatherer:
    """The walk + Eq. 9 gather on a moderngl context, tiled under a memory budget; start lists come from
    :meth:`start_lists` (None: every receiver starts at the root, the classic walk). Subclasses (the
    gatherers of the table) choose the start lists and the budget split.

    ``nodes``: (M,) :data:`pipeline.bsh.format.NODE_DTYPE` (40-byte records); ``splat_radius`` (M,) the
    nodes' splat radii [m] (bsh.npz ``splat_radius``, :func:`pipeline.bsh.builder.splat_radii`; None = the
    node radii); ``emitters`` (E, 12) the points of small objects Eq. 9 adds (their disc's area, a quarter
    of it from any side and, for the flat share in column 7, once to one side) where the micro-buffer's
    depth lies behind them (bsh.npz ``emitters``, :func:`pipeline.bsh.builder.split_emitters`;
    None = none).
    """

    DISPATCH = 4096  # receivers per compute dispatch (interrupt checks between dispatches)
    # profiling only (bench/speed/bench_walk_profile.py): walk.comp.glsl switches PROF_NOSPLAT (stopped nodes are not
    # splatted: the traversal's own cost), PROF_NOBACK (no back-face cull; the image is then wrong) and
    # PROF_ITERS / PROF_SPLATS (nodes_visited counts the loop iterations instead: node visits + splat texels; or the
    # splats); the splat's parts, each switch doing one more of it (the images are then wrong): PROF_QUEUE_ONLY (the
    # queue's pushes and reads), PROF_SETUP_ONLY (+ the stopped node re-read and put in the splat frame),
    # PROF_TEXEL_EMPTY (+ the splat's bounds, row and texel loops, no texel test), PROF_NOWRITE (+ the texel tests,
    # no micro-buffer read or write)
    PROFILE_DEFINES: tuple[str, ...] = ()
    # walk the receivers in Morton (Z) order of their pixels instead of row-major (measured: no faster on
    # llvmpipe, 8-lane SIMD; kept for the GPU bench)
    MORTON_ORDER = False
    TEXEL_UBO = True  # the walk reads the texel table from a uniform block where it fits (False: the SSBO)
    TEXEL_UBO_BINDING = 0  # its uniform-block binding point (no other program of the pipeline uses one)
    NODE_TEX = True  # the walk reads its nodes from a 2-D texture where it fits (False: the node SSBO)
    NODE_TEX_UNIT = 0  # its texture unit (bound before every tile's walk)
    GATHER_SHARE = 1.0  # share of the memory budget for micro-buffers and start lists (the rest: the cut's)

    def __init__(self, ctx: Any, nodes: np.ndarray, params: GatherParams, splat_radius: np.ndarray | None = None,
                 emitters: np.ndarray | None = None, object_dirs: np.ndarray | None = None) -> None:
        from .. import gl

        self.ctx, self.params, self.m = ctx, params, int(params.m)
        self.keep_microbuffers = False  # debugging/tests: keep the last tile's micro-buffers (n, m, m, 4)
        self.last_microbuffers: np.ndarray | None = None
        self.last_lobe_buffers: np.ndarray | None = None  # and lobe buffers (n, lobe_m, lobe_m, 4)
        # the lobe micro-buffers of glossy receivers (GatherParams.lobe_m; none for Lambert)
        self.lobe_m = int(params.lobe_m) if params.brdf != "lambert" and params.lobe_samples > 0 else 0
        self.budget = params.memory_budget_bytes * self.GATHER_SHARE  # [bytes]
        self.max_ssbo = ctx.info.get("GL_MAX_SHADER_STORAGE_BLOCK_SIZE")
        nodes = np.ascontiguousarray(nodes)
        if nodes.dtype.itemsize != NODE_BYTES:
            raise ValueError(f"nodes must be {NODE_BYTES}-byte records")
        self.n_nodes = int(nodes.shape[0])
        nbytes = self.n_nodes * NODE_BYTES
        if self.max_ssbo and nbytes > self.max_ssbo:  # measured: Mesa llvmpipe reads a 200 MiB SSBO past its 128 MiB limit
            log.warning("%d nodes = %d B exceed GL_MAX_SHADER_STORAGE_BLOCK_SIZE (%d B, %s); binding the whole buffer "
                        "anyway (Mesa llvmpipe reads past the limit; if the image is wrong, prune more: --tc/--tn)",
                        self.n_nodes, nbytes, self.max_ssbo, gl.context_info(ctx)["renderer"])
        t_up = time.perf_counter()
        self.node_buf = ctx.buffer(nodes)                       # (the array itself: no bytes copy of 40 B a node)
        self.startup_s = {"bsh_upload": time.perf_counter() - t_up}   # start-up costs [s], relight's stats.json
        splat = as_nodes(nodes)["radius"] if splat_radius is None else np.asarray(splat_radius)
        if splat.shape != (self.n_nodes,):
            raise ValueError(f"splat_radius must be ({self.n_nodes},), got {splat.shape}")
        self.splat_buf = ctx.buffer(np.ascontiguousarray(splat, np.float32))
        emit = np.zeros((0, 12), np.float32) if emitters is None else np.asarray(emitters, np.float32).reshape(-1, 12)
        self.n_emitters = int(len(emit))
        self.emit_buf = ctx.buffer(np.ascontiguousarray(emit).tobytes() if len(emit) else b"\0" * 48)
        # the object's nodes' radiance by direction (surfels.in_micro_buffers with dirs_side: (K, S², 3), S×S octahedral cells)
        self.obj_dir_side = self._n_views = 0
        if object_dirs is None:
            self.obj_dir_buf = ctx.buffer(reserve=16)     # bound, never read (obj_dir_side 0)
        else:
            od = np.asarray(object_dirs, np.float32)
            S = int(round(math.sqrt(od.shape[1])))
            if od.ndim != 3 or od.shape[2] != 3 or S * S != od.shape[1] or params.object_first < 0 \
                    or od.shape[0] != self.n_nodes - params.object_first:
                raise ValueError(f"object_dirs must be (object nodes, S², 3), got {od.shape}")
            self.obj_dir_side = S
            self.obj_dir_buf = ctx.buffer(np.concatenate([od, np.zeros(od.shape[:2] + (1,), np.float32)], 2).tobytes())
        self.texels = texel_table(self.m, params.solid_angle)
        self.texel_buf = ctx.buffer(self.texels.tobytes())
        binds = glsl_defines(GATHER_BINDINGS)
        # the walk reads the texel table from a uniform block where it fits (an SSBO load on llvmpipe is a loop
        # over the SIMD lanes of bounds-checked scalar loads; a uniform-block load is a branch-free gather)
        defs: dict[str, Any] = {**binds, "PBGI_LAMBDA": repr(float(params.splat_lambda)),
                                "PBGI_POINT_FALLBACK": int(bool(params.point_fallback)),
                                **{k: 1 for k in self.PROFILE_DEFINES}}
        ubo_max = int(ctx.info.get("GL_MAX_UNIFORM_BLOCK_SIZE") or 0)
        self.texel_ubo = None
        if self.TEXEL_UBO and self.m * self.m * TEXEL_BYTES <= ubo_max:
            defs["PBGI_TEXEL_UBO"] = self.m * self.m
            self.texel_ubo = ctx.buffer(self.texels.tobytes())
        # the walk reads its nodes from a 2-D texture where it fits (walk.comp.glsl PBGI_NODE_TEX: a texel fetch is a
        # vector gather on llvmpipe, an SSBO read at a per-lane index a loop over the lanes)
        self.node_tex = None
        n_rows = -(-3 * self.n_nodes // (1 << NODE_TEX_SHIFT))
        if self.NODE_TEX and n_rows <= int(ctx.info.get("GL_MAX_TEXTURE_SIZE") or 0):
            t_up = time.perf_counter()
            tx = node_texels(nodes, splat)
            self.node_tex = ctx.texture((tx.shape[1], tx.shape[0]), 4, tx, dtype="u4")
            self.node_tex.filter = (0x2600, 0x2600)   # GL_NEAREST (an integer texture filtered linearly is incomplete)
            defs["PBGI_NODE_TEX"] = NODE_TEX_SHIFT
            self.startup_s["bsh_upload"] += time.perf_counter() - t_up
        t_prog = time.perf_counter()
        # one program for the hemisphere walk and one for the lobe walk (PBGI_WALK_LOBE): llvmpipe runs every
        # branch of the loop body under a lane mask, so one program with both splats paid for both
        self.walk = gl.make_compute(ctx, "walk.comp.glsl", here=__file__,
                                    defines={**defs, "PBGI_WALK_LOBE": 0})
        self.walk_lobe = (gl.make_compute(ctx, "walk.comp.glsl", here=__file__,
                                          defines={**defs, "PBGI_WALK_LOBE": 1})
                          if self.lobe_m else None)
        self.walks = [w for w in (self.walk, self.walk_lobe) if w is not None]
        if self.texel_ubo is not None:
            for w in self.walks:
                try:
                    w["PbgiTexelBlock"].binding = self.TEXEL_UBO_BINDING
                except KeyError:  # the lobe walk does not read the texel table
                    pass
        self.gather = gl.make_compute(ctx, "eq9.comp.glsl", here=__file__, defines=binds)
        self.startup_s["programs"] = time.perf_counter() - t_prog   # compile + link (Mesa's shader cache: warm after one run)
        for w in self.walks:
            self._set(w, node_tex=self.NODE_TEX_UNIT)
            w["pbgi_cone_trig"].write(cone_trig_table().tobytes())   # pbgi_backface_cull's (cos, sin) of the half-angles
            self._set(w, m=self.m, stop_multiple=float(params.stop_multiple), omega_pix=params.omega_pix,
                      n_nodes=self.n_nodes)
        self._set(self.gather, m=self.m, brdf_kind=BRDF_IDS[params.brdf], masking=MASK_IDS[params.masking],
                  lobe_samples=int(params.lobe_samples), lobe_texels=float(params.lobe_texels),
                  n_emit=self.n_emitters, lobe_m=self.lobe_m)
        # the lobe texels' floor (pbgi_lobe_tan): the median splat radius of the leaves
        leaf = as_nodes(nodes)["right"] == 0xFFFFFFFF
        self.lobe_leaf_r = float(np.median(splat[leaf])) if leaf.any() else 0.0
        for prog in (*self.walks, self.gather):
            self._set(prog, lobe_leaf_r=self.lobe_leaf_r, lobe_tmax=2.5)
        self.iter_budget = walk_iteration_budget(ctx)
        for w in self.walks:
            self._set(w, disc_cone=float(params.disc_cone), object_near=float(params.object_near),
                      object_reach=float(min(params.object_reach, 1e30)),
                      object_stop=float(params.object_stop),
                      object_first=int(params.object_first) if params.object_first >= 0 else 0xFFFFFFFF,
                      obj_dir_side=self.obj_dir_side,
                      lobe_m=max(self.lobe_m, 1),
                      pbgi_depth_scale=float(as_nodes(nodes)["radius"][0]) or 1.0)   # the root's radius [m]

    def start_lists(self, recv: Receivers, pixels: np.ndarray, shape: tuple[int, int]) -> tuple[Optional[StartLists], dict[str, Any]]:
        """(start lists or None for [root], cut statistics) for these receivers."""
        return None, {}

    def run(self, recv: Receivers, pixels: np.ndarray | None = None, shape: tuple[int, int] | None = None,
            timings: Timings | None = None, view_dirs: np.ndarray | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Radiance (P, 3) float32 leaving each receiver towards its eye, and stats (``cut``: the cut's).
        ``view_dirs`` (D, 3) unit world directions: the radiance (P, D, 3) leaving each receiver towards each
        (0 below its tangent plane; no lobe buffers: Eq. 9's narrow lobes read the hemisphere buffer)."""
        t = timings or Timings()
        order = None
        if pixels is not None and shape is not None and len(pixels) > 1 and self.MORTON_ORDER:
            from .cut import morton_encode
            px = np.asarray(pixels, np.int64)
            order = np.argsort(morton_encode(px % shape[1], px // shape[1]), kind="stable")
            recv, pixels = recv.take(order), px[order]
        start_lists, cut = self.start_lists(recv, pixels, shape)
        rad, stats = self.walk_and_gather(recv, start_lists, t, view_dirs)
        if order is not None:
            out = np.empty_like(rad)
            out[order] = rad
            rad = out
        stats.update(cut=cut, gather_budget_bytes=self.budget, walk_iteration_budget=self.iter_budget)
        return rad, stats

    @staticmethod
    def _set(prog: Any, **kw: Any) -> None:
        from .. import gl

        gl.set_uniforms(prog, **kw)

    def walk_and_gather(self, recv: Receivers, start_lists: Optional[StartLists], t: Timings,
                        view_dirs: np.ndarray | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Walk every receiver from its start lists (None: the root) in tiles, then Eq. 9 (towards each of
        ``view_dirs`` when given: :meth:`run`)."""
        ctx, m = self.ctx, self.m
        P = len(recv)
        D = 0 if view_dirs is None else len(view_dirs)
        out = np.zeros((P, D, 3) if D else (P, 3), np.float32)
        ml = self.lobe_m if not D else 0
        lobe_t = self.params.lobe_tan(recv.roughness) if ml else np.zeros(P, np.float32)
        n_lobe = int(np.count_nonzero(lobe_t))
        if n_lobe == 0:
            ml = 0
        tile = tile_size(m, self.budget, self.max_ssbo, P, ml)
        if D:   # the outputs (tile·D vec4) within the budget as well
            tile = max(1, min(tile, int(self.budget // (16 * D + m * m * TEXEL_BYTES))))
        stats: dict[str, Any] = {"receivers": P, "tile_receivers": tile, "tiles": 0, "nodes_visited": 0,
                                 "microbuffer_bytes": tile * (m * m + ml * ml) * TEXEL_BYTES, "start_nodes": 0,
                                 "lobe_receivers": n_lobe, "lobe_m": ml, "lobe_nodes_visited": 0}
        if P == 0:
            return out, stats
        mb = ctx.buffer(reserve=tile * m * m * TEXEL_BYTES)
        lobe_buf = ctx.buffer(reserve=tile * max(ml, 1) ** 2 * TEXEL_BYTES)
        bufs = {k: ctx.buffer(reserve=tile * 16 * (max(D, 1) if k == "out" else 1)) for k in ("a", "b", "c", "d", "e", "out")}
        vdir = ctx.buffer(np.concatenate([np.asarray(view_dirs, np.float32).reshape(D, 3), np.zeros((D, 1), np.float32)],
                                         1).tobytes()) if D else None
        self.view_dir_buf = vdir if vdir is not None else self.obj_dir_buf
        self._set(self.gather, n_views=D)
        self._n_views = D
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
                for lo, hi in fitting_ranges(tlo, thi, toffs, sn_limit // 4):
                    stats["start_list_splits"] += 1
                    n = hi - lo
                    r = recv.slice(lo, hi)
                    with t.step("upload"):
                        bufs["a"].write(np.concatenate([r.position, r.roughness[:, None]], 1).astype(np.float32).tobytes())
                        bufs["b"].write(np.concatenate([r.normal, r.metallic[:, None]], 1).astype(np.float32).tobytes())
                        bufs["c"].write(np.concatenate([r.base_color, lobe_t[lo:hi, None]], 1).astype(np.float32).tobytes())
                        bufs["d"].write(np.concatenate([r.view, np.zeros((n, 1))], 1).astype(np.float32).tobytes())
                        bufs["e"].write(np.concatenate([r.geometric, np.zeros((n, 1))], 1).astype(np.float32).tobytes())
                        mb.clear(size=n * m * m * TEXEL_BYTES, chunk=empty_texel)
                        if ml:
                            lobe_buf.clear(size=n * ml * ml * TEXEL_BYTES, chunk=empty_texel)
                        if toffs is not None:
                            a, b = toffs[lo - tlo], toffs[hi - tlo]
                            offs = (toffs[lo - tlo:hi - tlo + 1] - a).astype(np.uint32)
                            snodes = tsnodes[a:b]
                            off_buf = ctx.buffer(offs.tobytes())
                            sn_buf = ctx.buffer(snodes.tobytes() if snodes.size else b"\0" * 4)
                            stats["start_nodes"] += int(snodes.size)
                        else:
                            off_buf, sn_buf = dummy, dummy
                    self._walk_tile(n, bufs, mb, lobe_buf, state, pending, off_buf, sn_buf, start_lists is not None,
                                    ml > 0 and bool(np.any(lobe_t[lo:hi] > 0)), t, stats)
                    with t.step("readback"):
                        res = np.frombuffer(bufs["out"].read(size=n * 16 * max(D, 1)), np.float32)
                        out[lo:hi] = res.reshape((n, D, 4) if D else (n, 4))[..., :3]
                        if self.keep_microbuffers:
                            self.last_microbuffers = np.frombuffer(mb.read(size=n * m * m * TEXEL_BYTES), np.float32).reshape(n, m, m, 4).copy()
                            if ml:
                                self.last_lobe_buffers = np.frombuffer(lobe_buf.read(size=n * ml * ml * TEXEL_BYTES),
                                                                       np.float32).reshape(n, ml, ml, 4).copy()
                    if toffs is not None:
                        off_buf.release()
                        sn_buf.release()
                stats["tiles"] += 1
            stats["start_list_splits"] -= stats["tiles"]
        finally:
            for b in (mb, lobe_buf, state, pending, dummy, *bufs.values(), *((vdir,) if vdir is not None else ())):
                b.release()
            self._set(self.gather, n_views=0)
            self._n_views = 0
        err = ctx.error
        if err != "GL_NO_ERROR":
            raise RuntimeError(f"GL error after the PBGI gather: {err}")
        return out, stats

    def _bind(self, bufs: dict, mb: Any, lobe_buf: Any, state: Any, pending: Any, off_buf: Any, sn_buf: Any) -> None:
        """Bind a tile's buffers and the gatherer's own to their GATHER_BINDINGS slots."""
        B = GATHER_BINDINGS
        for buf, name in ((self.node_buf, "NODES"), (mb, "MICROBUFFER"), (self.texel_buf, "TEXELS"), (bufs["a"], "RECV_A"),
                          (bufs["b"], "RECV_B"), (off_buf, "START_OFF"), (sn_buf, "START_NODE"), (state, "STATE"),
                          (bufs["c"], "RECV_C"), (bufs["d"], "RECV_D"), (bufs["e"], "RECV_E"), (bufs["out"], "OUT"), (pending, "PENDING"),
                          (self.splat_buf, "SPLAT"), (self.emit_buf, "EMIT"), (lobe_buf, "LOBE"),
                          (self.obj_dir_buf, "OBJ_DIRS"), (self.view_dir_buf, "VIEW_DIRS")):
            buf.bind_to_storage_buffer(B[name])

    def _resumable(self, prog: Any, n: int, pending: Any) -> int:
        """Run ``prog`` over n receivers in passes until none is pending (llvmpipe stops a loop after 65 535
        iterations: each pass does ``iter_budget`` and saves its state); returns the passes run."""
        passes = 0
        while True:
            check_interrupt()
            pending.write(np.zeros(1, np.uint32).tobytes())
            self._set(prog, init=int(passes == 0))
            for first in range(0, n, self.DISPATCH):
                self._set(prog, first=first)
                prog.run(group_x=(min(self.DISPATCH, n - first) + 63) // 64)
            passes += 1
            if int(np.frombuffer(pending.read(), np.uint32)[0]) == 0:
                return passes

    def _gather(self, n: int, t: Timings) -> None:
        """Eq. 9 for n receivers (× the view directions in directions mode)."""
        with t.step("gather"):
            self._set(self.gather, n_recv=n)
            ng = n * max(self._n_views, 1)
            for first in range(0, ng, self.DISPATCH):
                self._set(self.gather, first=first)
                self.gather.run(group_x=(min(self.DISPATCH, ng - first) + 63) // 64)
            self.ctx.finish()

    def _walk_tile(self, n: int, bufs: dict, mb: Any, lobe_buf: Any, state: Any, pending: Any, off_buf: Any,
                   sn_buf: Any, use_lists: bool, lobe: bool, t: Timings, stats: dict[str, Any]) -> None:
        """Walk n receivers (resumable passes) into their micro-buffers, then (``lobe``) the glossy ones
        from the root into their lobe buffers, then the Eq. 9 gather. Node visits add to ``stats``."""
        self._bind(bufs, mb, lobe_buf, state, pending, off_buf, sn_buf)
        if self.texel_ubo is not None:
            self.texel_ubo.bind_to_uniform_block(self.TEXEL_UBO_BINDING)
        if self.node_tex is not None:
            self.node_tex.use(location=self.NODE_TEX_UNIT)
        for lobe_pass in ((0, 1) if lobe else (0,)):
            walk = self.walk_lobe if lobe_pass else self.walk
            self._set(walk, n_recv=n, use_lists=int(use_lists and not lobe_pass), iter_budget=self.iter_budget)
            with t.step("walk_lobe" if lobe_pass else "walk"):
                passes = self._resumable(walk, n, pending)
                st = np.frombuffer(state.read(size=n * 16), np.uint32).reshape(n, 4)
                visits = int(st[:, 3].astype(np.int64).sum())
            stats["lobe_nodes_visited" if lobe_pass else "nodes_visited"] += visits
            stats["walk_passes"] = max(stats["walk_passes"], passes)
        self._gather(n, t)

    def release(self) -> None:
        for b in (self.node_buf, self.texel_buf, self.splat_buf, self.emit_buf, self.texel_ubo, self.obj_dir_buf,
                  self.node_tex):
            if b is not None:
                b.release()
        for w in self.walks:
            w.release()
        self.gather.release()
