"""The RGBA8 normal-cone packer of the 40-byte node (:func:`pack_cones`; the node format and the unpacker:
:mod:`pipeline.bsh.format`) and the angle kernel it shares with the tree builder: numba kernels, float64
arithmetic, angles in radians."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .format import CONE_PACK_SLACK, UP32

# numba's on-disk cache (__pycache__, git-ignored) spares the compile on later runs
_CACHE = True


@njit(cache=_CACHE)
def angle(ax, ay, az, bx, by, bz):
    """Angle between unit vectors, accurate near 0 and pi (atan2 of |a x b| and a.b)."""
    cx = ay * bz - az * by
    cy = az * bx - ax * bz
    cz = ax * by - ay * bx
    return math.atan2(math.sqrt(cx * cx + cy * cy + cz * cz), ax * bx + ay * by + az * bz)



@njit(cache=_CACHE)
def pack_cone(a0, a1, a2, half, slack):
    """One cone → (RGBA8 word, decoded float32 axis x, y, z, decoded float32 half-angle rounded
    up). See :func:`pack_cones`."""
    r0 = min(max(int(np.rint((a0 + 1.0) * 0.5 * 255.0)), 0), 255)
    r1 = min(max(int(np.rint((a1 + 1.0) * 0.5 * 255.0)), 0), 255)
    r2 = min(max(int(np.rint((a2 + 1.0) * 0.5 * 255.0)), 0), 255)
    d0 = r0 / 255.0 * 2.0 - 1.0
    d1 = r1 / 255.0 * 2.0 - 1.0
    d2 = r2 / 255.0 * 2.0 - 1.0
    dl = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    e0 = np.float32(d0 / dl)
    e1 = np.float32(d1 / dl)
    e2 = np.float32(d2 / dl)
    delta = angle(a0, a1, a2, np.float64(e0), np.float64(e1), np.float64(e2))
    if half >= math.pi:
        A = 255
    else:
        A = int(math.ceil((half + delta + slack) / math.pi * 255.0))
        A = min(max(A, 0), 255)
    word = np.uint32(r0 | (r1 << 8) | (r2 << 16) | (A << 24))
    th = A / 255.0 * math.pi
    t32 = np.float32(th)
    if np.float64(t32) < th:
        t32 = np.float32(th * UP32)
    return word, e0, e1, e2, t32


@njit(cache=_CACHE)
def pack_cones_nb(axis, half, slack):
    """See :func:`pack_cones` (this is its kernel)."""
    M = axis.shape[0]
    packed = np.empty(M, dtype=np.uint32)
    dec = np.empty((M, 3), dtype=np.float32)
    ang = np.empty(M, dtype=np.float32)
    for i in range(M):
        packed[i], dec[i, 0], dec[i, 1], dec[i, 2], ang[i] = pack_cone(axis[i, 0], axis[i, 1], axis[i, 2],
                                                                       half[i], slack)
    return packed, dec, ang


def pack_cones(axis: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pack cones (unit axis (M,3), half-angle (M,) rad, float64) into RGBA8 uint32 (R = byte 0).

    R,G,B = round((axis+1)/2·255); the decoded axis â = normalise(RGB/255·2−1) is off by
    δ = angle(axis, â); A = ceil((half + δ + slack)/π·255) clipped to 255 (255 = all
    directions), so the decoded cone (â, A/255·π) contains the true one. Returns (packed uint32,
    decoded axis float32, decoded half-angle float32 rounded up)."""
    axis = np.ascontiguousarray(np.asarray(axis, np.float64).reshape(-1, 3))
    half = np.ascontiguousarray(np.asarray(half, np.float64).reshape(-1))
    return pack_cones_nb(axis, half, CONE_PACK_SLACK)
