"""The BSH node format of ``bsh.npz`` (DESIGN contract ``pcrelight.bsh/1``) and the shader buffer bindings.

One place for: the 40-byte node record (:data:`NODE_DTYPE`, std430 ``struct Node`` of
``gather/pbgi_common.glsl``), its RGBA8 normal cone (pack: :func:`pipeline.bsh.cones.pack_cones`, unpack:
:func:`decode_cones`, the GLSL ``pbgi_cone_decode``), and the SSBO binding numbers of the PBGI
programs (:data:`GATHER_BINDINGS`, :data:`CUT_BINDINGS`). The GLSL side never spells a binding: the
loaders inject :func:`glsl_defines` (``#define PBGI_BIND_<NAME> <n>``) and the shaders use the names.

Node record (little-endian, 40 bytes): ``right`` uint32 (index of the right child, :data:`LEAF` for
a leaf; the left child is the next record), ``skip`` uint32 (index after the sub-tree), ``center``
3×float32 [m], ``color`` 3×float32 (linear RGB radiance), ``radius`` float32 [m], ``cone`` uint32
(RGBA8, R in bits 0–7: axis = normalise(RGB/255·2−1), half-angle = A/255·π [rad], A = 255 = all
directions).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

NODE_BYTES = 40
NODE_DTYPE = np.dtype({"names": ["right", "skip", "center", "color", "radius", "cone"],
                       "formats": ["<u4", "<u4", ("<f4", (3,)), ("<f4", (3,)), "<f4", "<u4"],
                       "offsets": [0, 4, 8, 20, 32, 36], "itemsize": NODE_BYTES})
LEAF = 0xFFFFFFFF
CONE_PACK_SLACK = 1e-6  # [rad] added before rounding the packed half-angle up (float32 decode error)
# the packed cone of all directions (axis +z, half-angle π: A = 255), what pack_cones([[0, 0, 1]], [π]) gives
# (tests/test_bsh_format.py): a joining root's cone without loading build-bsh's numba kernels (~0.5 CPU s a relight)
ALL_DIRECTIONS_CONE = 128 | 128 << 8 | 255 << 16 | 255 << 24
# bsh.npz members that build-bsh does not write: the node records hold them (:func:`derived_arrays`), and
# io.read_npz puts them back, the same bytes as build_bsh returns (issue 23 item 5: a 3 M-point textured
# cloud's file 458 → ~300 MB, its write and read that much shorter)
# float32 round-up factor: float32(x * UP32) >= x for every x >= 0 that float32 can hold
UP32 = 1.0 + 2.0 ** -22

DERIVED_KEYS = ("center", "color", "radius", "child", "cone_axis", "cone_half_angle", "depth", "first")

# SSBO bindings of the walk and Eq. 9 gather programs (gather/walk.comp.glsl, gather/eq9.comp.glsl)
GATHER_BINDINGS = {"NODES": 0, "MICROBUFFER": 1, "TEXELS": 2, "RECV_A": 3, "RECV_B": 4, "START_OFF": 5,
                   "START_NODE": 6, "STATE": 7, "RECV_C": 8, "RECV_D": 9, "OUT": 10, "PENDING": 11, "SPLAT": 12, "EMIT": 13,
                   "LOBE": 14, "VIEW_DIRS": 15, "OBJ_DIRS": 16,
                   "ISTATE": 17, "IMP": 18,   # importance.comp.glsl's progress and per-cluster importance
                   "RECV_E": 19}              # eq9.comp.glsl: the receivers' geometric normals
# SSBO bindings of the mipmapped/hybrid cut program (gather/cut.geom.glsl)
CUT_BINDINGS = {"NODES": 0, "MIP_CONE": 3, "MIP_SPHERE": 4, "MIP_COUNT": 5}
# image units of the envmap gatherer's prefilter and split-sum table programs (gather/envmap.{prefilter,lut}.comp.glsl)
IMAGE_BINDINGS = {"IMAGE_OUT": 0}


def glsl_defines(bindings: dict[str, int]) -> dict[str, int]:
    """``{"PBGI_BIND_<NAME>": n}`` for :func:`pipeline.gl.make_compute` / ``make_program`` ``defines``."""
    return {f"PBGI_BIND_{k}": int(v) for k, v in bindings.items()}


def decode_cones(packed: np.ndarray, dtype: type = np.float64) -> tuple[np.ndarray, np.ndarray]:
    """Unpack RGBA8 cones as ``pbgi_cone_decode`` does: (axis (M,3), half-angle (M,) [rad]) in ``dtype``
    (float32: the GPU's arithmetic step for step; a zero RGB axis decodes to +z)."""
    f = np.dtype(dtype).type
    p = np.asarray(packed, np.uint32).reshape(-1)
    c = np.stack([(p >> np.uint32(s)) & np.uint32(255) for s in (0, 8, 16, 24)], -1).astype(f) / f(255)
    a = c[:, :3] * f(2) - f(1)
    ln = np.sqrt((a * a).sum(-1, dtype=f)).astype(f)
    axis = np.where((ln > 0)[:, None], a / np.where(ln > 0, ln, f(1))[:, None], np.array([0, 0, 1], f)).astype(f)
    half = np.where((p >> np.uint32(24)) == 255, f(np.pi), c[:, 3] * f(np.pi)).astype(f)
    return axis, half


def decoded_cones(packed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(axis (M,3) float32, half-angle (M,) float32 [rad]) of RGBA8 cones as build-bsh stores them beside the
    nodes (``cone_axis``, ``cone_half_angle``): the axis normalised in float64 then rounded, the half-angle
    A/255·π rounded *up* to float32 (conservative; :func:`decode_cones` rounds to nearest as the GPU does).
    The arithmetic of ``cones.pack_cone``'s decode step for step (bit-identical); the per-byte values come
    from 256-entry tables."""
    b = np.ascontiguousarray(np.asarray(packed).reshape(-1), dtype="<u4").view(np.uint8).reshape(-1, 4)
    unit = np.arange(256) / 255.0 * 2.0 - 1.0             # a colour byte r → r / 255 · 2 − 1 (float64)
    d = [unit[b[:, a]] for a in range(3)]
    dl = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    axis = np.empty((b.shape[0], 3), np.float32)
    for a in range(3):
        axis[:, a] = d[a] / dl
    th = np.arange(256) / 255.0 * np.pi                     # the alpha byte A → A / 255 · π, rounded up
    up = th.astype(np.float32)
    low = up.astype(np.float64) < th
    up[low] = (th[low] * UP32).astype(np.float32)
    return axis, up[b[:, 3]]


def node_depths(right: np.ndarray) -> np.ndarray:
    """(M,) int32 depth (root 0) of every node of a depth-first node array, from its ``right`` words (the
    left child of an inner node i is i + 1), level by level."""
    r = np.asarray(right, np.uint32).reshape(-1)
    inner = r != np.uint32(LEAF)
    depth = np.zeros(r.size, np.int32)
    cur = np.zeros(min(r.size, 1), np.int64)
    level = 0
    while cur.size:
        depth[cur] = level
        c = cur[inner[cur]]
        cur = np.concatenate([c + 1, r[c].astype(np.int64)])
        level += 1
    return depth


def check_tree(raw: np.ndarray, where: str = "bsh.npz") -> None:
    """InputError (naming ``where``) unless the (M,) node records are a depth-first tree: node i's sub-tree is
    ``[i, skip[i])``, a leaf's is ``[i, i + 1)``, an inner node's is itself, its left child's ``[i + 1, r)`` and
    its right child's ``[r, skip[i])`` with ``r = right[i] = skip[i + 1]``."""
    m = raw.size
    i = np.arange(m, dtype=np.int64)
    skip = raw["skip"].astype(np.int64)
    r = raw["right"].astype(np.int64)
    leaf = r == LEAF
    ok = (skip > i) & (skip <= m) & (~leaf | (skip == i + 1))
    if ok.all() and (~leaf).any():
        j = np.flatnonzero(~leaf)
        ok_inner = (j + 1 < m) & (r[j] > j + 1) & (r[j] < skip[j])
        ok = ok_inner.all() and bool(np.all(skip[j + 1] == r[j]) and np.all(skip[r[j]] == skip[j]))
    if not np.all(ok) or (m and skip[0] != m):
        raise InputError(where, "the node records are not a depth-first tree (right, skip)")


def point_ranges(right: np.ndarray, skip: np.ndarray, count: np.ndarray, where: str = "bsh.npz") -> np.ndarray:
    """(M,) int64 ``first`` of every node (its points are ``order[first:first + count]``): the leaves' ranges
    follow one another in depth-first order, so a node's points start after those of the leaves before it
    (an exclusive prefix sum of the leaves' counts). InputError (naming ``where``) unless every node's count is
    that of the leaves of its sub-tree ``[i, skip[i])``."""
    r = np.asarray(right, np.uint32).reshape(-1)
    cnt = np.asarray(count, np.int64).reshape(-1)
    pre = np.zeros(r.size + 1, np.int64)
    np.cumsum(np.where(r == np.uint32(LEAF), cnt, 0), out=pre[1:])
    if cnt.size != r.size or np.any(pre[np.asarray(skip, np.int64)] - pre[:-1] != cnt) or np.any(cnt < 0):
        raise InputError(where, "'count' is not the sum of the leaves' counts of each node's sub-tree")
    return pre[:-1]


def range_slots(first: np.ndarray, count: np.ndarray) -> np.ndarray:
    """(Σ count,) int64: the slots ``first[j] … first[j] + count[j] − 1`` of the given nodes' point ranges, node after
    node (index ``order`` with it for the points themselves)."""
    first = np.asarray(first, np.int64).reshape(-1)
    count = np.asarray(count, np.int64).reshape(-1)
    starts = np.cumsum(count) - count                    # each node's first place in the result
    return np.arange(int(count.sum()), dtype=np.int64) + np.repeat(first - starts, count)


def derived_arrays(nodes: np.ndarray, count: np.ndarray, where: str = "bsh.npz") -> dict[str, np.ndarray]:
    """The members of bsh.npz named in :data:`DERIVED_KEYS`, from its (M,) :data:`NODE_DTYPE` node records
    (checked by :func:`check_tree`) and its ``count``: ``center``, ``color`` (M,3) and ``radius`` (M,) float32 (the
    records' own values), ``child`` (M,2) int32 ((i+1, right) for inner nodes, (-1, -1) for leaves), the stored
    decoded cone (:func:`decoded_cones`), ``depth`` (:func:`node_depths`) and ``first`` (:func:`point_ranges`)."""
    a = np.ascontiguousarray(nodes).reshape(-1)
    raw = a.view(NODE_DTYPE) if a.dtype.itemsize == NODE_BYTES else as_nodes(a)
    check_tree(raw, where)
    r = raw["right"]
    inner = r != np.uint32(LEAF)
    child = np.full((raw.size, 2), -1, np.int32)
    child[inner, 0] = np.flatnonzero(inner) + 1
    child[inner, 1] = r[inner]
    axis, half = decoded_cones(raw["cone"])
    return {"center": np.ascontiguousarray(raw["center"]), "color": np.ascontiguousarray(raw["color"]),
            "radius": np.ascontiguousarray(raw["radius"]), "child": child, "cone_axis": axis,
            "cone_half_angle": half, "depth": node_depths(r), "first": point_ranges(r, raw["skip"], count, where)}


def with_derived(arrays: dict[str, np.ndarray], where: str = "bsh.npz",
                 only: frozenset[str] | None = None) -> dict[str, np.ndarray]:
    """``arrays`` (a bsh.npz read, ``nodes`` of 40-byte records) with the absent :data:`DERIVED_KEYS` (``only``: of
    those in it) computed from its ``nodes`` and ``count`` (InputError naming ``where`` if they are not a tree)."""
    missing = [k for k in DERIVED_KEYS if k not in arrays and (only is None or k in only)]
    if missing:
        d = derived_arrays(arrays["nodes"], arrays["count"], where)
        arrays.update({k: d[k] for k in missing})
    return arrays


def cone_trig_table() -> np.ndarray:
    """(256, 2) float32: (cos, sin) of the node cone half-angle A/255·π for every alpha byte A."""
    a = np.arange(256) / 255.0 * np.pi
    return np.stack([np.cos(a), np.sin(a)], 1).astype(np.float32)


def as_nodes(nodes: np.ndarray) -> np.ndarray:
    """View any 40-byte record array (or raw bytes) as :data:`NODE_DTYPE` records."""
    a = np.ascontiguousarray(nodes)
    return a if a.dtype == NODE_DTYPE else np.frombuffer(a.tobytes(), dtype=NODE_DTYPE)


def nodes_from_bsh(bsh: dict[str, np.ndarray], where: str = "bsh.npz") -> np.ndarray:
    """The (M,) :data:`NODE_DTYPE` node array of a bsh.npz dict, checked (InputError naming ``where``)."""
    nodes = bsh["nodes"]
    if nodes.dtype.itemsize != NODE_BYTES:
        raise InputError(where, f"'nodes' records are {nodes.dtype.itemsize} bytes, expected {NODE_BYTES}")
    raw = np.frombuffer(np.ascontiguousarray(nodes).tobytes(), dtype=NODE_DTYPE)
    if raw.size == 0:
        raise InputError(where, "the BSH has no nodes")
    if not (np.all(np.isfinite(raw["center"])) and np.all(np.isfinite(raw["color"])) and np.all(np.isfinite(raw["radius"]))):
        raise InputError(where, "non-finite node centre, colour or radius")
    if raw["skip"][0] != raw.size:
        raise InputError(where, f"root skip is {raw['skip'][0]}, expected M = {raw.size}")
    return raw
