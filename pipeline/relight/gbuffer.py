"""G-buffer of the object to relight (DESIGN stage 7 step 1): rasterised through ``pipeline.gl``.

Camera (:class:`pipeline.camera.Camera`): pinhole, vertical field of view, square pixels, pixel centres at
+0.5, row 0 at the top — the same convention as scene.json's views (:mod:`pipeline.camera`). Object parts come from
``io.read_object`` (OBJ, PLY, glTF 2.0 metallic-roughness with textures) and are placed by an
optional 4×4 row-major ``to_world``. Single-sided materials are back-face culled (a camera inside
a closed object sees nothing of it); double-sided glTF materials are drawn with flipped normals.
Outputs float32 (H, W, ·) arrays: position [m], unit normal (the shading normal), geom_normal (the unit normal of
the triangle's plane, towards the eye: Eq. 9 takes no light from below it), base colour (linear), metallic,
roughness, emission (linear radiance the surface emits: glTF emissive factor × strength × texture; 0 for
other formats), view (unit vector to the eye), mask (bool coverage). Textures are looked up through their
KHR_texture_transform (``io.read_object``'s ``base_color_uv``, ``mr_uv``, ``emissive_uv``, ``normal_uv``); a
normal map perturbs the shading normal (tangent frame from the screen-space derivatives of position and UV).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..camera import Camera
from ..runtime import get_logger

log = get_logger("gbuffer")


def place_parts(parts: list[dict[str, Any]], to_world: np.ndarray | None) -> list[dict[str, Any]]:
    """Apply a 4×4 row-major local → world transform (positions; normals by the inverse transpose, renormalised).

    The placed positions stay float64 (the G-buffer rounds them to float32 for GL, as before): the surfel
    sampler's discrete choices (trimesh's minimum-distance rejection) then see the same surface at any scale of
    ``to_world`` (float32 positions made geometry × 10⁻³ pick other surfels: 1.2·10⁻³ relative RMS, issue 28).
    Normals are unit after the transform (a scale s made them 1/s long, and below 1e-20 the G-buffer took them
    for missing); those the file leaves zero or non-finite (:func:`_sanitize_normals`) are zero."""
    if to_world is None:
        return parts
    M = np.asarray(to_world, np.float64).reshape(4, 4)
    A, t = M[:3, :3], M[:3, 3]
    out = []
    for p in parts:
        q = dict(p)
        q["positions"] = p["positions"].astype(np.float64) @ A.T + t
        if p.get("normals") is not None:
            n0 = _sanitize_normals(p["normals"], len(p["normals"])).astype(np.float64)   # the file's zeros stay zero
            n = n0 @ np.linalg.inv(A)
            ln = np.linalg.norm(n, axis=1, keepdims=True)
            ok = np.isfinite(ln) & (ln > 0)
            q["normals"] = np.where(ok, n / np.where(ok, ln, 1.0), 0.0).astype(np.float32)
        out.append(q)
    return out


def _sanitize_normals(n: np.ndarray | None, count: int) -> np.ndarray:
    """Unit normals; zero or non-finite ones become (0,0,0) (the shader then uses the geometric one)."""
    if n is None:
        return np.zeros((count, 3), np.float32)
    n = np.asarray(n, np.float64)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    ok = np.isfinite(ln) & (ln > 1e-20)
    return np.where(ok, n / np.where(ok, ln, 1.0), 0.0).astype(np.float32)


def render_gbuffer(ctx: Any, parts: list[dict[str, Any]], cam: Camera) -> dict[str, np.ndarray]:
    """Rasterise ``parts`` (world space) from ``cam`` into float32 targets; returns the G-buffer."""
    from .. import gl

    W, H = cam.size
    allp = np.concatenate([p["positions"] for p in parts]).astype(np.float64)
    lo, hi = allp.min(0), allp.max(0)
    c = (lo + hi) / 2
    rad = float(np.linalg.norm(hi - lo) / 2) + 1e-30
    d = float(np.linalg.norm(np.asarray(cam.eye, np.float64) - c))
    far = (d + rad) * 1.01 + 1e-30
    near = max(d - rad, far * 1e-5) * 0.99
    vp = cam.proj_matrix(near, far) @ cam.view_matrix()
    prog = gl.make_program(ctx, "gbuffer.vert.glsl", "gbuffer.frag.glsl", here=__file__)
    tex = [ctx.texture((W, H), 4, dtype="f4") for _ in range(5)]
    depth = ctx.depth_texture((W, H))
    fbo = ctx.framebuffer(color_attachments=tex, depth_attachment=depth)
    prev_fbo = ctx.fbo
    fbo.use()
    fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
    ctx.enable(ctx.DEPTH_TEST)
    prog["view_proj"].write(vp.T.astype(np.float32).tobytes())  # column-major for GLSL
    prog["eye"].value = tuple(float(x) for x in cam.eye)
    made = [fbo, depth, *tex]
    try:
        for p in parts:
            v = p["positions"].astype(np.float32)
            f = np.asarray(p["faces"], np.uint32).reshape(-1)
            if f.size == 0:
                continue
            nv = len(v)
            nrm = _sanitize_normals(p.get("normals"), nv)
            uv = p["uv"].astype(np.float32) if p.get("uv") is not None else np.zeros((nv, 2), np.float32)
            col = p["vertex_color"].astype(np.float32) if p.get("vertex_color") is not None else np.ones((nv, 3), np.float32)
            data = np.concatenate([v, nrm, uv, col], 1).astype(np.float32)
            vbo = ctx.buffer(data.tobytes())
            ibo = ctx.buffer(f.tobytes())
            vao = ctx.vertex_array(prog, [(vbo, "3f 3f 2f 3f", "in_pos", "in_nrm", "in_uv", "in_col")],
                                   index_buffer=ibo, index_element_size=4)
            made += [vbo, ibo, vao]
            _set(prog, base_color=tuple(float(x) for x in p["base_color"]), metallic=float(p["metallic"]),
                 roughness=float(p["roughness"]), has_bc_tex=0, has_mr_tex=0, has_em_tex=0, bc_tex=0, mr_tex=1,
                 em_tex=2, emissive=tuple(float(x) for x in p.get("emissive", (0.0, 0.0, 0.0))), has_nm_tex=0,
                 nm_tex=3, nm_scale=float(p.get("normal_scale", 1.0)))
            for name, key in (("bc_xf", "base_color_uv"), ("mr_xf", "mr_uv"), ("em_xf", "emissive_uv"),
                              ("nm_xf", "normal_uv")):
                xf = p.get(key)
                xf = np.eye(3) if xf is None else np.asarray(xf, np.float64)
                if name in prog:
                    prog[name].write(np.ascontiguousarray(xf.T, np.float32).tobytes())   # column-major for GLSL
            for unit, key, flag in ((0, "base_color_tex", "has_bc_tex"), (1, "mr_tex", "has_mr_tex"),
                                    (2, "emissive_tex", "has_em_tex"), (3, "normal_tex", "has_nm_tex")):
                img = p.get(key)
                if img is not None:
                    img = np.ascontiguousarray(np.flipud(np.asarray(img, np.float32)[..., :3]))
                    t = ctx.texture((img.shape[1], img.shape[0]), 3, img.tobytes(), dtype="f4")
                    t.build_mipmaps()
                    t.repeat_x = t.repeat_y = True
                    t.use(location=unit)
                    made.append(t)
                    _set(prog, **{flag: 1})
            if p.get("double_sided"):
                ctx.disable(ctx.CULL_FACE)
            else:
                ctx.enable(ctx.CULL_FACE)
                ctx.front_face = "ccw"
                ctx.cull_face = "back"
            vao.render()
        ctx.finish()
        out = [np.flipud(np.frombuffer(t.read(), np.float32).reshape(H, W, 4)).copy() for t in tex]
    finally:
        ctx.disable(ctx.DEPTH_TEST | ctx.CULL_FACE)
        prev_fbo.use()
        for o in made:
            o.release()
    err = ctx.error
    if err != "GL_NO_ERROR":
        raise RuntimeError(f"GL error while rasterising the G-buffer: {err}")
    mask = out[0][..., 3] > 0.5
    pos = out[0][..., :3]
    view = np.asarray(cam.eye, np.float32)[None, None] - pos
    vl = np.linalg.norm(view, axis=-1, keepdims=True)
    view = np.where(vl > 0, view / np.where(vl > 0, vl, 1), 0).astype(np.float32)
    gb = {"position": pos, "normal": out[1][..., :3], "geom_normal": out[4][..., :3], "base_color": out[2][..., :3], "metallic": out[2][..., 3],
          "roughness": out[3][..., 0], "emission": out[3][..., 1:4], "view": view, "mask": mask}
    for k in gb:
        if k != "mask":
            gb[k] = np.where(mask[..., None] if gb[k].ndim == 3 else mask, gb[k], 0).astype(np.float32)
    return gb


def _set(prog: Any, **kw: Any) -> None:
    for k, v in kw.items():
        try:
            prog[k].value = v
        except KeyError:
            pass
