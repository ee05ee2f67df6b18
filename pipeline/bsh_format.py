"""The BSH node format of ``bsh.npz`` (DESIGN contract ``pcrelight.bsh/1``) and the shader buffer bindings.

One place for: the 40-byte node record (:data:`NODE_DTYPE`, std430 ``struct Node`` of
``gather/pbgi_common.glsl``), its RGBA8 normal cone (pack: :func:`pack_cones`, unpack:
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

from .errors import InputError

NODE_BYTES = 40
NODE_DTYPE = np.dtype({"names": ["right", "skip", "center", "color", "radius", "cone"],
                       "formats": ["<u4", "<u4", ("<f4", (3,)), ("<f4", (3,)), "<f4", "<u4"],
                       "offsets": [0, 4, 8, 20, 32, 36], "itemsize": NODE_BYTES})
LEAF = 0xFFFFFFFF
CONE_PACK_SLACK = 1e-6  # [rad] added before rounding the packed half-angle up (float32 decode error)

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


def pack_cones(axis: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pack cones (unit axis (M,3), half-angle (M,) rad, float64) into RGBA8 uint32 (R = byte 0).

    R,G,B = round((axis+1)/2·255); the decoded axis â = normalise(RGB/255·2−1) is off by
    δ = angle(axis, â); A = ceil((half + δ + slack)/π·255) clipped to 255 (255 = all
    directions), so the decoded cone (â, A/255·π) contains the true one. Returns (packed uint32,
    decoded axis float32, decoded half-angle float32 rounded up)."""
    from . import bsh_core

    axis = np.ascontiguousarray(np.asarray(axis, np.float64).reshape(-1, 3))
    half = np.ascontiguousarray(np.asarray(half, np.float64).reshape(-1))
    return bsh_core.pack_cones_nb(axis, half, CONE_PACK_SLACK)


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
