"""Headless GL: context, exact pixels from a known triangle, GS + transform feedback counts."""

from __future__ import annotations

import numpy as np

from pipeline import gl


def test_egl_context_is_gl45_core(gl_context):
    info = gl.context_info(gl_context)
    assert info["route"] == "egl"
    major, minor = map(int, info["version"].split()[0].split(".")[:2])
    assert (major, minor) >= (4, 3)


def test_triangle_pixels_exact(gl_context):
    prog = gl.make_program(gl_context, "smoke_tri.vert.glsl", "smoke_tri.frag.glsl", here=gl.__file__)
    fbo = gl_context.framebuffer(color_attachments=[gl_context.texture((8, 8), 4, dtype="f4")])
    fbo.use()
    fbo.clear(0, 0, 0, 0)
    vbo = gl_context.buffer(np.array([-1, -1, 1, -1, -1, 1], dtype="f4").tobytes())
    gl_context.vertex_array(prog, [(vbo, "2f", "in_pos")]).render()
    px = np.frombuffer(fbo.read(components=4, dtype="f4"), dtype="f4").reshape(8, 8, 4)
    j, i = np.mgrid[0:8, 0:8]  # row (y from the bottom), column
    expected = (i + j) < 7
    assert np.array_equal(px[:, :, 3] > 0.5, expected)
    np.testing.assert_array_equal(px[expected][:, :3], np.tile([1.0, 0.5, 0.25], (28, 1)))
    assert gl_context.error == "GL_NO_ERROR"


def test_geometry_shader_transform_feedback_count_exact(gl_context):
    r = gl.smoke_test(gl_context)
    assert r["tf_primitives"] == r["tf_expected"] == 35
    assert r["tf_values_ok"] and r["triangle_pixels"] == 28 and r["error"] == "GL_NO_ERROR"


def test_load_glsl_resolves_includes(tmp_path):
    (tmp_path / "a.glsl").write_text('#version 430\n#include "b.glsl"\nvoid main(){}\n')
    (tmp_path / "b.glsl").write_text('#include "a.glsl"\nfloat f(){return 1.0;}\n')
    src = gl.load_glsl("a.glsl", tmp_path / "x.py")
    assert "float f()" in src and src.count("#version") == 1
