"""Test-only BSH builders: a median-split BSH with one leaf per point (exact spheres and cones), so the
gather tests need neither build-bsh nor a cloud file. build-bsh is the real builder."""

from __future__ import annotations

import numpy as np

from pipeline.bsh.format import LEAF, NODE_DTYPE, decode_cones
from pipeline.bsh.cones import pack_cones


def merge_spheres(c1, r1, c2, r2):
    d = float(np.linalg.norm(c2 - c1))
    if d + r2 <= r1:
        return c1, r1
    if d + r1 <= r2:
        return c2, r2
    r = 0.5 * (d + r1 + r2)
    c = c1 + (c2 - c1) / d * (r - r1)
    return c, r * (1 + 1e-6)


def merge_cones(a1, h1, a2, h2):
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
    """A small, valid binary BSH (:data:`pipeline.bsh.format.NODE_DTYPE`, depth-first, skip links) by median splits along
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
        c, r = merge_spheres(c1, r1, c2, r2)
        a, hh = merge_cones(*cones[i + 1], *cones[right])
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
    nodes["cone"] = pack_cones(axes, halves)[0]
    return nodes


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
    ax, half = decode_cones(nodes["cone"], np.float32)
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
