"""The receiving object in its own micro-buffers (Christensen 2008, "Point-based approximate colour
bleeding"): surfels of the object's surface, their BSH, and the node array every gatherer walks.

The paper's PBGI (000 §5) lights the object by the room alone, as if the object were not there: no
self-shadow, no light between its parts. Here the object's surface is sampled into surfels (area-
uniform, blue-noise: :func:`sample_surfels`), their hierarchy is built by build-bsh's core
(:func:`object_bsh`), and :func:`merge_nodes` appends it to the room's nodes under a new root, so the
walk rasterises room and object together, depth-tested:

* pass 0 — the surfels are black: the object occludes the room for itself (its own shadows);
* bounce b = 1, 2 — each surfel is a receiver first (the classic walk, its normal as the view
  direction), its outgoing radiance from the previous pass recolours the object's nodes
  (:func:`node_colours`), then the pixels are gathered: one (two) bounce(s) of light between the object's
  parts.

Near field (``walk.comp.glsl``, nodes from ``object_first`` on): an object leaf whose centre lies less
than ``object_near`` × its splat radius above the receiver's tangent plane is not splatted (its own
surfel and its neighbours on a flat or convex surface: no false self-shadow); an object node seen from
behind is culled as the room's are (a closed surface is seen from outside); open meshes get two-sided
surfels (one per side).

Units: metres, linear RGB radiance; conventions as the rest of relight.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..bsh_format import LEAF, NODE_DTYPE, pack_cones
from ..runtime import get_logger

log = get_logger("relight")

MIN_SURFELS, MAX_SURFELS = 2000, 100_000
SPACING_PIXELS = 1.5   # auto count: surfel spacing = this × the pixel footprint at the object's distance


def auto_count(area: float, footprint: float) -> int:
    """Surfels for total area ``area`` [m²] at pixel footprint ``footprint`` [m]: spacing
    SPACING_PIXELS × footprint, clamped to [MIN_SURFELS, MAX_SURFELS]."""
    s = max(SPACING_PIXELS * footprint, 1e-30)
    return int(np.clip(area / (s * s), MIN_SURFELS, MAX_SURFELS))


def _texture(img: np.ndarray | None, uv: np.ndarray) -> np.ndarray | None:
    """Bilinear lookup of an (H, W, C) image at OpenGL uv (v = 0 at the bottom row), repeat wrap."""
    if img is None:
        return None
    H, W = img.shape[:2]
    x = (uv[:, 0] % 1.0) * W - 0.5
    y = (1.0 - (uv[:, 1] % 1.0)) * H - 0.5
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    def at(yy, xx):
        return img[yy % H, xx % W].astype(np.float64)
    return ((1 - fy) * ((1 - fx) * at(y0, x0) + fx * at(y0, x0 + 1)) + fy * ((1 - fx) * at(y0 + 1, x0) + fx * at(y0 + 1, x0 + 1)))


def parts_area(parts: list[dict[str, Any]]) -> float:
    """Total triangle area of the (world-space) parts [m²]."""
    tot = 0.0
    for p in parts:
        v = p["positions"].astype(np.float64)
        f = np.asarray(p["faces"], np.int64).reshape(-1, 3)
        tot += 0.5 * float(np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum())
    return tot


def sample_surfels(parts: list[dict[str, Any]], count: int, seed: int = 0) -> dict[str, np.ndarray]:
    """About ``count`` surfels on the parts' surfaces, area-uniform with a minimum distance (trimesh's
    ``sample_surface_even``). Returns float32 arrays: ``position`` (N,3) [m], ``normal`` (N,3) (the
    interpolated vertex normal, else the face's), ``base_color`` (N,3), ``metallic`` (N,), ``roughness``
    (N,) (factor × texture × vertex colour as the G-buffer), and ``area`` (N,) [m²] (each part's area
    over its surfels). Parts whose mesh is not closed get a second, flipped surfel at each sample."""
    import trimesh

    areas = []
    meshes = []
    for p in parts:
        m = trimesh.Trimesh(np.asarray(p["positions"], np.float64), np.asarray(p["faces"], np.int64).reshape(-1, 3),
                            process=False)
        meshes.append(m)
        areas.append(float(m.area))
    total = sum(areas) or 1.0
    rng = np.random.default_rng(seed)
    out: dict[str, list[np.ndarray]] = {k: [] for k in ("position", "normal", "base_color", "metallic", "roughness", "area")}
    for p, m, a in zip(parts, meshes, areas):
        n_part = max(1, int(round(count * a / total)))
        if a <= 0:
            continue
        radius = math.sqrt(a / n_part / math.pi) * 0.9
        pts, fi = trimesh.sample.sample_surface_even(m, n_part * 2, radius=radius, seed=int(rng.integers(2 ** 31)))
        if len(pts) < n_part // 2:                              # degenerate meshes: plain area sampling
            pts, fi = trimesh.sample.sample_surface(m, n_part, seed=int(rng.integers(2 ** 31)))
        tri = m.triangles[fi]
        bary = trimesh.triangles.points_to_barycentric(tri, pts)
        bary = np.nan_to_num(bary, nan=1.0 / 3.0)
        f = m.faces[fi]
        fn = m.face_normals[fi]
        nrm = fn
        if p.get("normals") is not None:
            vn = np.asarray(p["normals"], np.float64)
            n_i = np.einsum("nk,nkj->nj", bary, vn[f])
            ln = np.linalg.norm(n_i, axis=1, keepdims=True)
            ok = (ln[:, 0] > 1e-12) & np.isfinite(ln[:, 0])
            n_i = np.where(ok[:, None], n_i / np.where(ok, ln[:, 0], 1)[:, None], fn)
            nrm = np.where((np.einsum("ij,ij->i", n_i, fn) > 0)[:, None], n_i, fn)   # never against the face
        bc = np.broadcast_to(np.asarray(p["base_color"], np.float64), (len(pts), 3)).copy()
        met = np.full(len(pts), float(p["metallic"]))
        rgh = np.full(len(pts), float(p["roughness"]))
        if p.get("uv") is not None:
            uv = np.einsum("nk,nkj->nj", bary, np.asarray(p["uv"], np.float64)[f])
            t = _texture(p.get("base_color_tex"), uv)
            if t is not None:
                bc *= t[:, :3]
            t = _texture(p.get("mr_tex"), uv)
            if t is not None:
                rgh *= t[:, 1]
                met *= t[:, 2]
        if p.get("vertex_color") is not None:
            bc *= np.einsum("nk,nkj->nj", bary, np.asarray(p["vertex_color"], np.float64)[f])
        share = np.full(len(pts), a / max(len(pts), 1))
        sides = [(pts, nrm)]
        if not m.is_watertight:
            sides.append((pts, -nrm))
        for q, nn in sides:
            out["position"].append(q)
            out["normal"].append(nn)
            out["base_color"].append(bc)
            out["metallic"].append(np.clip(met, 0, 1))
            out["roughness"].append(np.clip(rgh, 0, 1))
            out["area"].append(share)
    return {k: np.ascontiguousarray(np.concatenate(v), np.float32) for k, v in out.items()}


def object_bsh(surfels: dict[str, np.ndarray]) -> dict[str, Any]:
    """The surfels' BSH by build-bsh's core (no pruning: the colours change between passes; no
    emitters). Colours start black (pass 0: the object only occludes)."""
    from ..build_bsh import build_bsh

    pts = surfels["position"]
    return build_bsh(pts, surfels["normal"], np.zeros_like(pts), prune=False, emitters="none", isolated=1e30,
                     closed_share=1.0)


def node_colours(bsh: dict[str, Any], radiance: np.ndarray) -> np.ndarray:
    """(K, 3) float32: every object node's colour = the mean outgoing radiance (N,3) of its surfels
    (equal-area surfels: the area mean), as build-bsh averages colours."""
    srt = np.asarray(radiance, np.float64)[bsh["order"]]
    cs = np.concatenate([np.zeros((1, 3)), np.cumsum(srt, 0)])
    first, count = bsh["first"].astype(np.int64), bsh["count"].astype(np.int64)
    return ((cs[first + count] - cs[first]) / np.maximum(count, 1)[:, None]).astype(np.float32)


def merge_nodes(room: np.ndarray, room_splat: np.ndarray, obj: np.ndarray,
                obj_splat: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """(nodes, splat radii, object_first): a new root over the room's tree (nodes 1…M) and the
    object's (M+1…M+K), depth-first like every BSH (the root's left child is the room's root, its
    right child the object's). The root's sphere contains both; its colour is black and its cone all
    directions (the walk always descends it: the receivers are inside)."""
    room = np.ascontiguousarray(room).view(NODE_DTYPE).reshape(-1)
    obj = np.ascontiguousarray(obj).view(NODE_DTYPE).reshape(-1)
    M, K = len(room), len(obj)
    out = np.zeros(1 + M + K, NODE_DTYPE)
    for dst, src, off in ((out[1:1 + M], room, 1), (out[1 + M:], obj, 1 + M)):
        dst[:] = src
        dst["skip"] = src["skip"] + off
        dst["right"] = np.where(src["right"] == LEAF, LEAF, src["right"] + off).astype(np.uint32)
    c0, r0 = room["center"][0].astype(np.float64), float(room["radius"][0])
    c1, r1 = obj["center"][0].astype(np.float64), float(obj["radius"][0])
    d = float(np.linalg.norm(c1 - c0))
    if d + r1 <= r0:
        c, r = c0, r0
    elif d + r0 <= r1:
        c, r = c1, r1
    else:
        r = 0.5 * (d + r0 + r1)
        c = c0 + (c1 - c0) * ((r - r0) / d)
    cone, _, _ = pack_cones(np.array([[0.0, 0.0, 1.0]]), np.array([math.pi]))
    out["right"][0], out["skip"][0] = 1 + M, 1 + M + K
    out["center"][0] = c
    out["color"][0] = 0.0
    out["radius"][0] = np.float32(r * (1 + 1e-6) + 1e-30)
    out["cone"][0] = cone[0]
    splat = np.concatenate([[out["radius"][0]], room_splat, obj_splat]).astype(np.float32)
    return out, splat, 1 + M
