"""Numba kernels of build-bsh (seed 000 §5.1, §5.4): Morton codes, radix sort, Karras 2012 LBVH,
bottom-up spheres / colours / normal cones, pruning and depth-first linearisation.

Conventions (see :mod:`pipeline.bsh.build_bsh` for the whole contract):

* Node ids before linearisation ("Karras ids"): internal node ``k`` of the LBVH is id ``k``
  (``0 <= k < L-1``, the root is 0), leaf ``k`` (the k-th non-empty voxel in Morton order) is id
  ``L-1+k``. With a single leaf the root is the leaf, id 0.
* A node's points are the contiguous range ``[first, first+count)`` of the Morton-sorted points.
* Everything geometric is accumulated in float64; stored centres and radii are float32 values
  chosen so that the containment invariants hold exactly in real arithmetic for the *stored*
  float32 numbers (centres rounded first, radii then computed from them and rounded up).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange
from numba.cpython.unsafe.numbers import leading_zeros

# numba's on-disk cache (__pycache__, git-ignored) spares the ~15 s compile on later runs
_CACHE = True
from .cones import angle, pack_cone  # noqa: E402  (the cone packer: one home)
from .format import UP32  # noqa: E402  (float32 round-up factor, one home)
# depth-first stacks: the LBVH over 64-bit codes + 64-bit index tie-breaks is at most 128 deep,
# and a pre-order stack holds at most depth + 1 entries
STACK = 160
# angular slack added to every computed cone half-angle [rad] (covers float64 rounding of acos/atan2)
ANGLE_EPS = 1e-9
# shrink_isolated_leaves: cells of at least this many leaves are tried on levels finer than the base one
DENSE = 24
# bottom_up: at most this many sub-trees done in parallel
SUBTREES = 256
# radix_argsort: contiguous chunks counted and scattered in parallel (at most; ≥ 65 536 keys each)
RADIX_CHUNKS = 8


# ----------------------------------------------------------------------------- input check
@njit(cache=_CACHE, parallel=True)
def check_normalise(points, normals, colors):
    """One pass over the cloud (in parallel): counts of points with a non-finite position, non-finite normal,
    zero-length (< 1e-6) normal and non-finite colour, and the unit normals (float32, normalised
    in float64)."""
    n = points.shape[0]
    out = np.empty((n, 3), dtype=np.float32)
    bad_p = 0
    bad_n = 0
    zero_n = 0
    bad_c = 0
    for i in prange(n):
        if not (np.isfinite(points[i, 0]) and np.isfinite(points[i, 1]) and np.isfinite(points[i, 2])):
            bad_p += 1
        if not (np.isfinite(colors[i, 0]) and np.isfinite(colors[i, 1]) and np.isfinite(colors[i, 2])):
            bad_c += 1
        x = np.float64(normals[i, 0]); y = np.float64(normals[i, 1]); z = np.float64(normals[i, 2])
        ln = 1.0
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            bad_n += 1
            x = 0.0; y = 0.0; z = 0.0
        else:
            ln = math.sqrt(x * x + y * y + z * z)
            if ln < 1e-6:
                zero_n += 1
                ln = 1.0
        out[i, 0] = np.float32(x / ln); out[i, 1] = np.float32(y / ln); out[i, 2] = np.float32(z / ln)
    return bad_p, bad_n, zero_n, bad_c, out


# ----------------------------------------------------------------------------- Morton codes
@njit(cache=_CACHE)
def _spread21(v):
    """Spread the low 21 bits of v so that bit i moves to bit 3i (uint64)."""
    x = np.uint64(v) & np.uint64(0x1FFFFF)
    x = (x | (x << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
    x = (x | (x << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
    x = (x | (x << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
    x = (x | (x << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
    x = (x | (x << np.uint64(2))) & np.uint64(0x1249249249249249)
    return x


@njit(cache=_CACHE, parallel=True)
def bounds(points):
    """(min (3,), max (3,)) of the (N, 3) points per axis, in their dtype (what ``points.min(axis=0)`` and
    ``max`` give; N ≥ 1, no NaN)."""
    n = points.shape[0]
    nch = min(n, 64)
    lo = np.empty((nch, 3), dtype=points.dtype)
    hi = np.empty((nch, 3), dtype=points.dtype)
    for c in prange(nch):
        s = (n * c) // nch
        e = (n * (c + 1)) // nch
        for a in range(3):
            lo[c, a] = points[s, a]
            hi[c, a] = points[s, a]
        for i in range(s + 1, e):
            for a in range(3):
                v = points[i, a]
                if v < lo[c, a]:
                    lo[c, a] = v
                if v > hi[c, a]:
                    hi[c, a] = v
    mn = lo[0].copy()
    mx = hi[0].copy()
    for c in range(1, nch):
        for a in range(3):
            mn[a] = min(mn[a], lo[c, a])
            mx[a] = max(mx[a], hi[c, a])
    return mn, mx


@njit(cache=_CACHE, parallel=True)
def morton_codes(points, lo, scale, bits):
    """64-bit Morton codes: cell q = clip(floor((p - lo) * scale), 0, 2^bits - 1) per axis,
    interleaved with x in the highest bit of each triple (x2 y2 z2 x1 y1 z1 ...)."""
    n = points.shape[0]
    out = np.empty(n, dtype=np.uint64)
    qmax = (1 << bits) - 1
    for i in prange(n):
        qx = int(math.floor((np.float64(points[i, 0]) - lo[0]) * scale))
        qy = int(math.floor((np.float64(points[i, 1]) - lo[1]) * scale))
        qz = int(math.floor((np.float64(points[i, 2]) - lo[2]) * scale))
        qx = min(max(qx, 0), qmax)
        qy = min(max(qy, 0), qmax)
        qz = min(max(qz, 0), qmax)
        out[i] = (_spread21(qx) << np.uint64(2)) | (_spread21(qy) << np.uint64(1)) | _spread21(qz)
    return out


@njit(cache=_CACHE, parallel=True)
def radix_argsort(keys, nbits):
    """Stable LSD radix argsort of uint64 keys using their low ``nbits`` bits (11-bit digits).

    Returns (order int64, sorted keys). Stable: equal keys keep increasing index order, which is
    the tie-break of Karras 2012. Each pass counts the digits of ``RADIX_CHUNKS`` contiguous chunks in
    parallel and scatters them in parallel, each chunk from its own offsets (chunk-major within a digit: the
    order of the sequential pass)."""
    n = keys.shape[0]
    idx = np.arange(n).astype(np.int64)
    k = keys.copy()
    if n <= 1:
        return idx, k
    k2 = np.empty_like(k)
    idx2 = np.empty_like(idx)
    digit = 11
    nb = 1 << digit
    mask = np.uint64(nb - 1)
    npass = (nbits + digit - 1) // digit
    nch = max(1, min(RADIX_CHUNKS, n // 65536))
    cnt = np.zeros((nch, nb), dtype=np.int64)
    for p in range(npass):
        sh = np.uint64(p * digit)
        for c in prange(nch):
            for b in range(nb):
                cnt[c, b] = 0
            for i in range((n * c) // nch, (n * (c + 1)) // nch):
                cnt[c, (k[i] >> sh) & mask] += 1
        # skip a pass whose digit is constant (e.g. unused high bits)
        d0 = (k[0] >> sh) & mask
        tot = 0
        for c in range(nch):
            tot += cnt[c, d0]
        if tot == n:
            continue
        s = 0
        for b in range(nb):
            for c in range(nch):
                x = cnt[c, b]
                cnt[c, b] = s
                s += x
        for c in prange(nch):
            for i in range((n * c) // nch, (n * (c + 1)) // nch):
                b = (k[i] >> sh) & mask
                j = cnt[c, b]
                cnt[c, b] = j + 1
                k2[j] = k[i]
                idx2[j] = idx[i]
        k, k2 = k2, k
        idx, idx2 = idx2, idx
    return idx, k


# ----------------------------------------------------------------------------- Karras 2012
@njit(cache=_CACHE)
def _delta(codes, i, j, n):
    """Length of the longest common prefix of keys i and j; keys are (code, index) so equal
    codes are broken by the index (Karras 2012 §4); -1 outside [0, n)."""
    if j < 0 or j >= n:
        return -1
    a = codes[i]
    b = codes[j]
    if a == b:
        return 64 + leading_zeros(np.uint64(i ^ j))
    return leading_zeros(a ^ b)


@njit(cache=_CACHE, parallel=True)
def karras_build(codes):
    """Binary radix tree over n >= 2 sorted codes (Karras 2012, Fig. 4), one parallel task per
    internal node. Returns (left, right) int64 (n-1,) in Karras ids (leaf k = n-1+k), and the
    leaf range (lo, hi) int64 (n-1,) of each internal node."""
    n = codes.shape[0]
    m = n - 1
    left = np.empty(m, dtype=np.int64)
    right = np.empty(m, dtype=np.int64)
    rlo = np.empty(m, dtype=np.int64)
    rhi = np.empty(m, dtype=np.int64)
    for i in prange(m):
        d = 1 if _delta(codes, i, i + 1, n) - _delta(codes, i, i - 1, n) > 0 else -1
        dmin = _delta(codes, i, i - d, n)
        lmax = 2
        while _delta(codes, i, i + lmax * d, n) > dmin:
            lmax *= 2
        ll = 0
        t = lmax // 2
        while t >= 1:
            if _delta(codes, i, i + (ll + t) * d, n) > dmin:
                ll += t
            t //= 2
        j = i + ll * d
        dnode = _delta(codes, i, j, n)
        s = 0
        div = 2
        while True:
            t = (ll + div - 1) // div
            if _delta(codes, i, i + (s + t) * d, n) > dnode:
                s += t
            if t == 1:
                break
            div *= 2
        gamma = i + s * d + min(d, 0)
        lo = min(i, j)
        hi = max(i, j)
        left[i] = (m + gamma) if lo == gamma else gamma
        right[i] = (m + gamma + 1) if hi == gamma + 1 else gamma + 1
        rlo[i] = lo
        rhi[i] = hi
    return left, right, rlo, rhi


@njit(cache=_CACHE)
def dfs_order(left, right, n_leaves):
    """Pre-order (left first) of the full tree in Karras ids; parents precede children."""
    total = 2 * n_leaves - 1
    out = np.empty(total, dtype=np.int64)
    if n_leaves == 1:
        out[0] = 0
        return out
    stack = np.empty(STACK, dtype=np.int64)
    sp = 0
    stack[0] = 0
    sp = 1
    k = 0
    m = n_leaves - 1
    while sp > 0:
        sp -= 1
        u = stack[sp]
        out[k] = u
        k += 1
        if u < m:
            if sp + 2 > STACK:
                raise ValueError("BSH deeper than the depth-first stack")
            stack[sp] = right[u]
            stack[sp + 1] = left[u]
            sp += 2
    return out


# ----------------------------------------------------------------------------- small geometry
@njit(cache=_CACHE)
def _round_up32(x):
    """Smallest-ish float32 value >= x (x >= 0), returned as float64."""
    return np.float64(np.float32(x * UP32))


@njit(cache=_CACHE)
def _unit3(x, y, z):
    """(x, y, z) normalised in float64 (float32 unit normals are off by ~1e-8)."""
    x = np.float64(x); y = np.float64(y); z = np.float64(z)
    ln = math.sqrt(x * x + y * y + z * z)
    return x / ln, y / ln, z / ln


@njit(cache=_CACHE)
def _welzl_cap(nrm, s, stride, c):
    """Minimum cap of the vectors nrm[s + (i·stride) mod c], i = 0…c−1 (normalised in float64), visited in
    that order — Welzl's incremental algorithm on the sphere (caps through 1, 2 or 3 boundary vectors). Exact
    when the vectors lie in an open hemisphere. Returns (axis x, y, z, cos of the half-angle)."""
    ux, uy, uz = _unit3(nrm[s, 0], nrm[s, 1], nrm[s, 2])
    ct = 1.0  # cos of half-angle
    tol = 1e-12
    for ii in range(1, c):
        pi_ = s + (ii * stride) % c
        px, py, pz = _unit3(nrm[pi_, 0], nrm[pi_, 1], nrm[pi_, 2])
        if ux * px + uy * py + uz * pz >= ct - tol:
            continue
        ux, uy, uz, ct = px, py, pz, 1.0
        for jj in range(ii):
            pj = s + (jj * stride) % c
            qx, qy, qz = _unit3(nrm[pj, 0], nrm[pj, 1], nrm[pj, 2])
            if ux * qx + uy * qy + uz * qz >= ct - tol:
                continue
            # cap with p and q on its boundary
            mx = px + qx; my = py + qy; mz = pz + qz
            ml = math.sqrt(mx * mx + my * my + mz * mz)
            if ml < 1e-12:  # antipodal: any axis perpendicular to p, half-angle pi/2
                if abs(px) < 0.9:
                    mx, my, mz = 0.0, -pz, py
                else:
                    mx, my, mz = pz, 0.0, -px
                ml = math.sqrt(mx * mx + my * my + mz * mz)
            ux = mx / ml; uy = my / ml; uz = mz / ml
            ct = ux * px + uy * py + uz * pz
            for kk in range(jj):
                pk = s + (kk * stride) % c
                rx, ry, rz = _unit3(nrm[pk, 0], nrm[pk, 1], nrm[pk, 2])
                if ux * rx + uy * ry + uz * rz >= ct - tol:
                    continue
                # cap with p, q, r on its boundary: axis normal to the plane through them
                ax_ = qx - px; ay_ = qy - py; az_ = qz - pz
                bx_ = rx - px; by_ = ry - py; bz_ = rz - pz
                nx = ay_ * bz_ - az_ * by_
                ny = az_ * bx_ - ax_ * bz_
                nz = ax_ * by_ - ay_ * bx_
                nl = math.sqrt(nx * nx + ny * ny + nz * nz)
                if nl < 1e-15:
                    continue  # degenerate triple; the final widening keeps the cone valid
                nx /= nl; ny /= nl; nz /= nl
                d = nx * px + ny * py + nz * pz
                if d < 0.0:
                    nx = -nx; ny = -ny; nz = -nz; d = -d
                ux, uy, uz, ct = nx, ny, nz, d
    return ux, uy, uz, ct


@njit(cache=_CACHE)
def _lex_less(V, i, j):
    """V[i] < V[j] lexicographically (x, then y, then z)."""
    for a in range(3):
        if V[i, a] != V[j, a]:
            return V[i, a] < V[j, a]
    return False


CONE_SUPPORT_MAX = 32    # boundary vectors re-solved in canonical order (more: the first solve's axis is kept)
CONE_SUPPORT_COS = 1e-6  # a vector within this of the cap's boundary cosine is a support candidate


@njit(cache=_CACHE)
def _min_cone(nrm, s, e, out):
    """Minimum cone (axis, half-angle) of the unit vectors nrm[s:e], the same whatever their order and
    multiplicity: Welzl's algorithm (:func:`_welzl_cap`) in a fixed scrambled order finds the cap, then the
    vectors on its boundary (within :data:`CONE_SUPPORT_COS`; at most :data:`CONE_SUPPORT_MAX`, duplicates
    dropped) are solved again in lexicographic order — the cap is fixed by its support, so a node of doubled
    or permuted points gets the same axis bit for bit. Exact when the vectors lie in an open hemisphere; in
    every case the half-angle is finally raised to the largest angle from the axis, so the cone always
    contains all the vectors. Writes out[0:3] = axis, out[3] = half-angle [rad]."""
    c = e - s
    # fixed scramble (Welzl's expected linear time): visit (j * stride) mod c with stride coprime to c
    stride = 1
    if c > 2:
        for cand in (7919, 104729, 15485863, 1299709):
            if c % cand != 0:
                a_, b_ = cand % c, c
                while b_:
                    a_, b_ = b_, a_ % b_
                if a_ == 1:
                    stride = cand % c
                    break
    ux, uy, uz, ct = _welzl_cap(nrm, s, stride, c)
    # canonical support: the boundary vectors, sorted, without duplicates, solved again
    sup = np.empty(CONE_SUPPORT_MAX, dtype=np.int64)
    k = 0
    for ii in range(s, e):   # as stored (float32 unit vectors are off by ≤ 1e-7: within the tolerance)
        if ux * nrm[ii, 0] + uy * nrm[ii, 1] + uz * nrm[ii, 2] <= ct + CONE_SUPPORT_COS:
            if k == CONE_SUPPORT_MAX:
                k = -1
                break
            sup[k] = ii
            k += 1
    if k > 1:
        for a in range(1, k):   # insertion sort (k ≤ 32)
            t = sup[a]
            b = a - 1
            while b >= 0 and _lex_less(nrm, t, sup[b]):
                sup[b + 1] = sup[b]
                b -= 1
            sup[b + 1] = t
        W = np.empty((k, 3), dtype=nrm.dtype)
        n = 0
        for a in range(k):
            i = sup[a]
            if n > 0 and nrm[i, 0] == W[n - 1, 0] and nrm[i, 1] == W[n - 1, 1] and nrm[i, 2] == W[n - 1, 2]:
                continue
            W[n, 0] = nrm[i, 0]; W[n, 1] = nrm[i, 1]; W[n, 2] = nrm[i, 2]
            n += 1
        ux, uy, uz, ct = _welzl_cap(W, 0, 1, n)
    # exact widening: half-angle = largest angle from the axis
    th = 0.0
    for ii in range(s, e):   # (atan2 of |a × b| and a · b: the vectors' lengths do not matter)
        a = angle(ux, uy, uz, np.float64(nrm[ii, 0]), np.float64(nrm[ii, 1]), np.float64(nrm[ii, 2]))
        if a > th:
            th = a
    out[0], out[1], out[2], out[3] = _sphere_if_wide(ux, uy, uz, min(th + ANGLE_EPS, math.pi))


@njit(cache=_CACHE, inline="always")
def _sphere_if_wide(ux, uy, uz, th):
    """A cone of half-angle ≥ π/2 culls nothing (Fig. 5's back-face test needs half-angle + δ < π/2) and is no
    disc: stored as the full sphere, axis +Z, so that its bytes do not depend on which of the many caps Welzl's
    order found for normals that fill more than a hemisphere. Returns (axis x, y, z, half-angle [rad])."""
    if th >= 0.5 * math.pi:
        return 0.0, 0.0, 1.0, math.pi
    return ux, uy, uz, th


@njit(cache=_CACHE)
def _merge_cones(a0, a1, a2, ta, b0, b1, b2, tb):
    """Exact minimum cone containing cones (a, ta) and (b, tb) (unit axes, half-angles in rad):
    its axis lies on the great circle through a and b. Returns (axis x, y, z, half-angle)."""
    a = (a0, a1, a2)
    b = (b0, b1, b2)
    if ta >= math.pi or tb >= math.pi:
        return a0, a1, a2, math.pi
    phi = angle(a[0], a[1], a[2], b[0], b[1], b[2])
    if phi + tb <= ta:
        return a0, a1, a2, ta
    if phi + ta <= tb:
        return b0, b1, b2, tb
    th = 0.5 * (phi + ta + tb)
    if th >= math.pi:
        return a0, a1, a2, math.pi
    rot = th - ta  # rotate a towards b by this angle
    # unit vector w orthogonal to a in the plane (a, b)
    dab = a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    wx = b[0] - dab * a[0]; wy = b[1] - dab * a[1]; wz = b[2] - dab * a[2]
    wl = math.sqrt(wx * wx + wy * wy + wz * wz)
    if wl < 1e-12:  # antipodal axes: any perpendicular plane works (both cones are symmetric)
        if abs(a[0]) < 0.9:
            wx, wy, wz = 0.0, -a[2], a[1]
        else:
            wx, wy, wz = a[2], 0.0, -a[0]
        wl = math.sqrt(wx * wx + wy * wy + wz * wz)
    wx /= wl; wy /= wl; wz /= wl
    cr = math.cos(rot); sr = math.sin(rot)
    ux = cr * a[0] + sr * wx; uy = cr * a[1] + sr * wy; uz = cr * a[2] + sr * wz
    ul = math.sqrt(ux * ux + uy * uy + uz * uz)
    ux /= ul; uy /= ul; uz /= ul
    # exact containment with the computed axis (triangle inequality on the sphere)
    t1 = angle(ux, uy, uz, a[0], a[1], a[2]) + ta
    t2 = angle(ux, uy, uz, b[0], b[1], b[2]) + tb
    return ux, uy, uz, min(max(t1, t2) + ANGLE_EPS, math.pi)


# ----------------------------------------------------------------------------- leaves
@njit(cache=_CACHE, parallel=True)
def gather_sorted(points, normals, colors, order):
    """points/normals/colours permuted into Morton order (float32 copies)."""
    n = order.shape[0]
    P = np.empty((n, 3), dtype=np.float32)
    Nn = np.empty((n, 3), dtype=np.float32)
    C = np.empty((n, 3), dtype=np.float32)
    for i in prange(n):
        o = order[i]
        for a in range(3):
            P[i, a] = points[o, a]
            Nn[i, a] = normals[o, a]
            C[i, a] = colors[o, a]
    return P, Nn, C


@njit(cache=_CACHE, parallel=True)
def leaf_attributes(P, Nn, C, lfirst, lcount, cen, rad, col, nsum, m2, mdist, xdist, cone):
    """Per leaf (voxel) k, written into row ``L-1+k`` of the node arrays (Karras ids):
    point-count-weighted means of position (rounded to float32) and colour, the sum of unit
    normals, the colour statistics of pruning (M2 = sum |c - mean|^2, mean and max distance),
    the distance of the farthest point from the float32 mean (into ``rad``; the splat radius is
    applied afterwards) and the exact minimum cone of the normals (axis, half-angle)."""
    L = lfirst.shape[0]
    off = L - 1
    for k_ in prange(L):
        k = off + np.int64(k_)
        s = lfirst[k_]
        c = lcount[k_]
        e = s + c
        for a in range(3):  # accumulate in the output rows (no per-leaf allocation)
            cen[k, a] = 0.0
            col[k, a] = 0.0
            nsum[k, a] = 0.0
        for i in range(s, e):
            for a in range(3):
                cen[k, a] += P[i, a]
                col[k, a] += C[i, a]
                nsum[k, a] += Nn[i, a]
        for a in range(3):
            cen[k, a] = np.float64(np.float32(cen[k, a] / c))
            col[k, a] = col[k, a] / c
        r = 0.0
        q2 = 0.0
        md = 0.0
        xd = 0.0
        for i in range(s, e):
            dx = P[i, 0] - cen[k, 0]; dy = P[i, 1] - cen[k, 1]; dz = P[i, 2] - cen[k, 2]
            d = math.sqrt(dx * dx + dy * dy + dz * dz)
            if d > r:
                r = d
            ex = C[i, 0] - col[k, 0]; ey = C[i, 1] - col[k, 1]; ez = C[i, 2] - col[k, 2]
            e2 = ex * ex + ey * ey + ez * ez
            q2 += e2
            de = math.sqrt(e2)
            md += de
            if de > xd:
                xd = de
        rad[k] = r
        m2[k] = q2
        mdist[k] = md / c
        xdist[k] = xd
        if c == 1:
            cone[k, 0] = Nn[s, 0]; cone[k, 1] = Nn[s, 1]; cone[k, 2] = Nn[s, 2]
            cone[k, 3] = ANGLE_EPS
        else:
            _min_cone(Nn, s, e, cone[k])


@njit(cache=_CACHE, inline="always")
def _top4(b0, b1, b2, b3, d):
    """(b0 ≤ b1 ≤ b2 ≤ b3) the four smallest of them and d, without branches (a min/max chain)."""
    t = max(b0, d)
    b0 = min(b0, d)
    u = max(b1, t)
    b1 = min(b1, t)
    t = max(b2, u)
    b2 = min(b2, u)
    b3 = min(b3, t)
    return b0, b1, b2, b3


@njit(cache=_CACHE, parallel=True)
def leaf_spacing(cen, perm2, window):
    """Approximate distance from each leaf centre to its 4th-nearest other leaf centre: the
    4th smallest distance among the ``window`` previous and next leaves in Morton order (the
    leaves' own order) and in a second Morton order of the leaves shifted by a fixed offset
    (``perm2``; a point at a block boundary of one Z-curve rarely is at one of the other). The
    candidates are a subset of all leaves, so this is an upper bound of the true 4-NN distance.
    Leaves with fewer than 4 distinct neighbours use the farthest found; a lone leaf gets 0.

    The four best of each order are kept in registers by a branchless min/max chain (two independent
    chains, merged at the end: the same four smallest distances as inserting the candidates one by one);
    a candidate that is not one (outside the cloud, or a leaf of the first window met again in the second)
    counts as +inf."""
    L = cen.shape[0]
    cen2 = np.empty_like(cen)
    pos2 = np.empty(L, dtype=np.int64)
    for q in prange(L):  # perm2 is a permutation: no write conflicts
        pos2[perm2[q]] = q
        for a in range(3):
            cen2[q, a] = cen[perm2[q], a]
    out = np.zeros(L)
    inf = np.inf
    for i in prange(L):
        cx = cen[i, 0]; cy = cen[i, 1]; cz = cen[i, 2]
        a0 = inf; a1 = inf; a2 = inf; a3 = inf
        b0 = inf; b1 = inf; b2 = inf; b3 = inf
        q0 = pos2[i]
        j0 = max(i - window, 0)
        j1 = min(i + window, L - 1)
        for j in range(j0, j1 + 1):
            dx = cen[j, 0] - cx; dy = cen[j, 1] - cy; dz = cen[j, 2] - cz
            d = dx * dx + dy * dy + dz * dz
            if j == i:
                d = inf
            a0, a1, a2, a3 = _top4(a0, a1, a2, a3, d)
        # a leaf of the second window that is in the first (|j - i| <= window) was counted there
        k0 = max(q0 - window, 0)
        k1 = min(q0 + window, L - 1)
        for qq in range(k0, k1 + 1):
            dx = cen2[qq, 0] - cx; dy = cen2[qq, 1] - cy; dz = cen2[qq, 2] - cz
            d = dx * dx + dy * dy + dz * dz
            if abs(perm2[qq] - i) <= window:
                d = inf
            b0, b1, b2, b3 = _top4(b0, b1, b2, b3, d)
        a0, a1, a2, a3 = _top4(a0, a1, a2, a3, b0)
        a0, a1, a2, a3 = _top4(a0, a1, a2, a3, b1)
        a0, a1, a2, a3 = _top4(a0, a1, a2, a3, b2)
        a0, a1, a2, a3 = _top4(a0, a1, a2, a3, b3)
        if a3 < inf:
            out[i] = math.sqrt(a3)
        elif a2 < inf:
            out[i] = math.sqrt(a2)
        elif a1 < inf:
            out[i] = math.sqrt(a1)
        elif a0 < inf:
            out[i] = math.sqrt(a0)
    return out


# ----------------------------------------------------------------------------- isolated leaves (16-NN median)
@njit(cache=_CACHE)
def _compact21(x):
    """Inverse of :func:`_spread21`: bits 3i of x → bit i."""
    x = np.uint64(x) & np.uint64(0x1249249249249249)
    x = (x | (x >> np.uint64(2))) & np.uint64(0x10C30C30C30C30C3)
    x = (x | (x >> np.uint64(4))) & np.uint64(0x100F00F00F00F00F)
    x = (x | (x >> np.uint64(8))) & np.uint64(0x1F0000FF0000FF)
    x = (x | (x >> np.uint64(16))) & np.uint64(0x1F00000000FFFF)
    x = (x | (x >> np.uint64(32))) & np.uint64(0x1FFFFF)
    return np.int64(x)


@njit(cache=_CACHE)
def _hash_slot(key, hbits):
    return np.int64((np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(64 - hbits))


@njit(cache=_CACHE)
def _cell_table(codes, shift):
    """Cells of the sorted ``codes`` at ``shift`` (cell key = code >> shift): keys (U,) uint64, run starts
    (U+1,) int64, and an open-addressing hash table (cell key → cell index, -1 empty) with its bit count."""
    L = codes.shape[0]
    sh = np.uint64(shift)
    starts = np.empty(L + 1, dtype=np.int64)
    keys = np.empty(L, dtype=np.uint64)
    U = 0
    prev = np.uint64(0)
    for i in range(L):
        key = codes[i] >> sh
        if i == 0 or key != prev:
            keys[U] = key
            starts[U] = i
            U += 1
            prev = key
    starts[U] = L
    hbits = 4
    while (1 << hbits) < 2 * U:
        hbits += 1
    mask = (1 << hbits) - 1
    table = np.full(1 << hbits, -1, dtype=np.int64)
    for u in range(U):
        s = _hash_slot(keys[u], hbits)
        while table[s] >= 0:
            s = (s + 1) & mask
        table[s] = u
    return keys[:U].copy(), starts[:U + 1].copy(), table, hbits


@njit(cache=_CACHE)
def _hash_find(table, hbits, keys, key):
    mask = (1 << hbits) - 1
    s = _hash_slot(key, hbits)
    while True:
        u = table[s]
        if u < 0:
            return -1
        if keys[u] == key:
            return u
        s = (s + 1) & mask


@njit(cache=_CACHE)
def _cells_per_level(codes, bits):
    """Number of non-empty cells and the most leaves in one cell, (bits + 1,) each, of the sorted ``codes`` at
    each level 0..bits (cells of level l: the codes' top 3 l bits)."""
    n = codes.shape[0]
    cells = np.ones(bits + 1, dtype=np.int64)
    most = np.zeros(bits + 1, dtype=np.int64)
    last = np.zeros(bits + 1, dtype=np.int64)    # first leaf of the current cell at each level
    for i in range(1, n):
        x = codes[i] ^ codes[i - 1]
        if x == 0:
            continue
        hb = 63 - leading_zeros(x)               # highest differing bit: other cells from level bits - hb // 3 on
        for lv in range(max(bits - hb // 3, 0), bits + 1):
            cells[lv] += 1
            most[lv] = max(most[lv], i - last[lv])
            last[lv] = i
    for lv in range(bits + 1):
        most[lv] = max(most[lv], n - last[lv])
    return cells, most


@njit(cache=_CACHE)
def _block_runs(keys, starts, table, hbits, top, u, runs):
    """The leaf runs of the non-empty cells among the 3 × 3 × 3 around cell u into ``runs`` (27, 5): first
    leaf, end, and the cell's offset from u (x, y, z); returns (number of runs, number of leaves)."""
    key = keys[u]
    cx = _compact21(key >> np.uint64(2))
    cy = _compact21(key >> np.uint64(1))
    cz = _compact21(key)
    nr = 0
    nb = 0
    for ox in range(-1, 2):
        x = cx + ox
        if x < 0 or x > top:
            continue
        for oy in range(-1, 2):
            y = cy + oy
            if y < 0 or y > top:
                continue
            for oz in range(-1, 2):
                z = cz + oz
                if z < 0 or z > top:
                    continue
                nk = (_spread21(x) << np.uint64(2)) | (_spread21(y) << np.uint64(1)) | _spread21(z)
                v = _hash_find(table, hbits, keys, nk)
                if v >= 0:
                    runs[nr, 0] = starts[v]
                    runs[nr, 1] = starts[v + 1]
                    runs[nr, 2] = ox
                    runs[nr, 3] = oy
                    runs[nr, 4] = oz
                    nb += starts[v + 1] - starts[v]
                    nr += 1
    return nr, nb


@njit(cache=_CACHE)
def _isolated_chunk(u0, u1, keys, starts, table, hbits, top, h, min_occ, cen, spacing, ratio, k, lo, eps, out, done):
    """Cells u0 … u1 - 1 of :func:`_isolated_level`."""
    need_low = (k + 1) // 2 - 1       # at most this many neighbours below spacing[i] / ratio: not isolated
    sq2 = math.sqrt(2.0)
    runs = np.empty((27, 5), dtype=np.int64)
    cap = 256                           # block buffers, grown when a block holds more leaves
    bx = np.empty(cap); by = np.empty(cap); bz = np.empty(cap); bl = np.empty(cap)
    bj = np.empty(cap, dtype=np.int64)
    roff = np.empty(28, dtype=np.int64)
    td = np.empty(k)
    tj = np.empty(k, dtype=np.int64)
    sv = np.empty(k)
    lowq = np.empty(need_low + 1)
    for u in range(u0, u1):
        if starts[u + 1] - starts[u] < min_occ:
            continue
        todo = False
        for i in range(starts[u], starts[u + 1]):
            if not done[i]:
                todo = True
                break
        if not todo:
            continue
        nr, nb = _block_runs(keys, starts, table, hbits, top, u, runs)
        if nb > cap:
            cap = max(nb, 2 * cap)
            bx = np.empty(cap); by = np.empty(cap); bz = np.empty(cap); bl = np.empty(cap)
            bj = np.empty(cap, dtype=np.int64)
        nb = 0
        rc = 0
        for r in range(nr):
            roff[r] = nb
            if runs[r, 2] == 0 and runs[r, 3] == 0 and runs[r, 4] == 0:
                rc = r
            for j in range(runs[r, 0], runs[r, 1]):
                bx[nb] = cen[j, 0]; by[nb] = cen[j, 1]; bz[nb] = cen[j, 2]
                bl[nb] = ratio * spacing[j]
                bj[nb] = j
                nb += 1
        roff[nr] = nb
        # the (need_low + 1)-th smallest ratio × spacing of the block (inf if it holds fewer leaves): a leaf with
        # spacing <= it has at most need_low leaves of the block, hence of any ball inside it, below spacing /
        # ratio, so it is not isolated as soon as the block proves its k nearest (the original test's outcome)
        nq = 0
        for q in range(nb):
            v_ = bl[q]
            if nq <= need_low:
                t = nq
                nq += 1
            elif v_ < lowq[need_low]:
                t = need_low
            else:
                continue
            while t > 0 and lowq[t - 1] > v_:
                lowq[t] = lowq[t - 1]
                t -= 1
            lowq[t] = v_
        vq = lowq[need_low] if nq > need_low else np.inf
        key = keys[u]
        cx = _compact21(key >> np.uint64(2))
        cy = _compact21(key >> np.uint64(1))
        cz = _compact21(key)
        # block faces (none beyond the grid's outer cells: no leaf lies there)
        fx0 = lo[0] + (cx - 1) * h if cx > 0 else -np.inf
        fx1 = lo[0] + (cx + 2) * h if cx < top else np.inf
        fy0 = lo[1] + (cy - 1) * h if cy > 0 else -np.inf
        fy1 = lo[1] + (cy + 2) * h if cy < top else np.inf
        fz0 = lo[2] + (cz - 1) * h if cz > 0 else -np.inf
        fz1 = lo[2] + (cz + 2) * h if cz < top else np.inf
        for i in range(starts[u], starts[u + 1]):
            if done[i]:
                continue
            px = cen[i, 0]; py = cen[i, 1]; pz = cen[i, 2]
            si = spacing[i]
            mg = min(px - fx0, fx1 - px, py - fy0, fy1 - py, pz - fz0, fz1 - pz) - eps
            if not mg > 0.0:
                continue
            if si <= vq:
                # fast path: count the block's leaves within mg (its own cell first) up to k + 1 (itself included)
                r0 = mg * mg
                n0 = 0
                for rr_ in range(nr):
                    r = rc if rr_ == 0 else (rr_ - 1 if rr_ <= rc else rr_)
                    for q in range(roff[r], roff[r + 1]):
                        dx = bx[q] - px; dy = by[q] - py; dz = bz[q] - pz
                        if dx * dx + dy * dy + dz * dz < r0:
                            n0 += 1
                    if n0 > k:
                        break
                if n0 > k:
                    out[i] = si
                    done[i] = True
                continue
            # counts within mg and within mg / sqrt(2), mg / 2, mg / sqrt(8): the smallest of these balls
            # holding k others is the tightest superset of its k nearest at hand. First only the cells
            # that reach into the ball of mg / sqrt(2) (boxes widened by eps), then, if need be, all.
            r0 = mg * mg
            r1 = 0.5 * r0
            r2 = 0.25 * r0
            r3 = 0.125 * r0
            slw = np.int64(ratio * si < si)   # leaf i itself (distance 0) is in every ball
            rr = -1.0
            n_low = 0
            for phase in range(2):
                n0 = 0; n1 = 0; n2 = 0; n3 = 0
                w0 = 0; w1 = 0; w2 = 0; w3 = 0
                for r in range(nr):
                    if phase == 0:
                        gx = lo[0] + (cx + runs[r, 2]) * h
                        gy = lo[1] + (cy + runs[r, 3]) * h
                        gz = lo[2] + (cz + runs[r, 4]) * h
                        ex = max(gx - eps - px, px - (gx + h + eps), 0.0)
                        ey = max(gy - eps - py, py - (gy + h + eps), 0.0)
                        ez = max(gz - eps - pz, pz - (gz + h + eps), 0.0)
                        if ex * ex + ey * ey + ez * ez >= r1:
                            continue
                    for q in range(roff[r], roff[r + 1]):
                        dx = bx[q] - px; dy = by[q] - py; dz = bz[q] - pz
                        d = dx * dx + dy * dy + dz * dz
                        lw = np.int64(bl[q] < si)
                        c0 = np.int64(d < r0); c1 = np.int64(d < r1); c2 = np.int64(d < r2); c3 = np.int64(d < r3)
                        n0 += c0; n1 += c1; n2 += c2; n3 += c3
                        w0 += c0 * lw; w1 += c1 * lw; w2 += c2 * lw; w3 += c3 * lw
                if n3 - 1 >= k:
                    rr = r3; n_low = w3 - slw
                elif n2 - 1 >= k:
                    rr = r2; n_low = w2 - slw
                elif n1 - 1 >= k:
                    rr = r1; n_low = w1 - slw
                elif phase == 1 and n0 - 1 >= k:
                    rr = r0; n_low = w0 - slw
                if rr > 0.0:
                    break
            if rr < 0.0:
                continue                    # its k nearest may lie beyond the block: next level
            if n_low <= need_low:
                out[i] = si
                done[i] = True
                continue
            # exact: the k nearest (they lie within rr), their spacings' median
            nf = 0
            for q in range(nb):
                j = bj[q]
                if j == i:
                    continue
                dx = bx[q] - px; dy = by[q] - py; dz = bz[q] - pz
                d = dx * dx + dy * dy + dz * dz
                if not d < rr:
                    continue
                if nf < k:
                    t = nf
                    nf += 1
                elif d < td[k - 1]:
                    t = k - 1
                else:
                    continue
                while t > 0 and td[t - 1] > d:
                    td[t] = td[t - 1]
                    tj[t] = tj[t - 1]
                    t -= 1
                td[t] = d
                tj[t] = j
            for t in range(k):
                v_ = spacing[tj[t]]
                w = t
                while w > 0 and sv[w - 1] > v_:
                    sv[w] = sv[w - 1]
                    w -= 1
                sv[w] = v_
            if k % 2 == 1:
                med = sv[k // 2]
            else:
                med = (sv[k // 2 - 1] + sv[k // 2]) / 2.0
            out[i] = med / sq2 if si > ratio * med else si
            done[i] = True


@njit(cache=_CACHE, parallel=True)
def _isolated_level(cen, codes, spacing, ratio, k, level, bits, lo, side, eps, min_occ, out, done):
    """One grid level of :func:`shrink_isolated_leaves`: cells of side ``side / 2^level`` (the Morton prefixes of
    ``codes``); every leaf not ``done`` whose ``k`` nearest other leaves provably lie in the 3 × 3 × 3 cells
    around its own gets its spacing into ``out`` and is ``done``. Only cells of at least ``min_occ`` leaves.

    Per leaf i, the leaves of the block within its distance to the block's faces (``mg``, less the rounding
    bound ``eps``) are all the leaves of the cloud that near, and so are those within mg / sqrt(2), mg / 2,
    mg / sqrt(8). When at least k of them are within the smallest of these, they hold its k nearest; when,
    besides, at most (k + 1) // 2 - 1 of them have ``ratio × spacing < spacing[i]``, so have at
    most that many of its k nearest, the lower middle of their sorted spacings (and the upper) is ≥ a value
    whose ratio × is ≥ spacing[i]: leaf i is not isolated, whatever the median (rounding is monotone). The
    others (the isolated ones, a few more) get the exact k nearest (insertion into a sorted list) and their
    spacings' median, computed as ``numpy.median`` does ((a + b) / 2)."""
    keys, starts, table, hbits = _cell_table(codes, 3 * (bits - level))
    U = keys.shape[0]
    h = side / (2.0 ** level)
    top = (1 << level) - 1
    nchunk = min(U, 256)
    for ch in prange(nchunk):   # one parallel loop over a plain function (parallel loops compile slowly)
        _isolated_chunk((U * ch) // nchunk, (U * (ch + 1)) // nchunk, keys, starts, table, hbits, top, h, min_occ,
                        cen, spacing, ratio, k, lo, eps, out, done)


def shrink_isolated_leaves(cen, codes, spacing, ratio, k, bits, lo, side):
    """:func:`pipeline.expansion.splats.shrink_isolated` (same result) for the leaves of a BSH: (spacing,
    number changed) — a leaf whose ``spacing`` exceeds ``ratio`` × the median spacing of its ``k`` nearest
    other leaves gets that median / sqrt(2). Exact (float64 squared distances) up to the choice among leaves
    tied at the k-th distance and to leaves with the same centre (the k-d tree query may count one of them as
    the leaf itself). ``cen`` (L, 3) float64: the leaf centres in Morton order; ``codes`` (L,) their sorted
    voxel codes at ``bits`` over the cube (``lo``, ``side``); each centre lies in its voxel up to float32
    rounding.

    Instead of a k-d tree (13 s at 3 M leaves on 2 cores), a uniform grid of the codes' prefixes
    (:func:`_isolated_level`): a level of ~8 leaves per non-empty cell first, the leaves it cannot settle
    then a level up (cells twice as large), down to the whole cube if need be; where cells of that level hold
    many leaves (a dense part), finer levels first."""
    spacing = np.asarray(spacing, np.float64)
    L = cen.shape[0]
    k = min(int(k), L - 1)
    if ratio <= 0 or L <= 1:
        return spacing, 0
    codes = np.asarray(codes, np.uint64)
    cen = np.ascontiguousarray(cen, np.float64)
    n_cells, most = _cells_per_level(codes, int(bits))
    base = int(bits)
    while base > 0 and L / n_cells[base] < 8.0:     # ~8 leaves per non-empty cell
        base -= 1
    lo = np.asarray(lo, np.float64)
    # a centre (a float32 value) lies within half a float32 ulp of its voxel
    eps = 2.0 ** -21 * (float(np.max(np.abs(lo))) + side) + side * 2.0 ** -40
    out = np.empty(L)
    done = np.zeros(L, np.bool_)
    # dense parts first, on finer levels (cells of >= DENSE leaves): a leaf costs the leaves of its block
    levels = [(lv, DENSE) for lv in range(int(bits), base, -1) if most[lv] >= DENSE] + \
             [(lv, 0) for lv in range(base, -1, -1)]
    for lv, min_occ in levels:
        _isolated_level(cen, codes, spacing, float(ratio), k, lv, int(bits), lo, float(side), eps, min_occ, out, done)
        if done.all():
            break
    if not done.all():   # at level 0 every leaf is a candidate of every other: cannot happen
        raise RuntimeError("shrink_isolated_leaves: leaves left without their nearest neighbours")
    return out, int(np.count_nonzero(out != spacing))


# ----------------------------------------------------------------------------- range sums (pack)
@njit(cache=_CACHE)
def _prefix_rows(v):
    """(N + 1, k) float64: row 0 zeros, row i + 1 = ``numpy.cumsum(v, axis=0)[i]`` (the same additions, in the
    same order: row 1 is v[0] itself)."""
    n, k = v.shape
    cs = np.empty((n + 1, k))
    for a in range(k):
        cs[0, a] = 0.0
    if n > 0:
        for a in range(k):
            cs[1, a] = v[0, a]
    for i in range(1, n):
        for a in range(k):
            cs[i + 1, a] = cs[i, a] + v[i, a]
    return cs


@njit(cache=_CACHE, parallel=True)
def _range_diff(cs, first, count):
    m = first.shape[0]
    k = cs.shape[1]
    out = np.empty((m, k))
    for j in prange(m):
        lo = first[j]
        hi = lo + count[j]
        for a in range(k):
            out[j, a] = cs[hi, a] - cs[lo, a]
    return out


@njit(cache=_CACHE)
def range_sums(v, first, count):
    """(M, k) Σ of the rows of ``v`` (N, k) float64 over ``[first, first + count)``, as differences of the
    prefix sums (what :func:`pipeline.bsh.builder.node_sums` computed with numpy, bit for bit)."""
    return _range_diff(_prefix_rows(v), first, count)


@njit(cache=_CACHE, parallel=True)
def masked_mean_colour(C, masked, first, count):
    """(M, 3) float32 mean colour of each node's points ``[first, first + count)`` with the ``masked`` points
    counted black: what ``node_sums(np.where(masked[:, None], 0.0, C), …) / max(count, 1)`` gives, bit for
    bit (the same prefix sums and differences in float64)."""
    n = C.shape[0]
    cs = np.empty((n + 1, 3))
    for a in range(3):
        cs[0, a] = 0.0
    for i in range(n):
        for a in range(3):
            v = 0.0 if masked[i] else np.float64(C[i, a])
            cs[i + 1, a] = v if i == 0 else cs[i, a] + v
    m = first.shape[0]
    out = np.empty((m, 3), dtype=np.float32)
    for j in prange(m):
        lo = first[j]
        hi = lo + count[j]
        c = np.float64(max(count[j], 1))
        for a in range(3):
            out[j, a] = np.float32((cs[hi, a] - cs[lo, a]) / c)
    return out


@njit(cache=_CACHE, parallel=True)
def range_counts(flag, first, count):
    """(M,) number of set ``flag`` points in each node's range ``[first, first + count)``."""
    n = flag.shape[0]
    cs = np.empty(n + 1, dtype=np.int64)
    cs[0] = 0
    for i in range(n):
        cs[i + 1] = cs[i] + (1 if flag[i] else 0)
    m = first.shape[0]
    out = np.empty(m, dtype=np.int64)
    for j in prange(m):
        out[j] = cs[first[j] + count[j]] - cs[first[j]]
    return out


@njit(cache=_CACHE)
def _closure_prefix(normals, weight):
    n = weight.shape[0]
    cs = np.empty((n + 1, 4))
    for a in range(4):
        cs[0, a] = 0.0
    acc0 = 0.0; acc1 = 0.0; acc2 = 0.0; acc3 = 0.0
    for i in range(n):
        w = weight[i]
        v1 = np.float64(normals[i, 0]) * w
        v2 = np.float64(normals[i, 1]) * w
        v3 = np.float64(normals[i, 2]) * w
        if i == 0:
            acc0 = w; acc1 = v1; acc2 = v2; acc3 = v3
        else:
            acc0 += w; acc1 += v1; acc2 += v2; acc3 += v3
        cs[i + 1, 0] = acc0; cs[i + 1, 1] = acc1; cs[i + 1, 2] = acc2; cs[i + 1, 3] = acc3
    return cs


@njit(cache=_CACHE, inline="always")
def _closure_at(cs, lo, hi, closed_share):
    """c + (1 − c) · closed_share of the points ``[lo, hi)`` from the prefix sums ``cs`` of (w, w n)."""
    s0 = cs[hi, 0] - cs[lo, 0]
    s1 = cs[hi, 1] - cs[lo, 1]
    s2 = cs[hi, 2] - cs[lo, 2]
    s3 = cs[hi, 3] - cs[lo, 3]
    c = math.sqrt(s1 * s1 + s2 * s2 + s3 * s3) / max(s0, 1e-300)
    c = min(max(c, 0.0), 1.0)
    return c + (1.0 - c) * closed_share


@njit(cache=_CACHE, parallel=True)
def closure_factor(normals, weight, first, count, closed_share):
    """Kernel of :func:`pipeline.bsh.builder.closure_share` (the same arithmetic as its numpy form: prefix
    sums of (w, w n), differences, c = |Σ w n| / max(Σ w, 1e-300) clipped to [0, 1], c + (1 − c) · share)."""
    cs = _closure_prefix(normals, weight)
    m = first.shape[0]
    out = np.empty(m)
    for j in prange(m):
        out[j] = _closure_at(cs, first[j], first[j] + count[j], closed_share)
    return out


@njit(cache=_CACHE, parallel=True)
def splat_area(normals, share, first, count, closed, closed_share):
    """(M,) splat area / π of each node [m²] (what :func:`pipeline.bsh.builder.splat_radii` takes as ``leaf_r2``):
    Σ r² of its voxels' splats (``share``: the prefix sums of each sorted point's share, :func:`point_share`),
    times :func:`closure_factor`'s factor where ``closed`` (bright inner nodes), bit for bit the numpy
    ``area * np.where(closed, closure_factor(normals, np.diff(share), …), 1.0)``, in one parallel pass."""
    n = share.shape[0] - 1
    m = first.shape[0]
    any_closed = False
    for j in range(m):
        if closed[j]:
            any_closed = True
            break
    weight = np.empty(n if any_closed else 0)      # the prefix sums of (w, w n) only when a node needs them
    for i in range(weight.shape[0]):
        weight[i] = share[i + 1] - share[i]
    cs = _closure_prefix(normals[:weight.shape[0]], weight)
    out = np.empty(m)
    for j in prange(m):
        lo = first[j]
        hi = lo + count[j]
        a = share[hi] - share[lo]
        if closed[j]:
            a = a * _closure_at(cs, lo, hi, closed_share)
        out[j] = a
    return out


@njit(cache=_CACHE)
def point_share(lrad, lcount):
    """(N + 1,) [0, cumsum of each point's share of its voxel's splat area]: ``lrad[k]² / lcount[k]`` repeated
    ``lcount[k]`` times, prefix-summed as ``numpy.cumsum`` does."""
    n = 0
    for k in range(lcount.shape[0]):
        n += lcount[k]
    out = np.empty(n + 1)
    out[0] = 0.0
    i = 0
    acc = 0.0
    for k in range(lcount.shape[0]):
        v = lrad[k] * lrad[k] / np.float64(lcount[k])
        for _ in range(lcount[k]):
            acc = v if i == 0 else acc + v
            i += 1
            out[i] = acc
    return out


# ----------------------------------------------------------------------------- bottom-up
@njit(cache=_CACHE, inline="always")
def _bottom_up_node(u, left, right, first, count, cen, rad, col, nsum, m2, md_ub, xd_ub, cone, exact):
    """The attributes of inner node u from its children's (see :func:`bottom_up`)."""
    a = left[u]
    b = right[u]
    na = count[a]
    nb = count[b]
    n = na + nb
    first[u] = first[a]
    count[u] = n
    # colour mean, M2, distance bounds
    dca = 0.0
    dcb = 0.0
    dd = 0.0
    for q in range(3):
        mu = (na * col[a, q] + nb * col[b, q]) / n
        col[u, q] = mu
        nsum[u, q] = nsum[a, q] + nsum[b, q]
        dca += (col[a, q] - mu) ** 2
        dcb += (col[b, q] - mu) ** 2
        dd += (col[a, q] - col[b, q]) ** 2
    m2[u] = m2[a] + m2[b] + dd * na * nb / n
    dca = math.sqrt(dca)
    dcb = math.sqrt(dcb)
    md_ub[u] = (na * (dca + md_ub[a]) + nb * (dcb + md_ub[b])) / n
    xd_ub[u] = max(dca + xd_ub[a], dcb + xd_ub[b])
    # sphere: minimum sphere of the two children's spheres
    dx = cen[b, 0] - cen[a, 0]; dy = cen[b, 1] - cen[a, 1]; dz = cen[b, 2] - cen[a, 2]
    d = math.sqrt(dx * dx + dy * dy + dz * dz)
    ra = rad[a]
    rb = rad[b]
    if d + rb <= ra:
        cx, cy, cz = cen[a, 0], cen[a, 1], cen[a, 2]
    elif d + ra <= rb:
        cx, cy, cz = cen[b, 0], cen[b, 1], cen[b, 2]
    else:
        r = 0.5 * (d + ra + rb)
        f = (r - ra) / d
        cx = cen[a, 0] + f * dx; cy = cen[a, 1] + f * dy; cz = cen[a, 2] + f * dz
    cx = np.float64(np.float32(cx)); cy = np.float64(np.float32(cy)); cz = np.float64(np.float32(cz))
    ex = cx - cen[a, 0]; ey = cy - cen[a, 1]; ez = cz - cen[a, 2]
    r1 = math.sqrt(ex * ex + ey * ey + ez * ez) + ra
    ex = cx - cen[b, 0]; ey = cy - cen[b, 1]; ez = cz - cen[b, 2]
    r2 = math.sqrt(ex * ex + ey * ey + ez * ez) + rb
    cen[u, 0] = cx; cen[u, 1] = cy; cen[u, 2] = cz
    rad[u] = _round_up32(max(r1, r2))
    # normal cone: exact ones were computed in parallel beforehand (exact_cones)
    if not exact[u]:
        mx, my, mz, mt = _merge_cones(cone[a, 0], cone[a, 1], cone[a, 2], cone[a, 3],
                                      cone[b, 0], cone[b, 1], cone[b, 2], cone[b, 3])
        cone[u, 0], cone[u, 1], cone[u, 2], cone[u, 3] = _sphere_if_wide(mx, my, mz, mt)


@njit(cache=_CACHE, parallel=True)
def bottom_up(left, right, rlo, rhi, order_dfs, n_leaves, lfirst, lcount, cen, rad, col, nsum, m2, md_ub, xd_ub,
              cone, exact):
    """Attributes of every inner node (Karras ids), children before parents, into the node arrays whose leaf rows are filled (:func:`leaf_attributes`) and
    whose cones of the inner nodes flagged in ``exact`` are done (:func:`exact_cones`).

    * first/count (returned): the node's range of Morton-sorted points.
    * colour: point-count-weighted mean of the children = mean of the node's points.
    * sphere: the minimum sphere containing both children's spheres (closed form), with the
      centre rounded to float32 first and the radius then recomputed and rounded up, so the
      stored parent contains the stored children exactly.
    * cone: unless exact, the exact minimum cone of the two children's cones.
    * pruning statistics: normal sum, colour M2 (exact, Chan's merge), upper bounds of the mean
      and of the max colour distance to the node's mean (triangle inequality over children).

    Children before parents: the tree is cut into up to ``SUBTREES`` sub-trees (the largest split first); each
    is a contiguous range of the pre-order ``order_dfs``, done backwards by one parallel task; then the nodes
    above them, backwards. Every node's arithmetic is the same whatever the order (bit-identical).
    """
    total = 2 * n_leaves - 1
    m = n_leaves - 1
    first = np.empty(total, dtype=np.int64)
    count = np.empty(total, dtype=np.int64)
    for k in range(n_leaves):
        first[m + k] = lfirst[k]
        count[m + k] = lcount[k]
    if m == 0:
        return first, count
    # frontier of sub-trees: node, its position in order_dfs, its size (nodes); split the largest inner one
    fn = np.empty(SUBTREES + 1, dtype=np.int64)
    fp = np.empty(SUBTREES + 1, dtype=np.int64)
    fs = np.empty(SUBTREES + 1, dtype=np.int64)
    top = np.empty(SUBTREES, dtype=np.int64)      # positions in order_dfs of the split nodes
    ntop = 0
    fn[0] = 0; fp[0] = 0; fs[0] = total
    nf = 1
    while nf < SUBTREES:
        best = -1
        for f in range(nf):
            if fn[f] < m and (best < 0 or fs[f] > fs[best]):
                best = f
        if best < 0 or fs[best] < 4096:
            break
        u = fn[best]
        pu = fp[best]
        top[ntop] = pu
        ntop += 1
        a = left[u]
        b = right[u]
        sa = 2 * (rhi[a] - rlo[a] + 1) - 1 if a < m else 1
        sb = 2 * (rhi[b] - rlo[b] + 1) - 1 if b < m else 1
        fn[best] = a; fp[best] = pu + 1; fs[best] = sa
        fn[nf] = b; fp[nf] = pu + 1 + sa; fs[nf] = sb
        nf += 1
    for f in prange(nf):
        for t in range(fp[f] + fs[f] - 1, fp[f] - 1, -1):
            u = order_dfs[t]
            if u < m:
                _bottom_up_node(u, left, right, first, count, cen, rad, col, nsum, m2, md_ub, xd_ub, cone, exact)
    # the split nodes: each is an ancestor of the later ones in pre-order, so backwards by position
    tp = np.sort(top[:ntop])
    for t in range(ntop - 1, -1, -1):
        _bottom_up_node(order_dfs[tp[t]], left, right, first, count, cen, rad, col, nsum, m2, md_ub, xd_ub, cone,
                        exact)
    return first, count


@njit(cache=_CACHE, parallel=True)
def exact_cones(left, right, rlo, rhi, lfirst, lcount, Nn, exact_cone_max, cone):
    """Exact minimum cones (Welzl) of the point normals of every inner node whose children are
    both leaves or which spans at most ``exact_cone_max`` leaves (voxels: a count that duplicated points do not
    change), in parallel; written into
    ``cone`` (Karras ids). Returns the flag array of the nodes done."""
    m = left.shape[0]
    exact = np.zeros(m, dtype=np.uint8)
    for u in prange(m):
        s = lfirst[rlo[u]]
        e = lfirst[rhi[u]] + lcount[rhi[u]]
        if (left[u] >= m and right[u] >= m) or rhi[u] - rlo[u] + 1 <= exact_cone_max:
            exact[u] = 1
            _min_cone(Nn, s, e, cone[u])
    return exact


# ----------------------------------------------------------------------------- pruning + DFS
@njit(cache=_CACHE, inline="always")
def _prunable(u, m, left, right, count, first, col, nsum, m2, md_ub, xd_ub, C, tc, tn, use_max):
    """§5.1 test for an inner node u: mean_p n_p . n_u > tn (n_u = normalised sum of the unit
    normals, so the mean dot is |sum|/count exactly) and the colour statistic < tc, where the
    statistic is the mean (paper) or max distance of the points' colours to the node's mean.
    Cheap bounds decide most nodes; the exact statistic is computed over the points otherwise."""
    n = count[u]
    sl = math.sqrt(nsum[u, 0] ** 2 + nsum[u, 1] ** 2 + nsum[u, 2] ** 2)
    if not (sl / n > tn):
        return False
    if not (tc > 0.0):
        return False
    rms = math.sqrt(max(m2[u], 0.0) / n)
    a = left[u]
    b = right[u]
    da = math.sqrt((col[a, 0] - col[u, 0]) ** 2 + (col[a, 1] - col[u, 1]) ** 2 + (col[a, 2] - col[u, 2]) ** 2)
    db = math.sqrt((col[b, 0] - col[u, 0]) ** 2 + (col[b, 1] - col[u, 1]) ** 2 + (col[b, 2] - col[u, 2]) ** 2)
    if use_max:
        lb = max(max(da, db), rms)
        ub = xd_ub[u]
    else:
        lb = (count[a] * da + count[b] * db) / n
        ub = min(md_ub[u], rms)
    if ub < tc * (1.0 - 1e-12):
        return True
    if lb >= tc:
        return False
    s = first[u]
    acc = 0.0
    for i in range(s, s + n):
        d = math.sqrt((C[i, 0] - col[u, 0]) ** 2 + (C[i, 1] - col[u, 1]) ** 2 + (C[i, 2] - col[u, 2]) ** 2)
        if use_max:
            if d > acc:
                acc = d
        else:
            acc += d
    if not use_max:
        acc /= n
    return acc < tc


@njit(cache=_CACHE)
def linearise(left, right, n_leaves, count, first, col, nsum, m2, md_ub, xd_ub, C,
              prune, tc, tn, use_max):
    """Depth-first (pre-order, left first) linearisation of the tree, turning each top-most
    prunable inner node into a leaf (cluster). Returns, per output node i: Karras id, right child
    (output index, -1 for a leaf), skip (index after the sub-tree), cluster flag, depth."""
    total = 2 * n_leaves - 1
    m = n_leaves - 1
    ids = np.empty(total, dtype=np.int64)
    rgt = np.full(total, -1, dtype=np.int64)
    clus = np.zeros(total, dtype=np.uint8)
    depth = np.zeros(total, dtype=np.int32)
    stack = np.empty(STACK, dtype=np.int64)
    sdep = np.empty(STACK, dtype=np.int32)
    spar = np.empty(STACK, dtype=np.int64)
    sright = np.empty(STACK, dtype=np.uint8)
    stack[0] = 0
    sdep[0] = 0
    spar[0] = -1
    sright[0] = 0
    sp = 1
    k = 0
    while sp > 0:
        sp -= 1
        u = stack[sp]
        ids[k] = u
        depth[k] = sdep[sp]
        p = spar[sp]
        if p >= 0 and sright[sp] == 1:
            rgt[p] = k
        inner = u < m
        if inner and prune and _prunable(u, m, left, right, count, first, col, nsum, m2, md_ub, xd_ub,
                                         C, tc, tn, use_max):
            clus[k] = 1
            inner = False
        if inner:
            if sp + 2 > STACK:
                raise ValueError("BSH deeper than the depth-first stack")
            stack[sp] = right[u]; sdep[sp] = depth[k] + 1; spar[sp] = k; sright[sp] = 1
            stack[sp + 1] = left[u]; sdep[sp + 1] = depth[k] + 1; spar[sp + 1] = k; sright[sp + 1] = 0
            sp += 2
        k += 1
    M = k
    ids = ids[:M]
    rgt = rgt[:M]
    clus = clus[:M]
    depth = depth[:M]
    # skip = index after the sub-tree: sizes bottom-up over the reversed pre-order
    size = np.ones(M, dtype=np.int64)
    for i in range(M - 1, -1, -1):
        if rgt[i] >= 0:
            size[i] = 1 + size[i + 1] + size[rgt[i]]
    skip = np.arange(M).astype(np.int64) + size
    return ids, rgt, skip, clus, depth


@njit(cache=_CACHE, parallel=True)
def assemble(ids, rgt, skip, cen, rad, col, nsum, first, count, cone, slack, words, fwords):
    """Gather the linearised nodes' attributes and fill the 40-byte records: ``words`` (M,10)
    uint32 and ``fwords`` the same memory seen as float32. Returns the decoded arrays."""
    M = ids.shape[0]
    dec = np.empty((M, 3), dtype=np.float32)
    ang = np.empty(M, dtype=np.float32)
    center = np.empty((M, 3), dtype=np.float32)
    radius = np.empty(M, dtype=np.float32)
    color = np.empty((M, 3), dtype=np.float32)
    normal = np.empty((M, 3), dtype=np.float32)
    child = np.full((M, 2), -1, dtype=np.int32)
    nfirst = np.empty(M, dtype=np.int64)
    ncount = np.empty(M, dtype=np.int64)
    for i in prange(M):
        u = ids[i]
        for a in range(3):
            center[i, a] = np.float32(cen[u, a])
            color[i, a] = np.float32(col[u, a])
        radius[i] = np.float32(rad[u])
        nl = math.sqrt(nsum[u, 0] ** 2 + nsum[u, 1] ** 2 + nsum[u, 2] ** 2)
        for a in range(3):
            normal[i, a] = np.float32(nsum[u, a] / nl) if nl > 1e-12 else np.float32(0.0)
        nfirst[i] = first[u]
        ncount[i] = count[u]
        if rgt[i] >= 0:
            child[i, 0] = i + 1
            child[i, 1] = rgt[i]
            words[i, 0] = np.uint32(rgt[i])
        else:
            words[i, 0] = np.uint32(0xFFFFFFFF)
        words[i, 1] = np.uint32(skip[i])
        for a in range(3):
            fwords[i, 2 + a] = center[i, a]
            fwords[i, 5 + a] = color[i, a]
        fwords[i, 8] = radius[i]
        words[i, 9], dec[i, 0], dec[i, 1], dec[i, 2], ang[i] = pack_cone(
            cone[u, 0], cone[u, 1], cone[u, 2], cone[u, 3], slack)
    return center, radius, color, normal, child, nfirst, ncount, dec, ang
