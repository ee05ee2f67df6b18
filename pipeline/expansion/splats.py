"""Point splats: the disc-splat geometry and the visibility test (on the cube-map cameras of :mod:`pipeline.camera`) that
render-cubemaps (the cube maps), reproject (their inverse, and the registered photo's occluders), register_photo
(the photo's pose) and the benches share.  No stage imports another stage: each imports this module.

Radii here are world lengths in **metres**; pixel radii say "px".

* :func:`knn_splat_radii` — a *cloud point's* splat radius: ``scale`` × the mean distance to its ``k``
  nearest points (its local spacing); the disc drawn for the point in a cube map.
* :func:`shrink_isolated` — the same radii with *isolated* points (radius > ratio × the median of their
  neighbours') shrunk to their share of area; build-bsh's leaves (:func:`pipeline.bsh.tree.shrink_isolated_leaves`,
  the same result on a grid) and reproject's photo occluders.
* Not here: :func:`pipeline.bsh.builder.splat_radii` — a *BSH node's* splat radius (min of its bounding-sphere
  radius and the area of its voxel leaves' discs), which relight's micro-buffers splat.

Conventions (render-cubemaps writes them in ``cameras.npz``; reproject and register_photo read them)
--------------------------------------------------------------------------------------
* One viewpoint ``eye`` (metres) gives 6 faces in the order +X −X +Y −Y +Z −Z (``face`` 0…5).
  Each face is a right-handed pinhole camera looking down its −Z axis with +Y up (OpenGL camera
  space), rotated as OpenGL renders cube-map faces (``lookAt`` table: +X: up −Y; −X: up −Y;
  +Y: up +Z; −Y: up −Z; +Z: up −Y; −Z: up −Y).  ``world_to_camera`` = [R | −R·eye].
* Pixels: for camera coordinates (x, y, z) with depth d = −z > 0,
  ``[u, v, 1]ᵀ ∝ K · [x, y, −z]ᵀ`` i.e. u = K00·x/d + K02, v = K11·y/d + K12, in pixel units
  whose (0, 0) is the corner of the first pixel of the file (pixel centres at i + 0.5);
  u indexes columns, v indexes **rows in file order**.  The row index grows with camera +Y, i.e.
  row 0 is the GL framebuffer's bottom row = the cube-map texture's t = 0 row, so each EXR is
  exactly the OpenGL cube-map face image (s along columns, t along rows; Table 8.19 of the GL
  spec) and can be uploaded with glTexImage2D as is.  As with every GL cube map, a face viewed
  top-down is the *mirror image* of what the camera sees (side faces: world +Y at the top row,
  but left and right swapped).
* A face is 90° square: K = [[W/2, 0, W/2], [0, H/2, H/2], [0, 0, 1]].
* Face EXR channels: R, G, B (linear LDR colour of the nearest splat), A (coverage 0/1),
  Z (depth d of the nearest splat's centre along the view axis, metres; 0 where empty).

Splatting (numba, deterministic)
--------------------------------
Every point is a screen-aligned disc (a GL point sprite) of world radius
``r = splat_scale · mean distance to its splat_k nearest neighbours`` (:func:`knn_splat_radii`) (local spacing; the defaults
k = 16, scale 1.25 left no hole in uniformly random samples of a plane at 64²…1024², while k = 8,
scale 1 left 0.3–0.6 % of the pixels empty); its pixel radius is ρ_max = f·r/d (f = W/2), capped at
``max_splat_px``; the pixel holding the centre is always covered.  The depth test uses the splat as
a sphere (a "depth sprite": depth d − r·sqrt(1 − ρ²/ρ_max²) at screen distance ρ from its centre),
so where splats of one surface overlap the pixel goes to the nearest centre, not to whichever
came first; ties → smaller point index.  The Z channel stores the winning splat's *centre* depth d.
Faces are rendered in parallel (one face per thread), deterministic.  ``renderer = gl`` draws
the same splats as GL point sprites (splat.vert/frag.glsl through pipeline/gl.py: sprite of side
2ρ_max + 2 px, fragments outside the disc discarded except the centre pixel, gl_FragDepth = sphere
depth / far, GL_LESS in index order, a guard band of max_splat_px so sprites centred outside a face
still reach it).  Measured on this 2-core machine under a load of ~10 (llvmpipe, one cube map, two runs): 20k
points 256²/1024²: numba 0.25–0.26/2.05–2.06 s, GL 0.39–0.53/1.99–2.40 s; 200k points: numba
0.33–0.39/4.49–5.03 s, GL 1.16–1.27/4.44–4.67 s; the two agree on 99.995–99.999 % of the pixels
(the rest: near-ties on GL's 24-bit depth).  numba
stays the default here (no GPU; exact float32 ties, tested against a brute-force reference); the
probe renders of the automatic viewpoints always use numba.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from numba import njit, prange

from ..camera import cube_cameras
from ..runtime import held_stops

# Defaults of the visibility test (render-cubemaps' options; reproject uses them when cameras.npz lacks them).
SPLAT_K = 16          # neighbours of the local spacing
SPLAT_SCALE = 1.25    # splat radius = SPLAT_SCALE × mean distance to the SPLAT_K nearest points
DEPTH_TOL = 0.02      # relative depth tolerance: seen if d ≤ Z·(1 + DEPTH_TOL) + RADIUS_TOL·r
RADIUS_TOL = 1.0      # … + this × the point's splat radius [in units of r]
FACING_TEST = True    # a point whose normal faces away from the eye is not seen

# ----------------------------------------------------------------------------- cameras
def project(points: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project world points (N,3) with one camera: returns (u, v, d) float64 — pixel coordinates in
    the file's column/row order (see the module docstring) and depth d = −z_cam (≤ 0: behind)."""
    p = np.asarray(points, dtype=np.float64)
    c = p @ w2c[:3, :3].T + w2c[:3, 3]
    d = -c[:, 2]
    q = np.stack([c[:, 0], c[:, 1], d], axis=1) @ np.asarray(K, dtype=np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        u = q[:, 0] / q[:, 2]
        v = q[:, 1] / q[:, 2]
    return u, v, d


def seen_in_face(points: np.ndarray, K: np.ndarray, w2c: np.ndarray, depth: np.ndarray,
                   cover: np.ndarray, rel_tol: float, normals: np.ndarray | None = None,
                   abs_tol: np.ndarray | float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Visibility of points in one rendered face: (seen bool (N,), row (N,), col (N,)).

    A point is seen when it is in front of the camera, faces it (n·(eye − p) > 0, when ``normals``
    are given), its nearest pixel (floor of u, v) lies in the image and is covered, and its depth
    d ≤ Z·(1 + rel_tol) + abs_tol with Z the depth channel there (abs_tol: scalar or per point,
    e.g. the point's splat radius: a neighbour's splat may win the point's own pixel).
    """
    h, w = depth.shape
    u, v, d = project(points, K, w2c)
    ok = (d > 0) & np.isfinite(u) & np.isfinite(v)
    col = np.full(len(d), -1, dtype=np.int64)
    row = np.full(len(d), -1, dtype=np.int64)
    col[ok] = np.floor(u[ok]).astype(np.int64)
    row[ok] = np.floor(v[ok]).astype(np.int64)
    ok &= (col >= 0) & (col < w) & (row >= 0) & (row < h)
    if normals is not None:
        eye = -w2c[:3, :3].T @ w2c[:3, 3]
        ok &= np.einsum("ij,ij->i", np.asarray(normals, dtype=np.float64), eye - np.asarray(points, dtype=np.float64)) > 0
    seen = np.zeros(len(d), dtype=bool)
    idx = np.nonzero(ok)[0]
    z = depth[row[idx], col[idx]]
    a = cover[row[idx], col[idx]] > 0
    tol = np.broadcast_to(np.asarray(abs_tol, dtype=np.float64), d.shape)[idx]
    seen[idx] = a & (d[idx] <= z * (1.0 + rel_tol) + tol)
    return seen, row, col


# ----------------------------------------------------------------------------- splatting
def knn_distances(points: np.ndarray, k: int, query: np.ndarray | None = None, chunk: int = 500_000) -> np.ndarray:
    """(M, min(k, N)) float64 distances [m] from each cloud point (or each of the points ``query``, indices) to its
    ``k`` nearest cloud points, ascending, the point itself (0) first: one SciPy cKDTree query on all cores, in
    chunks of ``chunk`` query points (the neighbour indices are not kept). :func:`statistical_inliers` and
    :func:`knn_splat_radii` share one such query (``dists=``) in render-cubemaps."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, dtype=np.float64)
    k = min(int(k), len(pts))
    q = pts if query is None else pts[np.asarray(query)]
    out = np.empty((len(q), k), dtype=np.float64)
    if k == 0 or len(q) == 0:
        return out
    tree = cKDTree(pts)
    with held_stops():   # SciPy's worker threads use these arrays
        for a in range(0, len(q), chunk):
            d, _ = tree.query(q[a:a + chunk], k=k, workers=-1)
            out[a:a + chunk] = d.reshape(-1, k)
    return out


def knn_splat_radii(points: np.ndarray, k: int = SPLAT_K, scale: float = SPLAT_SCALE,
                    query: np.ndarray | None = None, dists: np.ndarray | None = None) -> np.ndarray:
    """(N,) float32 splat radius of each cloud point [m]: ``scale`` × the mean distance to its ``k`` nearest
    points (the point itself excluded; its local spacing), the world radius of the disc drawn for it in a cube
    map; only for the points ``query`` (indices) when given.  Duplicate points (distance 0) get the median
    positive radius; fewer than 2 points: 1 mm.  ``dists``: :func:`knn_distances` of the same points (and
    ``query``) with at least k + 1 columns, when already computed."""
    n = len(points)
    if n < 2:
        return np.full(n if query is None else len(query), 1e-3, dtype=np.float32)
    k = min(k, n - 1)
    if dists is None or dists.shape[1] < k + 1:
        dists = knn_distances(points, k + 1, query)
    m = len(dists)
    r = dists[:, 1:k + 1].reshape(m, k).mean(axis=1) * scale
    pos = r[r > 0]
    fallback = float(np.median(pos)) if pos.size else 1e-3
    r = np.where(r > 0, r, fallback)  # duplicate points: use the typical spacing
    return r.astype(np.float32)


def shrink_isolated(cen: np.ndarray, spacing: np.ndarray, ratio: float, k: int = 16) -> tuple[np.ndarray, int]:
    """(radii [m], points changed) for the splat radii ``spacing`` (N,) [m] of the points ``cen`` (N,3) [m]: a
    point (a BSH leaf, or a cloud point with its :func:`knn_splat_radii`) whose spacing exceeds ``ratio`` × the median spacing of its ``k`` nearest ones gets that median / sqrt(2);
    ``ratio`` 0 returns the input.  Used by build-bsh (leaf discs) and reproject (the registered photo's
    occluder discs, and which points read the photo's local peak).

    Why: the splat radius d4/sqrt(2) gives a disc of about twice a point's share of area on a sampled
    surface, where neighbouring discs overlap and the micro-buffer's depth test counts each place once.
    A sphere smaller than the point spacing (a 4 cm lamp among 9 cm spacing) gets 2–3 points whose 4th
    neighbour lies on a far surface: discs of that size, and nothing overlaps them.  With the disc equal
    to the point's share (its neighbours' median disc / 2) the back-culled discs of m points on a sphere
    add up, in expectation, to its cross-section: m · share · E[max(0, cos)] = 4πR² / 4."""
    if ratio <= 0 or len(spacing) <= 1:
        return spacing, 0
    from scipy.spatial import cKDTree

    k = min(k, len(spacing) - 1)
    with held_stops():   # SciPy's worker threads use these arrays
        _, nb = cKDTree(cen).query(cen, k=k + 1, workers=-1)
    med = np.median(spacing[nb[:, 1:]], axis=1)
    iso = spacing > ratio * med
    return np.where(iso, med / math.sqrt(2.0), spacing), int(np.count_nonzero(iso))


@njit(cache=True, inline="always")
def _splat_into(fi, i, px, py, pz, radius, rots, fx, fy, cx, cy, width, height, near, max_px, zbuf, dbuf, ibuf):
    """Splat point i (eye-relative position px, py, pz) into face fi; False when it misses it."""
    d = -(rots[fi, 2, 0] * px + rots[fi, 2, 1] * py + rots[fi, 2, 2] * pz)
    if d <= near:
        return False
    xc = rots[fi, 0, 0] * px + rots[fi, 0, 1] * py + rots[fi, 0, 2] * pz
    yc = rots[fi, 1, 0] * px + rots[fi, 1, 1] * py + rots[fi, 1, 2] * pz
    u = fx * xc / d + cx
    v = fy * yc / d + cy
    rp = fx * radius / d
    if rp > max_px:
        rp = max_px
    if u + rp < 0.0 or v + rp < 0.0 or u - rp >= width or v - rp >= height:
        return False
    c0 = max(int(math.floor(u - rp)), 0)
    c1 = min(int(math.floor(u + rp)), width - 1)
    w0 = max(int(math.floor(v - rp)), 0)
    w1 = min(int(math.floor(v + rp)), height - 1)
    uc = int(math.floor(u))
    vc = int(math.floor(v))
    rp2 = rp * rp
    for row in range(w0, w1 + 1):
        dy = row + 0.5 - v
        for col in range(c0, c1 + 1):
            dx = col + 0.5 - u
            rho2 = (dx * dx + dy * dy) / rp2
            if rho2 > 1.0 and not (row == vc and col == uc):
                continue
            ze = np.float32(d - radius * math.sqrt(max(0.0, 1.0 - rho2)))
            zb = zbuf[fi, row, col]
            if ze < zb or (ze == zb and i < ibuf[fi, row, col]):
                zbuf[fi, row, col] = ze
                dbuf[fi, row, col] = d
                ibuf[fi, row, col] = i
    return True


@njit(parallel=True, cache=True)
def _splat_kernel(points, radii, normals, cull, rots, eyes, fx, fy, cx, cy, width, height, near, max_px,
                  zbuf, dbuf, ibuf):
    """Cube maps (faces 6v…6v+5 = +X −X +Y −Y +Z −Z of view v, one eye each, f = W/2), per face
    (F,H,W): zbuf = depth of the nearest sphere-splat surface, dbuf = that splat's centre depth,
    ibuf = its point index (−1 empty).  One face per thread.  A point is splatted into the face of
    its major axis, and into the others only when its disc may leave that face (minor/major + ρ/f
    ≥ 1) — exactly what splatting every point into every face gives, with ~6× less work."""
    nf = rots.shape[0]
    n = points.shape[0]
    for fi in prange(nf):
        k = fi % 6
        ex = eyes[fi, 0]; ey = eyes[fi, 1]; ez = eyes[fi, 2]
        for i in range(n):
            px = points[i, 0] - ex
            py = points[i, 1] - ey
            pz = points[i, 2] - ez
            ax = abs(px); ay = abs(py); az = abs(pz)
            if ax >= ay and ax >= az:
                fm = 0 if px > 0 else 1
                m = ax; s1 = ay; s2 = az
            elif ay >= az:
                fm = 2 if py > 0 else 3
                m = ay; s1 = ax; s2 = az
            else:
                fm = 4 if pz > 0 else 5
                m = az; s1 = ax; s2 = ay
            if fm != k:
                if m <= near:
                    continue  # its depth along every face axis is ≤ m ≤ near: drawn nowhere
                e = min(fx * radii[i] / m, max_px) / fx
                if s1 / m + e < 1.0 - 1e-9 and s2 / m + e < 1.0 - 1e-9:
                    continue  # the disc stays inside its major face
            if cull and normals[i, 0] * px + normals[i, 1] * py + normals[i, 2] * pz >= 0.0:
                continue  # back-facing: the eye is behind the point's surface
            _splat_into(fi, i, px, py, pz, radii[i], rots, fx, fy, cx, cy, width, height, near, max_px,
                        zbuf, dbuf, ibuf)


def splat_cube_faces(points: np.ndarray, radii: np.ndarray, K: np.ndarray, w2c: np.ndarray,
                width: int, height: int, near: float = 1e-3, max_px: float = 32.0,
                normals: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Depth-tested disc splats of ``points`` into the F = 6V faces of V cube maps (as
    :func:`pipeline.camera.cube_cameras` lays them out: intrinsics ``K``, size width × height); with ``normals``,
    back-facing points (n·(eye − p) ≤ 0) are culled.
    Returns (depth (F,H,W) float32, 0 where empty; index (F,H,W) int32, −1 empty).
    Depths are compared in float32 (ties → lower index)."""
    w2c = np.asarray(w2c, dtype=np.float64).reshape(-1, 4, 4)
    if len(w2c) % 6:
        raise ValueError(f"splat_cube_faces renders whole cube maps: {len(w2c)} faces is not a multiple of 6")
    rots = np.ascontiguousarray(w2c[:, :3, :3])
    eyes = np.ascontiguousarray(-np.einsum("fji,fj->fi", rots, w2c[:, :3, 3]))  # eye = −Rᵀt
    nf = len(w2c)
    zbuf = np.full((nf, height, width), np.inf, dtype=np.float32)
    dbuf = np.zeros((nf, height, width), dtype=np.float32)
    ibuf = np.full((nf, height, width), -1, dtype=np.int32)
    cull = normals is not None
    nrm = np.ascontiguousarray(normals if cull else np.zeros((1, 3)), dtype=np.float64)
    _splat_kernel(np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(radii, dtype=np.float64),
                  nrm, cull, rots, eyes, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                  int(width), int(height), float(near), float(max_px), zbuf, dbuf, ibuf)
    return dbuf, ibuf


def splat_cube_faces_gl(points: np.ndarray, radii: np.ndarray, K: np.ndarray, w2c: np.ndarray,
                   width: int, height: int, near: float = 1e-3, max_px: float = 32.0,
                   normals: np.ndarray | None = None, ctx: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """The GL route of :func:`splat_cube_faces` (point sprites, splat.vert/frag.glsl): same disc, centre
    pixel and sphere-depth rules, depth test GL_LESS in drawing order (ties → lower index) on a
    24-bit depth buffer of sphere depth / far — so near-ties may resolve differently from the
    float32 numba route.  Back-face culling is not implemented here (``normals`` must be None)."""
    import moderngl

    from .. import gl

    if normals is not None:
        raise NotImplementedError("the GL splatter has no back-face culling; use the numba route")
    w2c = np.asarray(w2c, dtype=np.float64).reshape(-1, 4, 4)
    own = ctx is None
    if own:
        ctx = gl.create_context()
    try:
        margin = int(math.ceil(max_px)) + 2
        full = (width + 2 * margin, height + 2 * margin)
        prog = gl.make_program(ctx, vertex="splat.vert.glsl", fragment="splat.frag.glsl", here=__file__)
        pts = np.ascontiguousarray(points, dtype=np.float32)
        rad = np.ascontiguousarray(radii, dtype=np.float32)
        vbo = ctx.buffer(np.concatenate([pts, rad[:, None]], axis=1).astype(np.float32).tobytes())
        vao = ctx.vertex_array(prog, [(vbo, "3f 1f", "in_pos", "in_radius")])
        t_id = ctx.texture(full, 1, dtype="i4")
        t_d = ctx.texture(full, 1, dtype="f4")
        depth = ctx.depth_texture(full)
        fbo = ctx.framebuffer(color_attachments=[t_id, t_d], depth_attachment=depth)
        fbo.use()
        ctx.enable(moderngl.DEPTH_TEST | moderngl.PROGRAM_POINT_SIZE)
        ctx.depth_func = "<"
        eyes = -np.einsum("fji,fj->fi", w2c[:, :3, :3], w2c[:, :3, 3])
        lo, hi = pts.min(axis=0).astype(np.float64), pts.max(axis=0).astype(np.float64)
        corners = np.array([[(lo, hi)[b >> k & 1][k] for k in range(3)] for b in range(8)])
        far = float(np.linalg.norm(corners[None] - eyes[:, None], axis=2).max()) * 1.01 + 1.0  # ≥ every depth
        prog["f"].value = float(K[0, 0])
        prog["size"].value = (float(width), float(height))
        prog["margin"].value = float(margin)
        prog["near"].value = float(near)
        prog["max_px"].value = float(max_px)
        prog["far"].value = far
        zs = np.zeros((len(w2c), height, width), dtype=np.float32)
        ids = np.full((len(w2c), height, width), -1, dtype=np.int32)
        for fi in range(len(w2c)):
            prog["R"].write(np.ascontiguousarray(w2c[fi, :3, :3].T, dtype=np.float32).tobytes())  # column-major
            prog["eye"].value = tuple(float(x) for x in eyes[fi])
            fbo.clear(depth=1.0)
            t_id.write(np.full(full[0] * full[1], -1, dtype=np.int32).tobytes())  # "empty" = −1
            vao.render(moderngl.POINTS)
            vp = (margin, margin, width, height)
            ids[fi] = np.frombuffer(fbo.read(viewport=vp, components=1, attachment=0, dtype="i4"),
                                    dtype=np.int32).reshape(height, width)
            zs[fi] = np.frombuffer(fbo.read(viewport=vp, components=1, attachment=1, dtype="f4"),
                                   dtype=np.float32).reshape(height, width)
        zs[ids < 0] = 0.0
        for obj in (vao, vbo, fbo, t_id, t_d, depth, prog):
            obj.release()
        return zs, ids
    finally:
        if own:
            ctx.release()


def render_cube_map(points: np.ndarray, colors: np.ndarray, radii: np.ndarray, eye: np.ndarray, size: int,
                near: float = 1e-3, max_px: float = 32.0, normals: np.ndarray | None = None,
                gl_ctx: Any = None) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """One cube map at ``eye``: faces (6, size, size, 5) float32 = R,G,B,A,Z and its cameras
    (numba splatter, or the GL route when a moderngl context ``gl_ctx`` is given)."""
    cams = cube_cameras(np.asarray(eye).reshape(1, 3), size)
    if gl_ctx is not None:
        z, idx = splat_cube_faces_gl(points, radii, cams["K"][0], cams["world_to_camera"], size, size, near, max_px,
                                normals, ctx=gl_ctx)
    else:
        z, idx = splat_cube_faces(points, radii, cams["K"][0], cams["world_to_camera"], size, size, near, max_px, normals)
    out = np.empty((6, size, size, 5), dtype=np.float32)
    hit = idx >= 0
    out[..., :3] = np.take(np.asarray(colors, dtype=np.float32), np.maximum(idx, 0), axis=0)
    out[..., :3] *= hit[..., None]
    out[..., 3] = hit
    out[..., 4] = z
    return out, cams

@njit(cache=True)
def _view_kernel(points, radii, rots, eyes, fx, fy, cx, cy, width, height, near, max_px, zbuf, dbuf, ibuf):
    """Every point into one pinhole view (face 0 of the buffers), in index order (ties → smaller index)."""
    ex = eyes[0, 0]; ey = eyes[0, 1]; ez = eyes[0, 2]
    for i in range(points.shape[0]):
        _splat_into(0, i, points[i, 0] - ex, points[i, 1] - ey, points[i, 2] - ez, radii[i], rots, fx, fy, cx, cy,
                    width, height, near, max_px, zbuf, dbuf, ibuf)


def view_index(points: np.ndarray, radii: np.ndarray, world_to_camera: np.ndarray, fov_deg: float,
               size: tuple[int, int], near: float = 1e-3, max_px: float = 32.0) -> tuple[np.ndarray, np.ndarray]:
    """Which disc splat (the cube-map splatter's rule, :func:`_splat_into`) one pinhole camera sees at each pixel:
    ``world_to_camera`` 4×4 (OpenGL eye space, looking down −Z, as :meth:`pipeline.camera.Camera.view_matrix`),
    vertical field of view ``fov_deg`` [degrees], ``size`` = (W, H). Returns (index (H, W) int32, −1 where none;
    that splat's centre depth (H, W) float32 [m]), **row 0 at the top** (as relit.exr, unlike the cube faces)."""
    w, h = int(size[0]), int(size[1])
    f = (h / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    m = np.asarray(world_to_camera, dtype=np.float64).reshape(4, 4)
    rots = np.ascontiguousarray(m[None, :3, :3])
    eyes = np.ascontiguousarray((-m[:3, :3].T @ m[:3, 3])[None])
    zbuf = np.full((1, h, w), np.inf, dtype=np.float32)
    dbuf = np.zeros((1, h, w), dtype=np.float32)
    ibuf = np.full((1, h, w), -1, dtype=np.int32)
    # fy = −f: the row index grows downwards (camera +Y up is row 0 at the top)
    _view_kernel(np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(radii, dtype=np.float64),
                 rots, eyes, f, -f, w / 2.0, h / 2.0, w, h, float(near), float(max_px), zbuf, dbuf, ibuf)
    return ibuf[0], dbuf[0]


def render_view(points: np.ndarray, colors: np.ndarray, radii: np.ndarray, world_to_camera: np.ndarray,
                fov_deg: float, size: tuple[int, int], near: float = 1e-3, max_px: float = 32.0) -> np.ndarray:
    """The cloud's disc splats seen by one pinhole camera (:func:`view_index`): (H, W, 5) float32 R,G,B,A,Z with
    row 0 at the top: colours of the nearest splat, coverage, its centre depth [m]."""
    ibuf, dbuf = view_index(points, radii, world_to_camera, fov_deg, size, near, max_px)
    out = np.zeros(ibuf.shape + (5,), dtype=np.float32)
    hit = ibuf >= 0
    out[..., :3][hit] = np.asarray(colors, dtype=np.float32)[ibuf[hit]]
    out[..., 3] = hit
    out[..., 4] = dbuf
    return out

# ----------------------------------------------------------------------------- stray points
def statistical_inliers(points: np.ndarray, neighbors: int = 20, std_ratio: float = 3.0,
                        dists: np.ndarray | None = None) -> np.ndarray:
    """(N,) bool: the points Open3D's statistical outlier removal keeps (``remove_statistical_outlier``: mean
    distance to the ``neighbors`` nearest points, the point itself included, > 0 and < the cloud's mean of that
    distance + ``std_ratio`` sample standard deviations, both over the points with a mean > 0).  Stray scan points
    far from the room would otherwise stretch the bounding box the viewpoint search fills; ``neighbors`` = 0 or
    fewer points than that → all True.  ``dists``: :func:`knn_distances` of ``points`` with ≥ ``neighbors``
    columns, when already computed.

    Computed here on SciPy's cKDTree (all cores) with Open3D's arithmetic — sums in its order, left to right —
    so the same points are kept (checked against Open3D in tests/test_render_cubemaps.py): Open3D's
    single k-d tree pass took 424 of render-cubemaps' 632 s on make-scene full's 3 M points."""
    n = len(points)
    if neighbors <= 0 or n <= neighbors:
        return np.ones(n, dtype=bool)
    if dists is None or dists.shape[1] < neighbors:
        dists = knn_distances(points, neighbors)
    s = dists[:, 0].copy()
    for j in range(1, neighbors):      # std::accumulate: left to right
        s += dists[:, j]
    avg = s / neighbors
    pos = avg > 0
    nv = int(pos.sum())
    if nv == 0:
        return np.zeros(n, dtype=bool)
    mean = float(np.cumsum(avg[pos])[-1]) / nv
    dev = avg[pos] - mean
    std = math.sqrt(float(np.cumsum(dev * dev)[-1]) / (nv - 1)) if nv > 1 else 0.0
    return pos & (avg < mean + std_ratio * std)

def candidate_viewpoints(points: np.ndarray, grid: int, clearance: float, box: np.ndarray | None = None) -> np.ndarray:
    """Cell centres of a lattice of about grid³ cubic-ish cells filling the bounding box of ``box``
    (default ``points``; cells per axis ∝ the box's extent, at least 1), kept where the nearest point
    is ≥ clearance away."""
    from scipy.spatial import cKDTree

    box = points if box is None else box
    lo = box.min(axis=0).astype(np.float64)
    hi = box.max(axis=0).astype(np.float64)
    ext = np.maximum(hi - lo, 1e-9)
    cell = float(np.prod(ext)) ** (1 / 3) / grid
    counts = [max(1, int(round(e / cell))) for e in ext]
    axes = [lo[a] + (np.arange(counts[a]) + 0.5) / counts[a] * (hi[a] - lo[a]) for a in range(3)]
    c = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    with held_stops():   # SciPy's worker threads use these arrays
        d, _ = cKDTree(points).query(c, k=1, workers=-1)
    return c[d >= clearance]

# ----------------------------------------------------------------------------- preview
def cross_layout(faces: np.ndarray) -> np.ndarray:
    """Six (S,S,C) faces in +X −X +Y −Y +Z −Z order → the standard OpenGL cube-map horizontal
    cross (3S, 4S, C): middle row −X +Z +X −Z, +Y above and −Y below +Z, faces drawn as stored
    (file row 0 at the top), so edges meet (the whole cross is the mirror image of the scene, as
    every GL cube-map cross)."""
    s = faces.shape[1]
    c = faces.shape[3]
    out = np.zeros((3 * s, 4 * s, c), dtype=faces.dtype)
    place = {1: (1, 0), 4: (1, 1), 0: (1, 2), 5: (1, 3), 2: (0, 1), 3: (2, 1)}
    for f, (r, q) in place.items():
        out[r * s:(r + 1) * s, q * s:(q + 1) * s] = faces[f]
    return out


SOURCE_COLOURS = np.array([[0.35, 0.35, 0.35], [0.1, 0.8, 0.1], [0.15, 0.35, 1.0]], dtype=np.float32)


def preview_cloud(path: str | Path, cloud: Any, eye: np.ndarray | None = None, size: int = 192) -> None:
    """PNG preview of a cloud: a cube-map cross from ``eye`` (default the box centre), tone-mapped
    colours on top; below, the point kinds: grey kept LDR, green projected, blue Poisson, red invalid."""
    from .. import io

    pts = cloud.points.astype(np.float64)
    if eye is None:
        eye = 0.5 * (pts.min(0) + pts.max(0))
    sel = np.arange(len(pts))
    if len(pts) > 300_000:  # a preview: a fixed subset (every k-th point), radii grown to match
        sel = sel[:: int(math.ceil(len(pts) / 300_000))]
    radii = knn_splat_radii(pts[sel]).astype(np.float64)
    pts = pts[sel]
    cloud = cloud.subset(sel)
    cams = cube_cameras(np.asarray(eye).reshape(1, 3), size)
    z, idx = splat_cube_faces(pts, radii, cams["K"][0], cams["world_to_camera"], size, size)
    hit = idx >= 0
    faces = np.zeros((6, size, size, 4), dtype=np.float32)
    faces[..., :3][hit] = cloud.colors[idx[hit]]
    faces[..., 3] = hit
    top = cross_layout(faces)
    from ..display import reinhard

    rgb = reinhard(top[..., :3], mask=top[..., 3] > 0)
    kind = np.zeros(len(pts), dtype=np.int64) if cloud.source is None else cloud.source.astype(np.int64).clip(0, 2)
    kcol = SOURCE_COLOURS[kind]
    if cloud.valid is not None:
        kcol[cloud.valid == 0] = (1.0, 0.1, 0.1)
    kf = np.zeros((6, size, size, 4), dtype=np.float32)
    kf[..., :3][hit] = kcol[idx[hit]]
    kf[..., 3] = hit
    bottom = cross_layout(kf)
    img = np.concatenate([rgb * top[..., 3:], bottom[..., :3]], axis=0)
    io.write_png(path, io.srgb_encode(img))
