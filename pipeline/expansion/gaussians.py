"""3D Gaussian splats (Kerbl et al. 2023) as a room's picture: the splats rendered from any pinhole camera on the
headless GL context — depth-sorted, alpha-blended anisotropic Gaussians (the EWA projection of the reference
rasteriser and its 0.3 px² low-pass in numpy, :func:`_projected`; ``gaussians.vert/frag.glsl`` draw the quads,
α = min(0.99, o·exp(−½ dᵀΣ'⁻¹d)) dropped below 1/255) —
with whatever colours the caller gives them (the import's LDR DC colours, or the HDR-expanded cloud's), and a
brute-force twin on the CPU (:func:`render_reference`) that the tests hold the GL route to; and a splat room made
from a surface cloud (:func:`splats_on_surface`: discs of Gaussians along each point's tangent plane), for test
data with a known truth.

Conventions: metres; ``world_to_camera`` is OpenGL eye space (looking down −z, +y up: relight's
:meth:`pipeline.camera.Camera.view_matrix`); ``f`` the focal length [pixels], the principal point at the image
centre; images (H, W, 4) premultiplied linear RGB + α with **row 0 at the top** (as relit.exr). Quaternions
(w, x, y, z) map a splat's own axes to world axes (:func:`pipeline.camera.quat_matrix`); ``sigma`` the standard
deviations along them [m] (a 3DGS file's exp(scale_*)).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..camera import quat_matrix

LOW_PASS_PX2 = 0.3      # the reference rasteriser's screen-space dilation [px²]
MAX_ALPHA = 0.99
MIN_ALPHA = 1.0 / 255.0


def covariances(sigma: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """World covariances (N, 3, 3) [m²] of splats with axes' standard deviations ``sigma`` (N, 3) and rotations
    ``quat`` (N, 4): Σ = R S Sᵀ Rᵀ."""
    M = quat_matrix(quat) * np.asarray(sigma, np.float64)[:, None, :]
    return M @ np.transpose(M, (0, 2, 1))


def _projected(pos: np.ndarray, sigma: np.ndarray, quat: np.ndarray, world_to_camera: np.ndarray, f: float,
               size: tuple[int, int], near: float) -> dict[str, np.ndarray]:
    """Every splat projected (float64; the one projection both renderers use): ``ok`` (N,) in front of the near
    plane with a positive-definite Σ', ``depth`` d [m], ``uv`` the centre (N, 2) [px, window coordinates: y up from
    the bottom edge], ``conic`` Σ'⁻¹ as (a, b, c) [px⁻²], ``rad`` the quad's half side 3 √λ_max(Σ') [px]."""
    m = np.asarray(world_to_camera, np.float64).reshape(4, 4)
    c = np.asarray(pos, np.float64) @ m[:3, :3].T + m[:3, 3]
    d = -c[:, 2]
    ok = d > near
    ds = np.where(ok, d, 1.0)
    # camera-space covariance: (R_wc M)(R_wc M)ᵀ with M = R_q S
    Mc = np.einsum("ij,njk->nik", m[:3, :3], quat_matrix(quat) * np.asarray(sigma, np.float64)[:, None, :])
    # (u, v) = f (x, y) / d + size / 2, d = −z: the Jacobian's rows (f/d, 0, f x/d²), (0, f/d, f y/d²)
    J = np.zeros((len(c), 2, 3))
    J[:, 0, 0] = J[:, 1, 1] = f / ds
    J[:, 0, 2] = f * c[:, 0] / ds ** 2
    J[:, 1, 2] = f * c[:, 1] / ds ** 2
    JM = J @ Mc
    P = JM @ np.transpose(JM, (0, 2, 1)) + LOW_PASS_PX2 * np.eye(2)
    det = P[:, 0, 0] * P[:, 1, 1] - P[:, 0, 1] ** 2
    ok &= det > 0
    dets = np.where(ok, det, 1.0)
    mid = 0.5 * (P[:, 0, 0] + P[:, 1, 1])
    return {"ok": ok, "depth": d, "uv": f * c[:, :2] / ds[:, None] + 0.5 * np.asarray(size, np.float64),
            "conic": np.stack([P[:, 1, 1], -P[:, 0, 1], P[:, 0, 0]], 1) / dets[:, None],
            "rad": 3.0 * np.sqrt(mid + np.sqrt(np.maximum(mid * mid - det, 0.1)))}


def render_reference(pos: np.ndarray, sigma: np.ndarray, quat: np.ndarray, opacity: np.ndarray, color: np.ndarray,
                     world_to_camera: np.ndarray, f: float, size: tuple[int, int], near: float = 1e-3) -> np.ndarray:
    """Brute force on the CPU (every splat at every pixel centre within its quad, back to front): the twin of
    :func:`render_gaussians`' rasterisation for small tests. (H, W, 4) premultiplied, row 0 at the top."""
    W, H = int(size[0]), int(size[1])
    pr = _projected(pos, sigma, quat, world_to_camera, f, size, near)
    ys, xs = np.mgrid[0:H, 0:W]
    px = np.stack([xs + 0.5, ys + 0.5], -1).reshape(-1, 2)          # GL window coordinates (y up)
    rgb = np.zeros((len(px), 3))
    a = np.zeros(len(px))
    col = np.asarray(color, np.float64)
    for i in np.argsort(-pr["depth"], kind="stable"):
        if not pr["ok"][i]:
            continue
        ca, cb, cc = pr["conic"][i]
        dd = px - pr["uv"][i]
        power = -0.5 * (ca * dd[:, 0] ** 2 + 2 * cb * dd[:, 0] * dd[:, 1] + cc * dd[:, 1] ** 2)
        ai = np.minimum(MAX_ALPHA, float(opacity[i]) * np.exp(np.minimum(power, 0.0)))
        ai[(ai < MIN_ALPHA) | (power > 0) | (np.abs(dd) > pr["rad"][i]).any(1)] = 0.0
        rgb = rgb * (1 - ai[:, None]) + ai[:, None] * col[i]
        a = a * (1 - ai) + ai
    out = np.concatenate([rgb, a[:, None]], 1).reshape(H, W, 4)
    return np.flipud(out).astype(np.float32)


def render_gaussians(pos: np.ndarray, sigma: np.ndarray, quat: np.ndarray, opacity: np.ndarray, color: np.ndarray,
                     world_to_camera: np.ndarray, f: float, size: tuple[int, int], near: float = 1e-3,
                     ctx: Any = None) -> tuple[np.ndarray, dict[str, Any]]:
    """The splats seen by one pinhole camera, on GL (``gaussians.vert/frag.glsl``: one point sprite a splat, projected
    in the shader, float32 target, back to front by their centres' depth, "over" blending of premultiplied
    colour). Returns ((H, W, 4) premultiplied linear RGB + α, row 0 at the top; stats: splats drawn, those whose
    3σ sprite is wider than llvmpipe's largest point and was cut at 255 px)."""
    import moderngl

    from .. import gl

    W, H = int(size[0]), int(size[1])
    m = np.asarray(world_to_camera, np.float64).reshape(4, 4)
    pos = np.asarray(pos, np.float64)
    d = -(pos @ m[2, :3] + m[2, 3])
    order = np.flatnonzero(d > near)
    order = order[np.argsort(-d[order].astype(np.float32), kind="stable")].astype(np.uint32)
    q = np.asarray(quat, np.float32)
    inst = np.concatenate([pos.astype(np.float32), np.asarray(sigma, np.float32), q / np.linalg.norm(q, axis=1, keepdims=True),
                           np.asarray(opacity, np.float32).reshape(-1, 1), np.asarray(color, np.float32)], 1)
    margin = 128
    full = (W + 2 * margin, H + 2 * margin)
    own = ctx is None
    if own:
        ctx = gl.create_context()
    try:
        prog = _program(ctx, own)
        vbo = ctx.buffer(inst if len(inst) else b"\0" * 56)
        ibo = ctx.buffer(order if len(order) else b"\0" * 4)      # the drawing order: back to front
        vao = ctx.vertex_array(prog, [(vbo, "3f 3f 4f 1f 3f", "in_pos", "in_sigma", "in_quat", "in_opacity", "in_color")],
                               index_buffer=ibo, index_element_size=4)
        tex = ctx.texture(full, 4, dtype="f4")
        fbo = ctx.framebuffer(color_attachments=[tex])
        fbo.use()
        fbo.clear(0.0, 0.0, 0.0, 0.0)
        fbo.scissor = (margin, margin, W, H)      # the guard band holds sprite centres, never fragments read back
        fbo.use()
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        ctx.enable(moderngl.BLEND | moderngl.PROGRAM_POINT_SIZE)
        ctx.blend_func = moderngl.ONE, moderngl.ONE_MINUS_SRC_ALPHA
        prog["R"].write(np.ascontiguousarray(m[:3, :3].T, np.float32).tobytes())   # column-major
        prog["eye"].value = tuple(float(x) for x in -m[:3, :3].T @ m[:3, 3])
        prog["f"].value = float(f)
        prog["size"].value = (float(W), float(H))
        prog["margin"].value = float(margin)
        prog["near"].value = float(near)
        if len(order):
            vao.render(moderngl.POINTS, vertices=len(order))
        ctx.finish()
        img = np.frombuffer(fbo.read(viewport=(margin, margin, W, H), components=4, dtype="f4"),
                            np.float32).reshape(H, W, 4)
        ctx.disable(moderngl.BLEND)
        gl.bind_dummy_framebuffer(ctx)            # not left bound to the framebuffer released here
        for o in (vao, vbo, ibo, fbo, tex) + ((prog,) if own else ()):
            o.release()
    finally:
        if own:
            ctx.release()
    return np.flipud(img).copy(), {"drawn": int(len(order)), "cut": _cut_count(pos, sigma, quat, m, f, size, near, d)}


_PROGRAMS: dict[int, tuple[Any, Any]] = {}   # id(ctx) → (ctx, program): compiled once per caller's context


def _program(ctx: Any, own: bool) -> Any:
    """The splat program on ``ctx``: compiled afresh on a context made for one call, else kept per context (a
    compile and link on llvmpipe is ~10⁻¹ s, a fifth of a 200 000-splat frame)."""
    from .. import gl

    hit = None if own else _PROGRAMS.get(id(ctx))
    if hit is None or hit[0] is not ctx:
        hit = (ctx, gl.make_program(ctx, vertex="gaussians.vert.glsl", fragment="gaussians.frag.glsl", here=__file__))
        if not own:
            _PROGRAMS[id(ctx)] = hit
    return hit[1]


def _cut_count(pos: np.ndarray, sigma: np.ndarray, quat: np.ndarray, m: np.ndarray, f: float, size: tuple[int, int],
               near: float, d: np.ndarray) -> int:
    """How many splats in front of the camera (``d`` their depths [m]) have a 3σ sprite wider than 255 px (a cheap
    bound first: only the splats whose largest σ could reach it are projected exactly)."""
    s = np.asarray(sigma, np.float64).max(axis=1)
    big = np.flatnonzero((d > near) & (4.5 * f * s / np.maximum(d, near) + 3.0 > 127.0))
    if big.size == 0:
        return 0
    pr = _projected(pos[big], np.asarray(sigma, np.float64)[big], np.asarray(quat, np.float64)[big], m, f, size, near)
    return int(np.count_nonzero(pr["ok"] & (2.0 * pr["rad"] + 1.0 > 255.0)))


def normal_quaternions(normals: np.ndarray) -> np.ndarray:
    """Unit quaternions (N, 4) (w, x, y, z) whose rotation takes +z to each unit normal (N, 3) (the shortest arc;
    −z → a half turn about x)."""
    n = np.asarray(normals, np.float64)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    q = np.stack([1.0 + n[:, 2], -n[:, 1], n[:, 0], np.zeros(len(n))], 1)      # (1 + z·n, z × n)
    flip = q[:, 0] < 1e-9
    q[flip] = [0.0, 1.0, 0.0, 0.0]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def surface_spacing(points: np.ndarray, k: int = 8) -> np.ndarray:
    """Each point's spacing [m] for :func:`splats_on_surface`: the mean of its ``k`` nearest distances, the point
    itself (0) among them (:func:`pipeline.expansion.splats.knn_distances`), i.e. (k − 1)/k × the mean distance to
    its k − 1 nearest other points."""
    from .splats import knn_distances

    return knn_distances(points, k).mean(axis=1)


def splats_on_surface(points: np.ndarray, normals: np.ndarray, spacing: np.ndarray, tangent: float = 0.6,
                      thickness: float = 0.05, opacity: float = 0.95) -> dict[str, np.ndarray]:
    """A 3DGS room made from a surface cloud: one flat Gaussian a point, σ = ``tangent`` × its spacing [m]
    (:func:`surface_spacing`) along
    its tangent plane and ``thickness`` × that along its normal, opacity ``opacity``. Returns pos, sigma, quat,
    opacity (as the renderers take them)."""
    s = np.asarray(spacing, np.float64) * tangent
    return {"pos": np.asarray(points, np.float64), "sigma": np.stack([s, s, s * thickness], 1),
            "quat": normal_quaternions(normals), "opacity": np.full(len(s), float(opacity))}


def focal_px(fov_deg: float, height: int) -> float:
    """The focal length [pixels] of a vertical field of view ``fov_deg`` over ``height`` pixels."""
    return (height / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
