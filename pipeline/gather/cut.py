"""Mipmapped and Hybrid PBGI cut finding (paper 000 §5.2.1, §5.2.2, §5.4), shared by the
``mipmapped`` and ``hybrid`` gatherers.

The walk (``walk.comp.glsl``) fills each receiver's micro-buffer by walking a list of start
nodes. Classic PBGI starts every receiver at the root. This module finds the start lists the other
two ways, with the iterative traversal over (node, pixel) pairs of the paper: a geometry shader under
transform feedback (``cut.geom.glsl``), ping-pong buffers, Z-order pixel indices, the three
cases of Fig. 7 on a *cone mip-map* of the G-buffer normals (Eq. 6–8).

- ``mipmapped``: the traversal runs to the end; every output pair (pixel, node) is a node the classic
  walk of that pixel splats at once (stop rule or leaf), so the gather splats it without descending.
- ``hybrid``: the traversal stops as soon as Ω(A) < Ω_tr (= omega_tr × Ω_pix, default 32) or the pixel
  is at level 0; the pair is handed to the classic walk, restricted to A's sub-tree, for every level-0
  pixel below the (possibly coarse) pixel. Hand-offs arrive on a second transform-feedback stream.

Exactness (stronger than the paper, which culls with the pixel's cone only): a coarse pixel stands for a
*set* of receivers (positions in a bounding sphere, normals in a cone), so the geometry shader refines a
node only when every receiver below would refine it in the classic walk and drops it only when every
receiver culls it; otherwise it splits the pixel (Fig. 7b). At level 0 it takes the classic walk's own
decision (same GLSL functions of ``pbgi_common.glsl``). Hence each receiver's cut is the classic cut and
the three methods give the same micro-buffers (up to floating-point ties), which the tests check.

Transform feedback: one geometry-shader pass per iteration writes two vertex streams into two buffers
(GL 4 ``EmitStreamVertex``; measured to work on Mesa llvmpipe 22.3 as on GPUs); the counts come from
an SSBO atomic counter per stream.

Memory: pairs are processed in chunks of at most ``capacity`` input pairs, so the transform-feedback
buffers (two ping-pong buffers of 4·capacity pairs + one hand-off buffer of capacity pairs, 8 bytes a
pair) never exceed the budget; a frontier larger than a chunk waits in host memory (a stack, processed
depth first). Pixel indices are row-major within the tile (y·w + x); output is sorted by (pixel, node).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..bsh.format import CUT_BINDINGS, LEAF, as_nodes, cone_trig_table, decode_cones, glsl_defines
from ..runtime import get_logger
from .base import GatherParams

log = get_logger("pbgi_mipmap")

LEVEL_SHIFT = 27                      # pixel code = level << 27 | Morton index at that level
CODE_MASK = (1 << LEVEL_SHIFT) - 1
MAX_LEVELS = 14                       # tiles up to 8192² (Morton indices of 26 bits)
ANG_EPS = 1e-4                        # coarse-level safety margins (see the geometry shader)
REL_EPS = 1e-4
CONE_MARGIN = 1e-6                    # added to each mip cone's half-angle [rad] (float32 rounding)
PAIR_BYTES = 8


# ----------------------------------------------------------------------------------------------------
# Z-order (Morton 2-D) indices
# ----------------------------------------------------------------------------------------------------
def _part1by1(v: np.ndarray) -> np.ndarray:
    v = v.astype(np.uint32) & np.uint32(0x0000FFFF)
    v = (v | (v << np.uint32(8))) & np.uint32(0x00FF00FF)
    v = (v | (v << np.uint32(4))) & np.uint32(0x0F0F0F0F)
    v = (v | (v << np.uint32(2))) & np.uint32(0x33333333)
    v = (v | (v << np.uint32(1))) & np.uint32(0x55555555)
    return v


def _compact1by1(v: np.ndarray) -> np.ndarray:
    v = v.astype(np.uint32) & np.uint32(0x55555555)
    v = (v | (v >> np.uint32(1))) & np.uint32(0x33333333)
    v = (v | (v >> np.uint32(2))) & np.uint32(0x0F0F0F0F)
    v = (v | (v >> np.uint32(4))) & np.uint32(0x00FF00FF)
    v = (v | (v >> np.uint32(8))) & np.uint32(0x0000FFFF)
    return v


def morton_encode(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Z-order index of pixel (x = column, y = row), both < 2¹⁶: x in the even bits, y in the odd bits.
    The four children of index c one level finer are 4c + (dx + 2·dy)."""
    x = np.asarray(x)
    y = np.asarray(y)
    if np.any(x < 0) or np.any(y < 0) or np.any(x >= 1 << 16) or np.any(y >= 1 << 16):
        raise ValueError("morton_encode: coordinates must be in [0, 65536)")
    return _part1by1(x) | (_part1by1(y) << np.uint32(1))


def morton_decode(code: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`morton_encode`: (x, y) as uint32 arrays."""
    code = np.asarray(code).astype(np.uint32)
    return _compact1by1(code), _compact1by1(code >> np.uint32(1))


# ----------------------------------------------------------------------------------------------------
# Cone mip-map of the G-buffer normals (Eq. 6–8 need, per coarse pixel, a cone of normals and — since
# positions differ inside a coarse pixel — a bounding sphere of the receivers' positions)
# ----------------------------------------------------------------------------------------------------
def _round_up_f32(x: np.ndarray) -> np.ndarray:
    """float64 → float32, rounded towards +inf (so a bound stays a bound)."""
    f = np.asarray(x, np.float64).astype(np.float32)
    low = f.astype(np.float64) < x
    return np.where(low, np.nextafter(f, np.float32(np.inf)), f).astype(np.float32)


def cone_mipmap(normals: np.ndarray, mask: np.ndarray, positions: np.ndarray | None = None) -> list[dict[str, Any]]:
    """Cone mip-map of a G-buffer tile.

    ``normals`` (H,W,3) unit shading normals, ``mask`` (H,W) bool (receiver present), ``positions``
    (H,W,3) world positions [m] (zeros when omitted). The tile is padded (empty) to S×S, S the next
    power of two ≥ max(H, W). Level l is (S/2^l)×(S/2^l); its pixel (i, j) covers the level-0 block
    rows [i·2^l, (i+1)·2^l), columns [j·2^l, (j+1)·2^l).

    Per level a dict with ``axis`` (n,n,3) f4, ``half_angle`` (n,n) f4 [rad], ``center`` (n,n,3) f4,
    ``radius`` (n,n) f4 [m], ``mask`` (n,n) bool, ``level``. Level 0 is the G-buffer itself (axis =
    the normal as given, half-angle 0, centre = the position, radius 0). Above it the cone axis is the
    normalised mean of the level-0 normals below and the half-angle the largest angle between that
    (float32) axis and any of them, evaluated in float64, plus 1e-6 rad, rounded up to float32 — so the
    cone contains every level-0 normal below it (the paper builds it like the BSH's cones, [BE05]; the
    direct max is at least as tight and exact). A zero mean (opposite normals) gives the whole sphere
    (half-angle π). The bounding sphere: centre of the bounding box of the level-0 positions below,
    radius the largest distance to them (float64, rounded up): the receiver geometry of a coarse pixel
    is enlarged to this sphere in every test of the traversal (conservative).
    """
    normals = np.asarray(normals)
    mask = np.asarray(mask).astype(bool)
    if normals.ndim != 3 or normals.shape[2] != 3 or mask.shape != normals.shape[:2]:
        raise ValueError(f"cone_mipmap: normals must be (H,W,3) and mask (H,W), got {normals.shape}, {mask.shape}")
    h, w = mask.shape
    if positions is None:
        positions = np.zeros((h, w, 3), np.float32)
    positions = np.asarray(positions)
    s = 1 << max(0, math.ceil(math.log2(max(h, w, 1))))
    nlev = int(round(math.log2(s))) + 1
    if nlev > MAX_LEVELS:
        raise ValueError(f"cone_mipmap: tile {h}x{w} too large (at most {1 << (MAX_LEVELS - 1)} a side)")
    m0 = np.zeros((s, s), bool)
    m0[:h, :w] = mask
    n32 = np.zeros((s, s, 3), np.float32)
    n32[:h, :w] = normals
    p32 = np.zeros((s, s, 3), np.float32)
    p32[:h, :w] = positions
    n32[~m0] = 0.0
    p32[~m0] = 0.0
    n64 = n32.astype(np.float64)
    p64 = p32.astype(np.float64)
    levels = [{"level": 0, "axis": n32, "half_angle": np.zeros((s, s), np.float32), "center": p32,
               "radius": np.zeros((s, s), np.float32), "mask": m0}]
    for lev in range(1, nlev):
        b = 1 << lev
        k = s >> lev
        nb = n64.reshape(k, b, k, b, 3)
        mb = m0.reshape(k, b, k, b)
        cnt = mb.sum(axis=(1, 3))
        nonempty = cnt > 0
        ssum = nb.sum(axis=(1, 3))                       # empty normals are zero
        norm = np.linalg.norm(ssum, axis=-1)
        degenerate = nonempty & (norm <= 1e-6 * np.maximum(cnt, 1))
        axis = np.where((norm > 0)[..., None], ssum / np.maximum(norm, 1e-300)[..., None], 0.0)
        axis[degenerate] = (0.0, 0.0, 1.0)
        axis32 = axis.astype(np.float32)
        a64 = axis32.astype(np.float64)
        a64 /= np.maximum(np.linalg.norm(a64, axis=-1, keepdims=True), 1e-300)
        cosang = np.einsum("ibjdc,ijc->ibjd", nb, a64)
        lens = np.linalg.norm(nb, axis=-1)
        cosang = np.clip(cosang / np.maximum(lens, 1e-300), -1.0, 1.0)
        ang = np.where(mb, np.arccos(cosang), 0.0).max(axis=(1, 3))
        ang = np.where(degenerate, np.pi, np.minimum(ang + CONE_MARGIN, np.pi))
        half = np.where(nonempty, _round_up_f32(ang), 0.0).astype(np.float32)
        half = np.minimum(half, np.float32(np.pi))
        pb = p64.reshape(k, b, k, b, 3)
        lo = np.where(mb[..., None], pb, np.inf).min(axis=(1, 3))
        hi = np.where(mb[..., None], pb, -np.inf).max(axis=(1, 3))
        lo[~nonempty] = 0.0
        hi[~nonempty] = 0.0
        ctr = (0.5 * (lo + hi)).astype(np.float32)
        dd = np.linalg.norm(pb - ctr.astype(np.float64)[:, None, :, None, :], axis=-1)
        rad = np.where(mb, dd, 0.0).max(axis=(1, 3))
        rad = rad * (1.0 + 1e-6) + 1e-30
        rad = np.where(nonempty, _round_up_f32(rad), 0.0).astype(np.float32)
        axis32[~nonempty] = 0.0
        levels.append({"level": lev, "axis": axis32, "half_angle": half, "center": ctr, "radius": rad,
                       "mask": nonempty})
    return levels


@dataclass
class Pyramid:
    """The cone mip-map in the GPU layout: every level in Z-order, levels concatenated (level 0 first).
    ``cone`` (T,4) f4 = (axis, cos γ') with γ' = min(γ + ANG_EPS, π) the half-angle widened by the
    safety margin (1 at level 0, unused there), ``sphere`` (T,4) f4 = (centre, radius; −1 for empty),
    ``level_off`` (L,) first entry of each level, ``size`` S, ``h``, ``w`` the real tile size."""

    cone: np.ndarray
    sphere: np.ndarray
    level_off: np.ndarray
    size: int
    h: int
    w: int
    norm_eps: float = 0.0     # max | |n| − 1 | over the receivers' normals (non-unit normals widen the margins)

    @property
    def n_levels(self) -> int:
        return len(self.level_off)

    def level0_codes(self) -> np.ndarray:
        """Sorted Z-order indices of the non-empty level-0 pixels."""
        n0 = self.size * self.size
        return np.flatnonzero(self.sphere[:n0, 3] >= 0).astype(np.uint32)


def build_pyramid(levels: list[dict[str, Any]], h: int, w: int) -> Pyramid:
    """Lay the levels of :func:`cone_mipmap` out in Z-order for the geometry shader."""
    s = levels[0]["mask"].shape[0]
    offs, cones, sphs = [], [], []
    off = 0
    for lv in levels:
        k = lv["mask"].shape[0]
        yy, xx = np.mgrid[0:k, 0:k]
        code = morton_encode(xx.ravel(), yy.ravel())
        cone = np.zeros((k * k, 4), np.float32)
        sph = np.full((k * k, 4), -1.0, np.float32)
        cone[code, :3] = lv["axis"].reshape(-1, 3)
        gam = np.minimum(lv["half_angle"].astype(np.float64) + ANG_EPS, np.pi)
        cone[code, 3] = 1.0 if lv["level"] == 0 else np.cos(gam).ravel()
        m = lv["mask"].ravel()
        sph[code[m], :3] = lv["center"].reshape(-1, 3)[m]
        sph[code[m], 3] = lv["radius"].ravel()[m]
        offs.append(off)
        off += k * k
        cones.append(cone)
        sphs.append(sph)
    n0 = levels[0]["axis"][levels[0]["mask"]].astype(np.float64)
    dev = float(np.max(np.abs(np.linalg.norm(n0, axis=1) - 1.0))) if len(n0) else 0.0
    norm_eps = float(_round_up_f32(np.array(dev * (1 + 1e-3) + 1e-7)))
    return Pyramid(np.concatenate(cones), np.concatenate(sphs), np.asarray(offs, np.uint32), s, h, w, norm_eps)


# ----------------------------------------------------------------------------------------------------
# Pair bookkeeping shared by the GPU driver and the CPU simulation
# ----------------------------------------------------------------------------------------------------
def _root_pairs(pyr: Pyramid) -> np.ndarray:
    top = pyr.n_levels - 1
    if pyr.sphere[pyr.level_off[top], 3] < 0:        # empty tile
        return np.zeros((0, 2), np.uint32)
    return np.array([[0, top << LEVEL_SHIFT]], np.uint32)


def _expand_done(done: np.ndarray, pyr: Pyramid) -> tuple[np.ndarray, np.ndarray]:
    """Finished (node, pixel code) pairs → (row-major level-0 pixel index int32, node uint32), sorted
    by (pixel, node). A coarse pixel (hybrid hand-off) expands to every non-empty level-0 pixel below."""
    if len(done) == 0:
        return np.zeros(0, np.int32), np.zeros(0, np.uint32)
    node = done[:, 0].astype(np.uint32)
    lev = (done[:, 1] >> np.uint32(LEVEL_SHIFT)).astype(np.int64)
    code = (done[:, 1] & np.uint32(CODE_MASK)).astype(np.int64)
    z0 = pyr.level0_codes().astype(np.int64)
    lo = np.searchsorted(z0, code << (2 * lev))
    hi = np.searchsorted(z0, (code + 1) << (2 * lev))
    cnt = hi - lo
    tot = int(cnt.sum())
    starts = np.cumsum(cnt) - cnt
    idx = np.repeat(lo - starts, cnt) + np.arange(tot)
    z = z0[idx]
    node = np.repeat(node, cnt)
    x, y = morton_decode(z.astype(np.uint32))
    pix = (y.astype(np.int64) * pyr.w + x.astype(np.int64))
    key = (pix.astype(np.uint64) << np.uint64(32)) | node.astype(np.uint64)
    order = np.argsort(key, kind="stable")
    return pix[order].astype(np.int32), node[order]


def _tile_arrays(tile: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(position (h,w,3), normal (h,w,3), mask (h,w)) of a G-buffer tile given as a dict or an object
    with ``position``/``normal``/``mask`` (``alpha`` > 0 is accepted for the mask)."""
    def get(name: str) -> Any:
        if isinstance(tile, dict):
            return tile.get(name)
        return getattr(tile, name, None)

    pos = get("position")
    nrm = get("normal")
    mask = get("mask")
    if mask is None and get("alpha") is not None:
        mask = np.asarray(get("alpha")) > 0
    if pos is None or nrm is None or mask is None:
        raise ValueError("find_cut: the G-buffer tile needs position, normal and mask")
    return np.asarray(pos, np.float32), np.asarray(nrm, np.float32), np.asarray(mask).astype(bool)


# ----------------------------------------------------------------------------------------------------
# CPU (numpy, float32) simulation of the geometry shader — the test oracle for the pair counts
# ----------------------------------------------------------------------------------------------------
def decode_nodes(nodes: np.ndarray) -> dict[str, np.ndarray]:
    """float32 decode of the 40-byte nodes exactly as ``pbgi_common.glsl`` does."""
    nd = as_nodes(nodes)
    cone = nd["cone"].astype(np.uint32)
    axis, half = decode_cones(cone, np.float32)
    return {"right": nd["right"].astype(np.uint32), "center": nd["center"].astype(np.float32),
            "radius": nd["radius"].astype(np.float32), "cone": cone, "axis": axis, "half": half,
            "all_dirs": (cone >> np.uint32(24)) == 255, "leaf": nd["right"] == LEAF}


def node_solid_angle(dist: np.ndarray, r: np.ndarray) -> np.ndarray:
    f = np.float32
    s = (r / np.where(dist > 0, dist, f(1))).astype(f)
    s2 = s * s
    om = f(2 * np.pi) * s2 / (f(1) + np.sqrt(np.maximum(f(1) - s2, f(0))))
    return np.where(dist <= r, f(2 * np.pi), om).astype(f)


def _step_cpu(pairs: np.ndarray, pyr: Pyramid, nd: dict[str, np.ndarray], prm: GatherParams,
              hybrid: bool) -> tuple[np.ndarray, np.ndarray]:
    """One traversal iteration on the CPU, mirroring ``cut.geom.glsl`` (float32 arithmetic).
    Returns (next pairs, finished pairs)."""
    f = np.float32
    node = pairs[:, 0]
    pix = pairs[:, 1]
    level = (pix >> np.uint32(LEVEL_SHIFT)).astype(np.int64)
    code = (pix & np.uint32(CODE_MASK)).astype(np.int64)
    ent = pyr.level_off[level].astype(np.int64) + code
    pc = pyr.cone[ent]
    ps = pyr.sphere[ent]
    c = nd["center"][node]
    r = nd["radius"][node]
    leaf = nd["leaf"][node]
    right = nd["right"][node]
    stop_mult, omega_pix, omega_tr = f(prm.stop_multiple), f(prm.omega_pix), f(prm.omega_tr_sr)
    nxt, done = [], []

    # level 0: the classic walk's decision
    z = level == 0
    v = (c[z] - ps[z, :3]).astype(f)
    dist = np.sqrt((v * v).sum(-1, dtype=f)).astype(f)
    n = pc[z, :3]
    hz = (v * n).sum(-1, dtype=f) < -r[z]
    hcs = cone_trig_table()[nd["cone"][node[z]] >> np.uint32(24)]      # pbgi_backface_cull, without trigonometry
    sd = np.minimum(r[z] / np.where(dist > 0, dist, f(1)), f(1)).astype(f)
    cd = np.sqrt(np.maximum(f(1) - sd * sd, f(0))).astype(f)
    vax = (v * nd["axis"][node[z]]).sum(-1, dtype=f)
    bf = ((~nd["all_dirs"][node[z]]) & (dist > r[z]) & (hcs[:, 0] * cd - hcs[:, 1] * sd > f(0))
          & (vax > dist * (hcs[:, 1] * cd + hcs[:, 0] * sd)))
    keep = ~(hz | bf)
    if hybrid:
        done.append(pairs[z][keep])
    else:
        om = node_solid_angle(dist, r[z])
        stop = leaf[z] | (om <= stop_mult * omega_pix)
        done.append(pairs[z][keep & stop])
        ref = keep & ~stop
        pz = pairs[z][ref]
        nxt.append(np.stack([pz[:, 0] + 1, pz[:, 1]], 1).astype(np.uint32))
        nxt.append(np.stack([right[z][ref], pz[:, 1]], 1).astype(np.uint32))

    # coarse levels (algebraic bounds, as the geometry shader)
    q = ~z
    if np.any(q):
        pq = pairs[q]
        cq, rq = c[q], r[q]
        w, cg = pc[q, :3], pc[q, 3]
        sg = np.sqrt(np.maximum(f(1) - cg * cg, f(0))).astype(f)
        cp, rp = ps[q, :3], ps[q, 3]
        D = (cq - cp).astype(f)
        d = np.sqrt((D * D).sum(-1, dtype=f)).astype(f)
        len_eps = (f(REL_EPS) * (d + rq + rp) + f(pyr.norm_eps) * (d + rp)).astype(f)
        dw = (w * D).sum(-1, dtype=f)
        dsin = np.sqrt(np.maximum(d * d - dw * dw, f(0))).astype(f)
        dot_max = (np.where(dw >= d * cg, d, dw * cg + dsin * sg) + rp).astype(f)
        dot_min = (np.where(dw <= -d * cg, -d, dw * cg - dsin * sg) - rp).astype(f)
        hz_all = dot_max + len_eps < -rq
        hz_none = dot_min - len_eps >= -rq
        nq = node[q]
        abyte = nd["cone"][nq] >> np.uint32(24)
        alld = abyte == 255
        trig = cone_trig_table()[abyte]
        hc, hs = trig[:, 0], trig[:, 1]
        ua = -(D * nd["axis"][nq]).sum(-1, dtype=f)
        bf_none = alld | (abyte >= 128) | (d + rp + len_eps <= rq)
        test = (~bf_none) & (d > rp + len_eps)
        sd = np.minimum(rq / (d + rp), f(1)).astype(f)
        smin = (hs * np.sqrt(np.maximum(f(1) - sd * sd, f(0))) + hc * sd).astype(f)
        bf_none = np.where(test, ua - rp + (d - rp) * smin - len_eps >= f(0), bf_none)
        far = (~alld) & (abyte < 128) & (d - rp > rq + len_eps)
        dm = np.where(far, d - rp, f(1)).astype(f)
        sd = np.minimum(rq / dm, f(1)).astype(f)
        cdl = np.sqrt(np.maximum(f(1) - sd * sd, f(0))).astype(f)
        cmax = (hc * cdl - hs * sd).astype(f)
        smax = (hs * cdl + hc * sd).astype(f)
        bf_all = far & (cmax > f(REL_EPS)) & (ua + rp + (d + rp) * smax + len_eps < f(0))
        alive = ~(hz_all | bf_all)
        om_c = node_solid_angle(d, rq)
        handoff = alive & (om_c < omega_tr) if hybrid else np.zeros_like(alive)
        done.append(pq[handoff])
        rest = alive & ~handoff
        refine_all = (~leaf[q]) & (node_solid_angle((d + rp).astype(f), rq) > stop_mult * omega_pix * f(1 + REL_EPS))
        om_p = (f(2 * np.pi) * (f(1) - cg)).astype(f)
        fig7a = rest & refine_all & hz_none & bf_none & (om_c > om_p)
        fig7b = rest & ~fig7a
        pa = pq[fig7a]
        nxt.append(np.stack([pa[:, 0] + 1, pa[:, 1]], 1).astype(np.uint32))
        nxt.append(np.stack([right[q][fig7a], pa[:, 1]], 1).astype(np.uint32))
        pb = pq[fig7b]
        cl = ((pb[:, 1] >> np.uint32(LEVEL_SHIFT)) - 1).astype(np.int64)
        cc = (pb[:, 1] & np.uint32(CODE_MASK)).astype(np.int64)
        for k in range(4):
            child = 4 * cc + k
            ok = pyr.sphere[pyr.level_off[cl].astype(np.int64) + child, 3] >= 0
            nxt.append(np.stack([pb[ok, 0], ((cl[ok] << LEVEL_SHIFT) | child[ok]).astype(np.uint32)], 1).astype(np.uint32))
    nx = np.concatenate(nxt) if nxt else np.zeros((0, 2), np.uint32)
    dn = np.concatenate(done) if done else np.zeros((0, 2), np.uint32)
    return nx.astype(np.uint32).reshape(-1, 2), dn.astype(np.uint32).reshape(-1, 2)


def simulate_cut(gbuffer_tile: Any, nodes: np.ndarray, params: GatherParams, hybrid: bool) -> tuple[np.ndarray, np.ndarray, dict]:
    """CPU (numpy float32) breadth-first run of the same traversal as :func:`find_cut`. Same outputs;
    ``stats["pairs_per_iteration"]`` etc. must equal the GPU's exactly (up to float ties)."""
    pos, nrm, mask = _tile_arrays(gbuffer_tile)
    h, w = mask.shape
    pyr = build_pyramid(cone_mipmap(nrm, mask, pos), h, w)
    nd = decode_nodes(nodes)
    frontier = _root_pairs(pyr)
    per_it, next_it, done_it, done_all = [], [], [], []
    while len(frontier):
        nx, dn = _step_cpu(frontier, pyr, nd, params, hybrid)
        per_it.append(len(frontier))
        next_it.append(len(nx))
        done_it.append(len(dn))
        done_all.append(dn)
        frontier = nx
    done = np.concatenate(done_all) if done_all else np.zeros((0, 2), np.uint32)
    pix, node = _expand_done(done, pyr)
    return pix, node, {"iterations": len(per_it), "pairs_per_iteration": per_it, "next_per_iteration": next_it,
                       "done_per_iteration": done_it, "finished_pairs": int(len(done)), "output_pairs": int(len(pix))}


# ----------------------------------------------------------------------------------------------------
# GPU: geometry shader + transform feedback, ping-pong, chunked under the memory budget
# ----------------------------------------------------------------------------------------------------
class _GpuState:
    def __init__(self, ctx: Any):
        import moderngl

        from .. import gl

        self.ctx = ctx
        self.prog = gl.make_program(ctx, "cut.vert.glsl", geometry="cut.geom.glsl",
                                    varyings=("o_next", "gl_NextBuffer", "o_done"), here=__file__,
                                    defines=glsl_defines(CUT_BINDINGS))
        self.fbo = ctx.framebuffer(color_attachments=[ctx.renderbuffer((1, 1), components=4)])
        self.counter = ctx.buffer(reserve=16)
        self.bufs = [ctx.buffer(reserve=PAIR_BYTES), ctx.buffer(reserve=PAIR_BYTES)]
        self.done = ctx.buffer(reserve=PAIR_BYTES)
        self.vaos = [ctx.vertex_array(self.prog, [(b, "2u", "in_pair")], mode=moderngl.POINTS) for b in self.bufs]
        self.mode = moderngl.POINTS


def _state(ctx: Any) -> _GpuState:
    extra = getattr(ctx, "extra", None)
    if not isinstance(extra, dict):
        extra = {}
        ctx.extra = extra
    st = extra.get("pbgi_mipmap")
    if st is None:
        st = _GpuState(ctx)
        extra["pbgi_mipmap"] = st
    return st


def _ensure(buf: Any, nbytes: int, limit: int) -> None:
    """Grow ``buf`` (contents discarded) to hold ``nbytes``, doubling but never beyond ``limit``."""
    if buf.size < nbytes:
        buf.orphan(max(nbytes, min(2 * buf.size, limit)))


def chunk_capacity(tf_budget: int) -> int:
    """Input pairs per transform-feedback pass so that the two ping-pong buffers (4 outputs a pair each)
    and the hand-off buffer (1 a pair) fit in ``tf_budget`` bytes: 9 × 8 bytes a pair."""
    return max(1, int(tf_budget) // (9 * PAIR_BYTES))


def find_cut(ctx: Any, gbuffer_tile: Any, nodes_buffer: Any, params: GatherParams, hybrid: bool,
             tf_budget: int | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Mipmapped (``hybrid=False``) or Hybrid PBGI cut of one G-buffer tile.

    ``gbuffer_tile``: dict/object with ``position`` (h,w,3), ``normal`` (h,w,3), ``mask`` (h,w) —
    the same float32 values the gather walks with. ``nodes_buffer``: moderngl buffer of the 40-byte
    BSH nodes. ``params``: m, stop_multiple, omega_tr, memory_budget_bytes. ``tf_budget``: bytes for the
    transform-feedback buffers (default memory_budget_bytes / 4, the rest being the gather's).

    Returns (pixel_idx int32 (K,) row-major in the tile, start_node uint32 (K,), stats), sorted by
    (pixel, node). stats: iterations, pairs/next/done per iteration, passes (chunks), peak TF bytes
    (allocated), capacity, finished pairs (before the hybrid expansion), output pairs, seconds.
    """
    t0 = time.perf_counter()
    pos, nrm, mask = _tile_arrays(gbuffer_tile)
    h, w = mask.shape
    if tf_budget is None:
        tf_budget = max(int(params.memory_budget_bytes) // 4, 9 * PAIR_BYTES)
    cap = chunk_capacity(tf_budget)
    pyr = build_pyramid(cone_mipmap(nrm, mask, pos), h, w)
    t_mip = time.perf_counter() - t0
    stats: dict[str, Any] = {"method": "hybrid" if hybrid else "mipmapped", "mip_levels": pyr.n_levels,
                             "capacity_pairs": cap, "tf_budget_bytes": int(tf_budget), "passes": 0,
                             "pairs_per_iteration": [], "next_per_iteration": [], "done_per_iteration": [],
                             "peak_tf_bytes": 0, "host_spills": 0, "time_mipmap_s": t_mip}
    start = _root_pairs(pyr)
    if len(start) == 0:
        stats.update(iterations=0, finished_pairs=0, output_pairs=0, time_s=time.perf_counter() - t0)
        return np.zeros(0, np.int32), np.zeros(0, np.uint32), stats

    st = _state(ctx)
    prog = st.prog
    st.fbo.use()
    for b in (*st.bufs, st.done):                        # start small: the peak is this call's
        if b.size > PAIR_BYTES:
            b.orphan(PAIR_BYTES)
    lim_pp, lim_done = 4 * cap * PAIR_BYTES, cap * PAIR_BYTES
    cone_buf = ctx.buffer(pyr.cone.tobytes())
    sph_buf = ctx.buffer(pyr.sphere.tobytes())
    nodes_buffer.bind_to_storage_buffer(CUT_BINDINGS["NODES"])
    cone_buf.bind_to_storage_buffer(CUT_BINDINGS["MIP_CONE"])
    sph_buf.bind_to_storage_buffer(CUT_BINDINGS["MIP_SPHERE"])
    st.counter.bind_to_storage_buffer(CUT_BINDINGS["MIP_COUNT"])
    lo = np.zeros(16, np.uint32)
    lo[:pyr.n_levels] = pyr.level_off
    prog["level_off"].write(lo.tobytes())
    prog["stop_multiple"].value = float(params.stop_multiple)
    prog["omega_pix"].value = params.omega_pix
    prog["omega_tr"].value = params.omega_tr_sr
    prog["hybrid"].value = int(bool(hybrid))
    prog["pbgi_cone_trig"].write(cone_trig_table().tobytes())
    prog["rel_eps"].value = REL_EPS
    prog["norm_eps"].value = pyr.norm_eps

    def add(lst: list, t: int, v: int) -> None:
        while len(lst) <= t:
            lst.append(0)
        lst[t] += v

    zero = np.zeros(4, np.uint32).tobytes()
    done_parts: list[np.ndarray] = []
    stack: list[tuple[int, np.ndarray]] = [(0, start)]
    while stack:
        t, arr = stack.pop()
        if len(arr) > cap:                               # split: the rest waits on the host
            stack.append((t, arr[cap:]))
            arr = arr[:cap]
        cur = 0
        _ensure(st.bufs[cur], len(arr) * PAIR_BYTES, lim_pp)
        st.bufs[cur].write(np.ascontiguousarray(arr, np.uint32).tobytes())
        n = len(arr)
        while n > 0:                                     # ping-pong while the frontier fits a chunk
            out = 1 - cur
            _ensure(st.bufs[out], 4 * n * PAIR_BYTES, lim_pp)
            _ensure(st.done, n * PAIR_BYTES, lim_done)
            stats["peak_tf_bytes"] = max(stats["peak_tf_bytes"], st.bufs[0].size + st.bufs[1].size + st.done.size)
            st.counter.write(zero)
            st.vaos[cur].transform([st.bufs[out], st.done], st.mode, vertices=n)
            n0, n1 = (int(x) for x in np.frombuffer(st.counter.read(size=8), np.uint32))
            stats["passes"] += 1
            add(stats["pairs_per_iteration"], t, n)
            add(stats["next_per_iteration"], t, n0)
            add(stats["done_per_iteration"], t, n1)
            if n1:
                done_parts.append(np.frombuffer(st.done.read(size=n1 * PAIR_BYTES), np.uint32).reshape(-1, 2).copy())
            if n0 > cap:                                 # too big for one pass: spill to the host
                stack.append((t + 1, np.frombuffer(st.bufs[out].read(size=n0 * PAIR_BYTES), np.uint32).reshape(-1, 2).copy()))
                stats["host_spills"] += 1
                break
            cur, n, t = out, n0, t + 1
    err = ctx.error
    if err != "GL_NO_ERROR":
        raise RuntimeError(f"find_cut: OpenGL error {err}")
    cone_buf.release()
    sph_buf.release()
    done = np.concatenate(done_parts) if done_parts else np.zeros((0, 2), np.uint32)
    pix, node = _expand_done(done, pyr)
    stats.update(iterations=len(stats["pairs_per_iteration"]), finished_pairs=int(len(done)),
                 output_pairs=int(len(pix)), time_s=time.perf_counter() - t0)
    return pix, node, stats


# ----------------------------------------------------------------------------------------------------
# Start lists for the walk (pipeline.gather.walk.WalkGatherer.walk_and_gather)
# ----------------------------------------------------------------------------------------------------
def _merge_stats(agg: dict[str, Any], st: dict[str, Any]) -> None:
    agg["blocks"] += 1
    for key in ("passes", "finished_pairs", "output_pairs", "host_spills"):
        agg[key] += int(st.get(key, 0))
    for key in ("time_s", "time_mipmap_s"):
        agg[key] += float(st.get(key, 0.0))
    agg["peak_tf_bytes"] = max(agg["peak_tf_bytes"], int(st.get("peak_tf_bytes", 0)))
    agg["iterations"] = max(agg["iterations"], int(st.get("iterations", 0)))
    for key in ("pairs_per_iteration", "next_per_iteration", "done_per_iteration"):
        lst = agg[key]
        for t, v in enumerate(st.get(key, [])):
            if t >= len(lst):
                lst.append(0)
            lst[t] += int(v)


def make_start_lists(ctx: Any, position: np.ndarray, normal: np.ndarray, recv_pixel: np.ndarray,
                     shape: tuple[int, int], nodes_buffer: Any, params: GatherParams, hybrid: bool,
                     block: int = 128, tf_budget: int | None = None):
    """A ``StartLists`` callable for :meth:`pipeline.gather.walk.WalkGatherer.walk_and_gather` and the cut statistics.

    ``position``/``normal`` (P,3) float32 are the receivers exactly as the gather gets them (the same
    float32 values, so level-0 decisions match the classic walk bit for bit); ``recv_pixel`` (P,) the
    flat (row-major) viewport pixel of each receiver; ``shape`` = (H, W). For receivers [lo, hi) the
    callable runs :func:`find_cut` on square power-of-two blocks (≤ ``block`` a side) of their
    bounding box and returns CSR (offsets (n+1,) uint32, start nodes uint32) sorted by (receiver,
    node). The returned dict accumulates the stats of every block (pairs per iteration summed).
    """
    H, W = (int(shape[0]), int(shape[1]))
    position = np.asarray(position, np.float32)
    normal = np.asarray(normal, np.float32)
    recv_pixel = np.asarray(recv_pixel, np.int64)
    P = len(recv_pixel)
    recv_of = np.full(H * W, -1, np.int64)
    recv_of[recv_pixel] = np.arange(P)
    agg: dict[str, Any] = {"method": "hybrid" if hybrid else "mipmapped", "blocks": 0, "passes": 0,
                           "finished_pairs": 0, "output_pairs": 0, "host_spills": 0, "time_s": 0.0,
                           "time_mipmap_s": 0.0, "peak_tf_bytes": 0, "iterations": 0,
                           "pairs_per_iteration": [], "next_per_iteration": [], "done_per_iteration": []}

    def start_lists(lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
        n = hi - lo
        pix = recv_pixel[lo:hi]
        ys, xs = pix // W, pix % W
        y0, y1, x0, x1 = int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1
        ext = max(y1 - y0, x1 - x0)
        b = min(1 << max(0, math.ceil(math.log2(ext))), int(block))
        sel = np.zeros((y1 - y0, x1 - x0), bool)
        sel[ys - y0, xs - x0] = True
        rr_parts, nn_parts = [], []
        for by in range(y0, y1, b):
            for bx in range(x0, x1, b):
                hh, ww = min(b, y1 - by), min(b, x1 - bx)
                m_ = sel[by - y0:by - y0 + hh, bx - x0:bx - x0 + ww]
                if not m_.any():
                    continue
                gy, gx = np.nonzero(m_)
                k = recv_of[(gy + by) * W + gx + bx]
                pos = np.zeros((hh, ww, 3), np.float32)
                nrm = np.zeros((hh, ww, 3), np.float32)
                pos[gy, gx] = position[k]
                nrm[gy, gx] = normal[k]
                p_loc, nodes, st = find_cut(ctx, {"position": pos, "normal": nrm, "mask": m_}, nodes_buffer,
                                            params, hybrid, tf_budget=tf_budget)
                _merge_stats(agg, st)
                py, px = p_loc // ww, p_loc % ww
                rr_parts.append(recv_of[(py + by) * W + px + bx] - lo)
                nn_parts.append(nodes)
        rr = np.concatenate(rr_parts) if rr_parts else np.zeros(0, np.int64)
        nn = np.concatenate(nn_parts) if nn_parts else np.zeros(0, np.uint32)
        order = np.lexsort((nn, rr))
        rr, nn = rr[order], nn[order]
        offs = np.zeros(n + 1, np.uint32)
        offs[1:] = np.cumsum(np.bincount(rr, minlength=n))
        log.debug("%s cut of receivers %d..%d: %d start nodes (%.1f MiB), peak TF %.1f MiB so far",
                  agg["method"], lo, hi, len(nn), 4 * len(nn) / 2 ** 20, agg["peak_tf_bytes"] / 2 ** 20)
        return offs, nn.astype(np.uint32)

    return start_lists, agg
