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
than ``object_near`` × its splat radius above the receiver's tangent plane and within ``object_reach`` (2) ×
that radius of it is not splatted (its own surfel and its neighbours on a flat or convex surface: no false
self-shadow; a farther leaf occludes at any height — a concave part's own far wall); an object node seen from
behind is culled as the room's are (a closed surface is seen from outside); open meshes get two-sided
surfels (one per side), their discs kept inside the open edge (:func:`boundary_offsets`).

Units: metres, linear RGB radiance; conventions as the rest of relight.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from ..bsh.format import ALL_DIRECTIONS_CONE, LEAF, NODE_DTYPE, range_slots
from ..color import luminance
from ..io import uv_transformed
from ..runtime import get_logger

log = get_logger("relight")

MIN_SURFELS, MAX_SURFELS = 2000, 50_000
AUTO_BOUNCES = (2, 4)  # bounces = -1 (auto): at least 2, at most 4 passes ...
AUTO_TAIL = 0.01       # ... stopping once the bounces still to come, estimated as a geometric tail, would add less than
                       # this share of the object's mean radiance (bench/README.md 'auto bounces')
LIT = 512              # auto bounce receivers (at most every surfel); 2048 gave the same image on the shipped
                       # scene (4x4 blocks within 0.3 %, bench/README.md) at 4x the bounce time
DIR_LOBE_SAMPLES = 8   # directional bounces: n×n VNDF samples a surfel and direction (the pixels' n = 32 made each bounce
                       # pass 25× dearer: 256 directions × 1 024 samples a surfel)
SPREAD_K = 8           # a surfel takes the radiance of its SPREAD_K nearest lit surfels facing its way
SELF_VIS_RECEIVERS = 256   # self-visibility (:func:`self_visibility`): surfels measured, at micro-buffer side ...
SELF_VIS_M = 16            # ... SELF_VIS_M (a cosine-weighted share: 16² texels give it to ~1 %)
GLOSSY_SELF_VIS = 0.05     # auto bounce receivers of a glossy object (directional bounces): every surfel lit (up to
MAX_LIT = 4096             # MAX_LIT) when its mean self-visibility is at least GLOSSY_SELF_VIS, else LIT (the bowl 0.20,
                           # the shipped knot 0.19, a sphere 0): bowl view1 GGX 0.1 / 0.25 block RMS 27.7 / 12.7 ->
                           # 22.2 / 11.2 %, every shipped glossy row as good or better (bench/README.md 'The glossy
                           # bowl's reflections of itself', bowl_glossy{,_small}.csv)


def auto_count(area: float, radius: float, m: int) -> int:
    """Surfels for an object of total area ``area`` [m²] and bounding radius ``radius`` [m] seen by m×m
    micro-buffers: spacing radius / m (a texel seen from across the object is ~2·radius/m wide), clamped to
    [MIN_SURFELS, MAX_SURFELS]. Measured on the shipped knot (view1, Lambert, 4×4 blocks against full_*):
    2 000 surfels 1.012 / 2.1 %, 4 000 1.013 / 1.9 %, 11 000 1.015 / 2.0 % — the image size does not enter."""
    s = max(radius / max(m, 1), 1e-30)
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


def closed(mesh: Any) -> bool:
    """Whether a trimesh is closed once coincident vertices are merged (seams of UVs or normals duplicate
    vertices without opening the surface)."""
    if mesh.is_watertight:
        return True
    m = mesh.copy()
    m.merge_vertices(merge_tex=True, merge_norm=True)
    return bool(m.is_watertight)


def boundary_offsets(mesh: Any, points: np.ndarray, normals: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """((N,) distance [the mesh's units], (N, 3) unit direction): from each point (on the mesh, unit face normal
    ``normals``) to the nearest point of the mesh's open boundary (edges of one face once coincident vertices are
    merged), within the point's tangent plane; inf and 0 where the mesh has no boundary or the nearest boundary
    point lies off that plane (more than 45° out of it: another sheet, not this one's edge). Candidate edges: those
    of the 8 nearest of the boundary's samples every ``spacing`` / 4; the nearest point of each is exact."""
    n = len(points)
    dist, dirs = np.full(n, np.inf), np.zeros((n, 3))
    m = mesh.copy()
    m.merge_vertices(merge_tex=True, merge_norm=True)
    import trimesh
    from scipy.spatial import cKDTree

    one = trimesh.grouping.group_rows(m.edges_sorted, require_count=1)
    if len(one) == 0 or n == 0 or not spacing > 0:
        return dist, dirs
    a, b = m.vertices[m.edges_sorted[one, 0]], m.vertices[m.edges_sorted[one, 1]]
    steps = np.maximum(np.ceil(np.linalg.norm(b - a, axis=1) / (spacing / 4.0)).astype(np.int64), 1)
    t = np.concatenate([np.arange(k + 1) / k for k in steps])
    seg = np.repeat(np.arange(len(one)), steps + 1)
    samples = a[seg] + t[:, None] * (b[seg] - a[seg])
    _, j = cKDTree(samples).query(points, k=min(8, len(samples)))
    j = np.asarray(j).reshape(n, -1)
    sa, ab = a[seg[j]], (b - a)[seg[j]]                                 # (n, k, 3): the candidate edges
    tt = np.clip(np.einsum("nkj,nkj->nk", points[:, None] - sa, ab) / np.maximum(np.einsum("nkj,nkj->nk", ab, ab), 1e-300),
                 0.0, 1.0)
    near = sa + tt[..., None] * ab
    v = near[np.arange(n), np.argmin(np.linalg.norm(near - points[:, None], axis=2), axis=1)] - points
    vn = np.einsum("ij,ij->i", v, normals)
    tang = v - vn[:, None] * normals
    e = np.linalg.norm(tang, axis=1)
    ok = (np.abs(vn) <= e) & (e > 0)
    dist[ok] = e[ok]
    dirs[ok] = tang[ok] / e[ok, None]
    return dist, dirs


def surface_at(part: dict[str, Any], faces: np.ndarray, face_normals: np.ndarray, bary: np.ndarray) -> dict[str, np.ndarray]:
    """The surface of ``part`` at points given by their triangles (``faces`` (N,3) vertex indices, ``face_normals``
    (N,3) unit, 0 for a degenerate face) and barycentrics ``bary`` (N,3), float64: ``normal`` (the interpolated vertex
    normal, never against the face; else the face's), ``geom_normal`` (the face's; a degenerate face: the shading
    normal), ``base_color`` (N,3), ``metallic``, ``roughness`` (N,) (factor × texture × vertex colour as the
    G-buffer, textures through their KHR_texture_transform, unclipped) and ``emission`` (N,3) (glTF emissive factor ×
    strength × texture). The one material lookup of the object's surface (surfels, self-reflection hits)."""
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    fn = np.asarray(face_normals, np.float64).reshape(-1, 3)
    bary = np.asarray(bary, np.float64).reshape(-1, 3)
    n = len(f)
    nrm = fn
    if part.get("normals") is not None:
        vn = np.asarray(part["normals"], np.float64)
        n_i = np.einsum("nk,nkj->nj", bary, vn[f])
        ln = np.linalg.norm(n_i, axis=1, keepdims=True)
        ok = (ln[:, 0] > 1e-12) & np.isfinite(ln[:, 0])
        n_i = np.where(ok[:, None], n_i / np.where(ok, ln[:, 0], 1)[:, None], fn)
        nrm = np.where((np.einsum("ij,ij->i", n_i, fn) > 0)[:, None], n_i, fn)   # never against the face
    bc = np.broadcast_to(np.asarray(part["base_color"], np.float64), (n, 3)).copy()
    met = np.full(n, float(part["metallic"]))
    rgh = np.full(n, float(part["roughness"]))
    em = np.broadcast_to(np.asarray(part.get("emissive", (0.0, 0.0, 0.0)), np.float64), (n, 3)).copy()
    if part.get("uv") is not None:
        uv = np.einsum("nk,nkj->nj", bary, np.asarray(part["uv"], np.float64)[f])
        t = _texture(part.get("base_color_tex"), uv_transformed(uv, part.get("base_color_uv")))
        if t is not None:
            bc *= t[:, :3]
        t = _texture(part.get("mr_tex"), uv_transformed(uv, part.get("mr_uv")))
        if t is not None:
            rgh *= t[:, 1]
            met *= t[:, 2]
        t = _texture(part.get("emissive_tex"), uv_transformed(uv, part.get("emissive_uv")))
        if t is not None and np.any(em > 0):
            em *= t[:, :3]
    if part.get("vertex_color") is not None:
        bc *= np.einsum("nk,nkj->nj", bary, np.asarray(part["vertex_color"], np.float64)[f])
    fn = np.where((np.linalg.norm(fn, axis=1) > 0.5)[:, None], fn, nrm)   # a degenerate face: its shading normal
    return {"normal": nrm, "geom_normal": fn, "base_color": bc, "metallic": met, "roughness": rgh, "emission": em}


def sample_surfels(parts: list[dict[str, Any]], count: int, seed: int = 0) -> dict[str, np.ndarray]:
    """About ``count`` surfels on the parts' surfaces, area-uniform with a minimum distance (trimesh's
    ``sample_surface_even``). Returns float32 arrays: ``position`` (N,3) [m], ``normal`` (N,3) (the
    interpolated vertex normal, else the face's), ``geom_normal`` (N,3) (the face's: the bounce passes' geometric
    horizon, as the G-buffer's for the pixels), ``base_color`` (N,3), ``metallic`` (N,), ``roughness``
    (N,) (factor × texture × vertex colour as the G-buffer, textures through their KHR_texture_transform),
    ``emission`` (N,3) (the radiance the surface emits: glTF emissive factor × strength × texture), ``area`` (N,) [m²] (each part's area
    over its surfels), ``side`` (N,) uint8, and ``edge_dist`` (N,) [m] / ``edge_dir`` (N,3): the way to the part's
    open boundary in the surfel's plane (:func:`boundary_offsets`; inf / 0 on a closed part: :func:`object_bsh` keeps
    the discs inside the edge). Parts whose mesh is not closed get a second, flipped surfel at
    each sample (side 1): the two sides get separate trees (:func:`object_bsh`), so that no node averages the
    light of both sides of a sheet."""
    import trimesh

    # trimesh works on the parts moved and scaled to the unit box (its tolerances are absolute: merging vertices
    # at 1e-8, zero-area faces at 1e-12 — a millimetre object lost faces and its closedness); positions and
    # areas come back in metres. The choices (faces, minimum distance) are then those of the object's shape, not
    # of its unit: geometry × s gives the surfels × s (to float rounding; issue 28).
    allp = np.concatenate([np.asarray(p["positions"], np.float64).reshape(-1, 3) for p in parts]) if parts else np.zeros((0, 3))
    lo_w = allp.min(0) if len(allp) else np.zeros(3)
    ext = float(np.max(allp.max(0) - lo_w)) if len(allp) else 0.0
    unit = ext if ext > 0 and math.isfinite(ext) else 1.0
    areas = []
    meshes = []
    for p in parts:
        m = trimesh.Trimesh((np.asarray(p["positions"], np.float64) - lo_w) / unit,
                            np.asarray(p["faces"], np.int64).reshape(-1, 3), process=False)
        meshes.append(m)
        areas.append(float(m.area))
    total = sum(areas) or 1.0
    rng = np.random.default_rng(seed)
    out: dict[str, list[np.ndarray]] = {k: [] for k in ("position", "normal", "geom_normal", "base_color", "metallic", "roughness", "area",
                                                         "side", "emission", "edge_dist", "edge_dir")}
    for p, m, a in zip(parts, meshes, areas):
        n_part = max(1, int(round(count * a / total)))
        if a <= 0:
            continue
        radius = math.sqrt(a / n_part / math.pi)
        tl = logging.getLogger("trimesh")
        level = tl.level
        tl.setLevel(logging.ERROR)                               # "only got n/m samples" is expected here
        try:
            pts, fi = trimesh.sample.sample_surface_even(m, n_part * 3, radius=radius, seed=int(rng.integers(2 ** 31)))
        finally:
            tl.setLevel(level)
        pts, fi = pts[:n_part], fi[:n_part]                      # random order: a prefix stays even
        if len(pts) < n_part // 2:                              # degenerate meshes: plain area sampling
            pts, fi = trimesh.sample.sample_surface(m, n_part, seed=int(rng.integers(2 ** 31)))
        tri = m.triangles[fi]
        bary = trimesh.triangles.points_to_barycentric(tri, pts)
        bary = np.nan_to_num(bary, nan=1.0 / 3.0)
        at = surface_at(p, m.faces[fi], m.face_normals[fi], bary)
        nrm, fn, bc, met, rgh, em = (at[k] for k in ("normal", "geom_normal", "base_color", "metallic", "roughness", "emission"))
        share = np.full(len(pts), a * unit * unit / max(len(pts), 1))
        pts = lo_w + pts * unit
        sides = [(pts, nrm, fn)]
        edist, edir = np.full(len(pts), np.inf), np.zeros((len(pts), 3))
        if not closed(m):
            sides.append((pts, -nrm, -fn))
            edist, edir = boundary_offsets(m, (pts - lo_w) / unit, fn, radius)
            edist = edist * unit
        for side, (q, nn, gn) in enumerate(sides):
            out["side"].append(np.full(len(q), side, np.uint8))
            out["position"].append(q)
            out["normal"].append(nn)
            out["geom_normal"].append(gn)
            out["base_color"].append(bc)
            out["metallic"].append(np.clip(met, 0, 1))
            out["roughness"].append(np.clip(rgh, 0, 1))
            out["area"].append(share)
            out["emission"].append(em)
            out["edge_dist"].append(edist)
            out["edge_dir"].append(edir)
    return {k: np.ascontiguousarray(np.concatenate(v), np.uint8 if k == "side" else np.float32) for k, v in out.items()}


EDGE_SHIFT = 0.6   # an open edge's surfel discs move inwards by this share of what they overhang it (_build_object_bsh)

OBJECT_BSH_KEYS = ("nodes", "splat_radius", "order", "first", "count")
# the sources an object BSH is computed by: a cached one is keyed by their bytes too (pipeline/, relative)
OBJECT_BSH_SOURCES = ("bsh/tree.py", "bsh/cones.py", "bsh/builder.py", "bsh/format.py", "relight/surfels.py")


def _object_bsh_key(position: np.ndarray, geom: np.ndarray, side: np.ndarray, *edges: np.ndarray) -> str:
    """Hex digest of an object BSH's inputs (the surfels' positions, face normals, sides and ways to an open edge)
    and of the code that builds it (:data:`OBJECT_BSH_SOURCES`)."""
    from ..io.cache import code_digest, content_digest

    return content_digest("pcrelight.object_bsh/2", position, geom, side, *edges, code_digest(OBJECT_BSH_SOURCES))


def _read_cached_bsh(path: Any, n: int) -> dict[str, Any] | None:
    """A cached object BSH of ``n`` surfels, or None where the file is missing or not one (then it is rebuilt)."""
    from ..io.cache import cache_read

    d = cache_read(path)
    if d is None or any(k not in d for k in OBJECT_BSH_KEYS):
        return None
    out = {k: d[k] for k in OBJECT_BSH_KEYS}
    m = len(out["nodes"])
    if (out["nodes"].dtype != NODE_DTYPE or out["order"].shape != (n,) or m == 0
            or any(out[k].shape != (m,) for k in ("splat_radius", "first", "count"))):
        return None
    return out


def object_bsh(surfels: dict[str, np.ndarray], cache: bool = True) -> dict[str, Any]:
    """The surfels' hierarchy: one BSH per side (:func:`sample_surfels`) by build-bsh's core (no pruning: the
    colours change between passes; no emitters), joined under one root (:func:`join_trees`). The discs lie in the
    surface's plane: their normals (the cones) are the faces' (``geom_normal``), not the smooth shading normals,
    which tilt a disc out of the surface (a quad with vertex normals 60° off its face shadowed itself by 7 % at
    grazing directions). Colours start black (pass 0: the object only occludes). Returns ``nodes``, ``splat_radius``, and for
    :func:`node_colours`: ``order`` (surfel index of each sorted position), ``first``/``count`` (each node's
    range in that order; the joining roots cover their sides' ranges); ``cache``: ``hit``, ``miss`` or ``off``.

    ``cache``: the result is kept in :func:`pipeline.io.cache.cache_dir` ("object_bsh"), named by a digest of the
    surfels and of the code (:func:`_object_bsh_key`), and read from there the next time (the same bytes): the
    build is ~20 ms of work, but loading build-bsh's numba kernels for it cost ~0.6 CPU s of every relight
    (bench/README.md 'relight's fixed costs')."""
    side = surfels.get("side", np.zeros(len(surfels["position"]), np.uint8))
    geom = surfels.get("geom_normal", surfels["normal"])
    n = len(surfels["position"])
    folder = None
    if cache:
        from ..io.cache import cache_dir

        folder = cache_dir("object_bsh")
    path = None
    if folder is not None:
        edges = [surfels[k] for k in ("edge_dist", "edge_dir") if k in surfels]
        path = folder / f"{_object_bsh_key(surfels['position'], geom, side, *edges)}.npz"
        got = _read_cached_bsh(path, n)
        if got is not None:
            return {**got, "cache": "hit"}
    out = _build_object_bsh(surfels["position"], geom, side, surfels.get("edge_dist"), surfels.get("edge_dir"))
    if path is not None:
        from ..io.cache import cache_write

        cache_write(path, out)
    return {**out, "cache": "miss" if path is not None else "off"}


def leaf_radius_of_points(b: dict[str, Any]) -> np.ndarray:
    """(N,) each point's leaf splat radius [m] in a build_bsh result ``b`` (its points in input order)."""
    leaf = np.flatnonzero(b["nodes"]["right"] == LEAF)
    cnt = b["count"][leaf].astype(np.int64)
    r = np.zeros(len(b["order"]))
    r[b["order"][range_slots(b["first"][leaf], cnt)]] = np.repeat(b["splat_radius"][leaf], cnt)
    return r


def _build_object_bsh(position: np.ndarray, geom: np.ndarray, side: np.ndarray, edge_dist: np.ndarray | None = None,
                      edge_dir: np.ndarray | None = None) -> dict[str, Any]:
    """:func:`object_bsh`'s build (no cache). A leaf's disc (build-bsh's splat radius r: its disc holds ~2.3× the
    surfel's share of area, so that neighbours' discs leave no gap) overhangs an open edge by r − e (e =
    ``edge_dist``): past a bowl's rim it hid 1.6 % of the sky from inside (a ray cast on the discs). Such a
    surfel's disc moves inwards (against ``edge_dir``) by EDGE_SHIFT · (r − e) and the side's tree is built again.
    Not the whole overhang: round discs touching a straight edge leave slivers open between them. Measured
    (bench/README.md "The near field's reach", bench/relight/bench_edge_shift.py): the discs' union on a face-on 2 m plate is
    +0.9 % of its form factor unmoved, −2.1 % moved wholly, unbiased at ~0.3; seen at grazing from inside the bowl
    ~0.64; 0.6 lies between."""
    from ..bsh.builder import build_bsh

    def build(p: np.ndarray, g: np.ndarray) -> dict[str, Any]:
        return build_bsh(p, g, np.zeros_like(p), prune=False, emitters="none", isolated=1e30, closed_share=1.0)

    trees, order, ranges = [], [], []
    for sd in np.unique(side):
        idx = np.flatnonzero(side == sd)
        pts = position[idx]
        b = build(pts, geom[idx])
        if edge_dist is not None and edge_dir is not None and np.isfinite(edge_dist[idx]).any():
            e = np.asarray(edge_dist[idx], np.float64)
            shift = EDGE_SHIFT * np.where(np.isfinite(e), np.maximum(leaf_radius_of_points(b) - e, 0.0), 0.0)
            if (shift > 0).any():
                pts = (pts - shift[:, None] * np.asarray(edge_dir[idx], np.float64)).astype(position.dtype)
                b = build(pts, geom[idx])
        base = sum(len(o) for o in order)
        trees.append((b["nodes"], b["splat_radius"]))
        ranges.append((b["first"].astype(np.int64) + base, b["count"].astype(np.int64)))
        order.append(idx[b["order"]])
    nodes, splat, offs = join_trees(trees)
    first = np.zeros(len(nodes), np.int64)
    count = np.zeros(len(nodes), np.int64)
    for (f, c), o in zip(ranges, offs):
        first[o:o + len(f)], count[o:o + len(f)] = f, c
    for i in range(len(nodes) - 1, -1, -1):   # the joining roots: their two children's ranges (contiguous)
        if count[i] == 0 and nodes["right"][i] != LEAF:
            l, r = i + 1, int(nodes["right"][i])
            first[i], count[i] = first[l], count[l] + count[r]
    return {"nodes": nodes, "splat_radius": splat, "order": np.concatenate(order), "first": first, "count": count}


def node_colours(bsh: dict[str, Any], radiance: np.ndarray) -> np.ndarray:
    """(K, C) float32: every object node's colour = the mean outgoing radiance (N, C) of its surfels
    (equal-area surfels: the area mean), as build-bsh averages colours."""
    srt = np.asarray(radiance, np.float64)[bsh["order"]]
    cs = np.concatenate([np.zeros((1, srt.shape[1])), np.cumsum(srt, 0)])
    first, count = bsh["first"], bsh["count"]
    return ((cs[first + count] - cs[first]) / np.maximum(count, 1)[:, None]).astype(np.float32)


def lit_subset(bsh: dict[str, Any], count: int) -> np.ndarray:
    """Indices of ``count`` surfels spread evenly over the surface: every k-th in the BSH's Morton order, kept
    in that order (neighbouring receivers walk alike: coherent SIMD lanes; in sampling order a bounce took
    2–3× as long)."""
    order = np.asarray(bsh["order"], np.int64)
    if count >= len(order):
        return order.copy()
    return order[np.linspace(0, len(order) - 1, count).round().astype(np.int64)]


def self_visibility(ctx: Any, merged: np.ndarray, msplat: np.ndarray, params: Any, srf: dict[str, np.ndarray],
                    idx: np.ndarray) -> np.ndarray:
    """(len(idx),) the share of each surfel ``idx``'s hemisphere that the object itself occupies, cosine-weighted
    (its form factor to the rest of the object, 0…1): the classic walk at :data:`SELF_VIS_M` with the room's nodes
    black, the object's white and the surfel a white Lambert reflector (it then reflects exactly that share). The
    near-field rules are the bounce passes', so a surfel's own and its neighbours' discs on a flat or convex surface
    count for nothing. ``merged``/``msplat``/``params`` as :func:`merge_nodes` and ``params.object_first`` give them."""
    import dataclasses

    from ..gather.base import Receivers
    from ..gather.classic import ClassicGatherer

    first = int(params.object_first)
    nodes = np.array(merged, copy=True)
    nodes["color"][:first] = 0.0
    nodes["color"][first:] = 1.0
    vp = dataclasses.replace(params, brdf="lambert", m=SELF_VIS_M)
    k = len(idx)
    geom = srf.get("geom_normal", srf["normal"])
    recv = Receivers(np.ascontiguousarray(srf["position"][idx]), np.ascontiguousarray(srf["normal"][idx]),
                     np.ascontiguousarray(srf["normal"][idx]), np.ones((k, 3), np.float32), np.zeros(k, np.float32),
                     np.ones(k, np.float32), np.ascontiguousarray(geom[idx]))
    g = ClassicGatherer(ctx, nodes, vp, splat_radius=msplat)
    try:
        rad, _ = g.run(recv, None, None)
    finally:
        g.release()
    return np.clip(np.nan_to_num(np.asarray(rad, np.float64).reshape(k, -1)[:, :3].mean(1)), 0.0, 1.0)


def spread(lit_pos: np.ndarray, lit_nrm: np.ndarray, lit_rad: np.ndarray, pos: np.ndarray, nrm: np.ndarray,
           k: int = SPREAD_K) -> np.ndarray:
    """Radiance (N,3) at surfels (pos, nrm) from the lit subset: the mean of the ``k`` nearest lit surfels
    weighted by max(0, n·n_j)⁴ / (d² + h²) (h = the lit spacing): a surfel takes the light of its side of a
    thin part, not the other side's. A surfel with no lit neighbour facing its way takes the nearest's."""
    from scipy.spatial import cKDTree

    k = min(k, len(lit_pos))
    tree = cKDTree(np.asarray(lit_pos, np.float64))
    d, j = tree.query(np.asarray(pos, np.float64), k=k, workers=-1)   # (every core: the same answer)
    d, j = d.reshape(len(pos), k), j.reshape(len(pos), k)
    h2 = float(np.median(d[:, -1]) ** 2) + 1e-300
    cos = np.einsum("nj,nkj->nk", np.asarray(nrm, np.float64), np.asarray(lit_nrm, np.float64)[j])
    w = np.maximum(cos, 0.0) ** 4 / (d * d + h2)
    none = w.sum(1) <= 0
    w[none, 0] = 1.0
    return (np.einsum("nk,nkc->nc", w, np.asarray(lit_rad, np.float64)[j]) / w.sum(1, keepdims=True)).astype(np.float32)


def _join(a: np.ndarray, sa: np.ndarray, b: np.ndarray, sb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A new root over tree ``a`` (nodes 1…len(a)) and tree ``b`` (after it), depth-first like every BSH (the
    root's left child is a's root, its right child b's); its sphere contains both, its colour is black and its
    cone all directions. Splat radii follow the nodes."""
    M, K = len(a), len(b)
    out = np.zeros(1 + M + K, NODE_DTYPE)
    for dst, src, off in ((out[1:1 + M], a, 1), (out[1 + M:], b, 1 + M)):
        dst[:] = src
        dst["skip"] = src["skip"] + off
        dst["right"] = np.where(src["right"] == LEAF, LEAF, src["right"] + off).astype(np.uint32)
    c0, r0 = a["center"][0].astype(np.float64), float(a["radius"][0])
    c1, r1 = b["center"][0].astype(np.float64), float(b["radius"][0])
    d = float(np.linalg.norm(c1 - c0))
    if d + r1 <= r0:
        c, r = c0, r0
    elif d + r0 <= r1:
        c, r = c1, r1
    else:
        r = 0.5 * (d + r0 + r1)
        c = c0 + (c1 - c0) * ((r - r0) / d)
    out["right"][0], out["skip"][0] = 1 + M, 1 + M + K
    out["center"][0] = c
    out["color"][0] = 0.0
    out["radius"][0] = np.float32(r * (1 + 1e-6) + 1e-30)
    out["cone"][0] = ALL_DIRECTIONS_CONE
    return out, np.concatenate([[out["radius"][0]], sa, sb]).astype(np.float32)


def join_trees(trees: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Join (nodes, splat radii) trees into one BSH: (nodes, splat radii, the index of each tree's root).
    One tree is returned as it is; more are chained: root(t0, root(t1, …))."""
    trees = [(np.ascontiguousarray(n).view(NODE_DTYPE).reshape(-1), np.asarray(s, np.float32)) for n, s in trees]
    if len(trees) == 1:
        return trees[0][0].copy(), trees[0][1].copy(), [0]
    rest, srest, offs = join_trees(trees[1:])
    nodes, splat = _join(trees[0][0], trees[0][1], rest, srest)
    return nodes, splat, [1] + [1 + len(trees[0][0]) + o for o in offs]


def merge_nodes(room: np.ndarray, room_splat: np.ndarray, obj: np.ndarray,
                obj_splat: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """(nodes, splat radii, object_first): the room's tree and the object's under one root
    (:func:`join_trees`); the object's nodes are the last ones, from object_first on."""
    nodes, splat, offs = join_trees([(room, room_splat), (obj, obj_splat)])
    return nodes, splat, offs[1]


def subtree(nodes: np.ndarray, splat: np.ndarray, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
    """One tree of the joined ``nodes`` (:func:`join_trees`), the nodes [lo, hi) with their splat radii, as a tree of
    its own (indices from 0; its skips past the end become ``hi − lo``): :func:`merge_nodes`' room is [1, object_first),
    its object [object_first, len)."""
    out = np.array(nodes[lo:hi], copy=True)
    out["skip"] -= np.uint32(lo)
    out["right"] = np.where(out["right"] == LEAF, LEAF, out["right"] - np.uint32(lo)).astype(np.uint32)
    return out, np.ascontiguousarray(splat[lo:hi], np.float32)


def diffuse_equivalent(srf: dict[str, np.ndarray], kind: str, masking: str = "height-correlated",
                       step: float = 0.02) -> np.ndarray:
    """(N, 3) the albedo that makes each surfel a Lambert reflector of its own hemispherical albedo: the
    cosine-weighted mean over outgoing directions of the BRDF's directional albedo (``brdf.directional_albedo``,
    Gauss–Legendre in cos θ_o). A bounce pass lights the surfels with it: a glossy part then sends the light it
    reflects in all, as its mean (its radiance towards one receiver is view-dependent; the mean keeps the
    energy). Affine in the base colour for fixed metallic and roughness, so it is computed at base 0 and 1 for
    each (metallic, roughness) rounded to ``step``."""
    from ..gather import brdf

    base = np.asarray(srf["base_color"], np.float64)
    if kind == "lambert":
        return base.astype(np.float32)
    key = np.stack([np.round(srf["metallic"] / step), np.round(srf["roughness"] / step)], 1).astype(np.int64)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    x, w = np.polynomial.legendre.leggauss(8)
    mu, w = 0.5 * (x + 1), 0.5 * w
    out = np.zeros_like(base)
    for u, (km, kr) in enumerate(uniq):
        met, rgh = float(np.clip(km * step, 0, 1)), float(np.clip(kr * step, 0, 1))
        a = []
        for b in (0.0, 1.0):
            tot = np.zeros(3)
            for mj, wj in zip(mu, w):
                wo = np.array([math.sqrt(1 - mj * mj), 0.0, mj])
                tot += 2 * wj * mj * brdf.directional_albedo(kind, wo, (b, b, b), met, rgh, masking, 48, 48)
            a.append(tot)
        sel = inv.reshape(-1) == u
        out[sel] = a[0] + (a[1] - a[0]) * base[sel]
    return np.clip(out, 0, 1).astype(np.float32)


def oct_cell(w: np.ndarray, side: int) -> np.ndarray:
    """(N,) int64 cell of unit directions w (N, 3) in a side×side octahedral map of the sphere, row-major (the twin of
    ``pbgi_common.glsl`` pbgi_oct_cell): p = w.xy/|w|₁, folded over the diagonals where w.z < 0."""
    w = np.asarray(w, np.float64).reshape(-1, 3)
    p = w[:, :2] / np.maximum(np.abs(w).sum(1, keepdims=True), 1e-30)
    sg = np.where(p >= 0, 1.0, -1.0)
    p = np.where((w[:, 2] < 0)[:, None], (1.0 - np.abs(p[:, ::-1])) * sg, p)
    c = np.clip(np.floor((p + 1.0) * 0.5 * side).astype(np.int64), 0, side - 1)
    return c[:, 1] * side + c[:, 0]


def oct_dirs(side: int) -> np.ndarray:
    """(side², 3) float64 unit direction of each cell's centre (:func:`oct_cell` of it is the cell)."""
    v, u = np.divmod(np.arange(side * side), side)
    p = np.stack([(u + 0.5) / side * 2 - 1, (v + 0.5) / side * 2 - 1], 1)
    z = 1.0 - np.abs(p).sum(1)
    p = np.where((z < 0)[:, None], (1.0 - np.abs(p[:, ::-1])) * np.where(p >= 0, 1.0, -1.0), p)
    d = np.concatenate([p, z[:, None]], 1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def bounce_tail(lums: list[np.ndarray]) -> float:
    """The share of the object's outgoing light that the bounces after the last pass would still add, from each
    surfel's luminance after passes 1…b (``lums``, arrays of one value per surfel). The increments are taken as a
    geometric series whose ratio q = ΣΔ_b / ΣΔ_{b−1} is summed over the surfels that the last pass still lit
    (Δ_b > 10⁻³ L_b: a bowl's outside never lights itself and must not dilute its inside's q; per surfel q is
    meaningless after two passes — a surfel in the object's shadow gets almost nothing in pass 1 and its first
    bounce in pass 2); still to come ΣΔ_b · q / (1 − q), divided by ΣL_b. 0 when nothing is lit or the last pass
    added nothing, 1 (go on) after one pass or when the increments do not shrink."""
    lums = [np.atleast_1d(np.asarray(x, np.float64)) for x in lums]
    if not lums or lums[-1].sum() <= 0:
        return 0.0
    if len(lums) < 2:
        return 1.0
    prev2 = lums[-3] if len(lums) > 2 else np.zeros_like(lums[-1])
    d, dp = lums[-1] - lums[-2], lums[-2] - prev2
    s = d > 1e-3 * lums[-1]
    if not s.any():
        return 0.0
    num, den = float(d[s].sum()), float(dp[s].sum())
    if den <= 0 or num >= den:
        return 1.0
    q = num / den
    return float(num * q / (1 - q) / lums[-1].sum())


def in_micro_buffers(ctx: Any, srf: dict[str, np.ndarray], nodes: np.ndarray, splat: np.ndarray | None, params: Any,
                     bounces: int, lit_count: int, timings: Any = None,
                     dirs_side: int = 0, bounce_m: int = 0,
                     emitters: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, Any, dict]:
    """Put the surfels ``srf`` (:func:`sample_surfels`) into the room's ``nodes`` (splat radii ``splat``, None =
    node radii) and light them ``bounces`` times: pass 0 leaves them black (occluders) or, where the object
    emits (``srf["emission"]``), their emission; each bounce walks
    ``lit_count`` of them (:func:`lit_subset`, the classic walk, the surfel's normal as its view direction),
    :func:`spread` s their radiance to the others and recolours the object's nodes. ``lit_count`` ≤ 0 (auto):
    :data:`LIT`, except for directional bounces of an object that sees itself (mean :func:`self_visibility` of
    :data:`SELF_VIS_RECEIVERS` surfels ≥ :data:`GLOSSY_SELF_VIS`; ``stats["self_visibility"]``, ``stats["lit_rule"]``):
    every surfel (at most :data:`MAX_LIT`), its light still spread over its :data:`SPREAD_K` nearest (a spatial filter
    at the surfel spacing: each surfel's own near-mirror lobe reads ~one texel of its micro-buffer, and its neighbours'
    differently oriented buffers average that aliasing — on the knot's view2 GGX 0.1 each surfel's own light gave
    10.8 % block RMS, spread 9.7 %).

    Returns (nodes, splat radii, ``params`` with ``object_first`` set, stats). In the bounce passes a glossy
    surfel is a Lambert reflector of its hemispherical albedo (:func:`diffuse_equivalent`) — unless ``dirs_side`` > 0
    and the BRDF is not Lambert: then each lit surfel's radiance is gathered with its own BRDF towards the centres
    of a dirs_side² octahedral map of directions (:func:`oct_dirs`; Eq. 9 in directions mode), spread and averaged
    over the object's nodes like the colours, and ``stats["object_dirs"]`` (object nodes, dirs_side², 3) is what the
    gatherers read (``object_dirs=``) instead of the object's node colours: a glossy part sends its light where
    its lobe points (a glossy bowl's inside). The room's nodes keep their colour. ``bounce_m`` > 0: the bounce
    passes' micro-buffer side (else ``params.m``). ``emitters`` (bsh.npz's, build-bsh's small bright objects, not
    in ``nodes``' colours): added by Eq. 9 in the bounce passes as in the final gather — without them the surfels
    missed the lamps' direct light (28 % of the knot's in the lamp room) and the object's light on itself
    with it: the knot at 512² read 0.964 / 0.952 of the path tracer (4×4 block RMS 5.2 / 5.6 %), with them
    0.985 / 0.978 (3.0 / 3.2 %) (bench/README.md).

    ``bounces`` < 0: as many as the object needs (:data:`AUTO_BOUNCES`): after each pass b ≥ 2 the bounces still
    to come are estimated from the increments of the surfels' luminance (:func:`bounce_tail`: a geometric series);
    the passes stop once that is < :data:`AUTO_TAIL` of the object's outgoing light (a uniformly lit hemispherical
    bowl of albedo ρ has q = ρ/2). For a Lambert object, or a glossy one whose surfels bounce as Lambert reflectors
    of their albedo (``dirs_side`` 0); a glossy object bounced by direction takes :data:`AUTO_BOUNCES`[0]."""
    import dataclasses
    import time

    from ..runtime import Timings
    from ..gather.base import Receivers
    from ..gather.classic import ClassicGatherer

    t = timings if timings is not None else Timings()
    room_splat = np.asarray(splat if splat is not None else np.asarray(nodes).view(NODE_DTYPE)["radius"], np.float32)
    with t.step("surfels"):
        t_bsh = time.perf_counter()
        obsh = object_bsh(srf)
        bsh_s = time.perf_counter() - t_bsh
        merged, msplat, first = merge_nodes(nodes, room_splat, obsh["nodes"], obsh["splat_radius"])
    params = dataclasses.replace(params, object_first=first)
    N = len(srf["position"])
    # auto: a glossy object bounced by direction keeps 2 passes — more made it worse (bowl view1 GGX 0.25 1.013 / 1.046
    # / 1.054 at 2 / 3 / 4, the knot's view2 1.001 / 1.012 / 1.016: bench/relight/auto_bounce_dirs_passes.csv); one bounced as
    # Lambert reflectors (roughness >= 0.5: no directional bounces) takes the Lambert object's tail rule — with 2 passes
    # the knot's view2 GGX 0.5 read 0.989 / 0.986 / 0.978 of full_*, with the rule (4 passes) 1.005 / 1.002 / 0.993
    # (bench/relight/auto_bounces_glossy_small.csv); GGX 1.0 stops at 2 by the rule
    auto = int(bounces) < 0 and (params.brdf == "lambert" or int(dirs_side) <= 0)
    if int(bounces) < 0 and not auto:
        bounces = AUTO_BOUNCES[0]
    max_bounces = AUTO_BOUNCES[1] if auto else int(bounces)
    directional = int(dirs_side) > 0 and params.brdf != "lambert" and max_bounces > 0
    stats: dict[str, Any] = {"surfels": N, "object_nodes": int(len(obsh["nodes"])), "bounces": max_bounces,
                             "bounce_s": [], "object_bsh_cache": obsh["cache"], "object_bsh_s": round(bsh_s, 4)}
    smooth = False            # spread the lit surfels' light even when every surfel is lit (auto, glossy)
    if int(lit_count) <= 0:   # auto: every surfel of a glossy object that sees itself (its reflections of itself)
        lit_count = LIT
        if directional:
            with t.step("self_visibility"):
                vis = self_visibility(ctx, merged, msplat, params, srf, lit_subset(obsh, min(N, SELF_VIS_RECEIVERS)))
            v = float(vis.mean())
            lit_count = min(N, MAX_LIT) if v >= GLOSSY_SELF_VIS else LIT
            smooth = v >= GLOSSY_SELF_VIS
            stats["self_visibility"] = round(v, 4)
            stats["lit_rule"] = (f"glossy, self-visibility {v:.3f} {'>=' if v >= GLOSSY_SELF_VIS else '<'} "
                                 f"{GLOSSY_SELF_VIS}: {'every surfel (at most %d)' % MAX_LIT if v >= GLOSSY_SELF_VIS else LIT} lit")
            log.info("bounce receivers auto: %s (mean over %d surfels)", stats["lit_rule"], len(vis))
    lit = lit_subset(obsh, min(N, max(1, int(lit_count))))
    stats["lit_surfels"] = int(len(lit))
    log.info("object BSH: %d nodes (%s); %s bounce(s), %d of %d surfels lit a bounce", len(obsh["nodes"]),
             {"hit": "from the cache", "miss": "built, cached", "off": "built"}[obsh["cache"]],
             f"auto ({AUTO_BOUNCES[0]}…{AUTO_BOUNCES[1]})" if auto else max_bounces, len(lit), N)
    bounces = max_bounces
    dirs = oct_dirs(int(dirs_side)) if directional else None
    if directional:   # bounce passes: each lit surfel with its own BRDF, towards every direction of the map
        albedo = srf["base_color"]
        bparams = dataclasses.replace(params, lobe_samples=min(int(params.lobe_samples), DIR_LOBE_SAMPLES))
        log.info("glossy bounces: %d directions a surfel (%d×%d octahedral map)", len(dirs), dirs_side, dirs_side)
    else:             # each surfel a Lambert reflector of its hemispherical albedo (diffuse_equivalent)
        albedo = diffuse_equivalent(srf, params.brdf, params.masking) if bounces else srf["base_color"]
        bparams = dataclasses.replace(params, brdf="lambert")
    if bounce_m:
        bparams = dataclasses.replace(bparams, m=int(bounce_m))
    stats["bounce_dirs"] = 0 if dirs is None else len(dirs)
    stats["bounce_microbuffer"] = int(bparams.m)
    geom = srf.get("geom_normal", srf["normal"])     # the faces' planes: Eq. 9's geometric horizon
    recv = Receivers(*(np.ascontiguousarray(a[lit]) for a in (srf["position"], srf["normal"], srf["normal"], albedo,
                                                              srf["metallic"], srf["roughness"], geom)))
    obj_dirs = None
    emit = srf.get("emission")
    emit = np.asarray(emit, np.float64) if emit is not None and np.any(emit > 0) else None
    if emit is not None:     # an emissive object lights itself: its nodes carry its emission from pass 0 on
        merged["color"][first:] = node_colours(obsh, emit)
        stats["emitting_surfels"] = int(np.count_nonzero(emit.max(1) > 0))
        log.info("object emission: %d of %d surfels emit (max %.4g): their light reaches the object's other parts",
                 stats["emitting_surfels"], N, float(emit.max()))
    lums: list[np.ndarray] = []   # each surfel's luminance after each pass (auto bounces)
    for b in range(int(bounces)):
        t0 = time.perf_counter()
        g = ClassicGatherer(ctx, merged, bparams, splat_radius=msplat, object_dirs=obj_dirs,
                            emitters=emitters if emitters is not None and len(emitters) else None)
        try:
            bt = Timings()
            with t.step(f"bounce{b + 1}"):
                lrad, _ = g.run(recv, None, None, timings=bt, view_dirs=dirs)
                lrad = np.where(np.isfinite(lrad), np.maximum(lrad, 0), 0).reshape(len(lit), -1)
                if len(lit) == N and not smooth:   # every surfel lit: lit is a permutation (Morton order) of them
                    rad = np.empty_like(lrad)
                    rad[lit] = lrad
                else:
                    rad = spread(recv.position, recv.normal, lrad, srf["position"], srf["normal"])
                if emit is not None:   # outgoing = reflected + emitted (the same towards every direction)
                    rad = (rad.reshape(N, -1, 3) + emit[:, None, :]).reshape(N, -1)
        finally:
            g.release()
        cols = node_colours(obsh, rad)
        if dirs is None:
            merged["color"][first:] = cols
            mean = rad.mean(0)
        else:
            obj_dirs = cols.reshape(len(cols), len(dirs), 3)
            lit_cells = np.maximum((obj_dirs.max(2) > 0).sum(1, keepdims=True), 1)
            merged["color"][first:] = obj_dirs.sum(1) / lit_cells    # the mean over the lit cells (not read)
            mean = rad.reshape(N, len(dirs), 3).mean((0, 1))
        stats["bounce_s"].append(round(time.perf_counter() - t0, 3))
        stats.setdefault("bounce_steps_s", []).append({k: round(v, 3) for k, v in bt.as_dict().items()})
        log.info("bounce %d: mean surfel radiance %s (max %.4g, 99.9th percentile %.4g), %.2f s", b + 1,
                 np.round(mean, 4).tolist(), float(rad.max()), float(np.percentile(rad, 99.9)), stats["bounce_s"][-1])
        lums.append(luminance(rad.reshape(N, -1, 3).mean(1), np.float64))
        if auto and b + 1 >= AUTO_BOUNCES[0]:
            tail = bounce_tail(lums)
            stats.setdefault("bounce_tail", []).append(round(tail, 5))
            if tail < AUTO_TAIL or b + 1 == bounces:
                stats["bounces"] = b + 1
                log.info("auto bounces: %d (the bounces still to come would add ~%.2f %% of the object's mean "
                         "radiance; stop below %.0f %%, at most %d)", b + 1, 100 * tail, 100 * AUTO_TAIL,
                         AUTO_BOUNCES[1])
                break
    stats["object_dirs"] = obj_dirs
    return merged, msplat, params, stats
