"""The 3D Gaussian splat renderer (pipeline/expansion/gaussians.py, issue 47): the GL route against its brute-force
CPU twin, the quaternions that lay a splat on a surface, the near plane, the sprite cut, and one flat splat's
analytic footprint."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.camera import Camera, quat_matrix
from pipeline.expansion import gaussians as G


def _camera(size=(64, 48)):
    cam = Camera(np.array([0.3, 0.5, 4.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]), 50.0, size)
    return cam.view_matrix(), G.focal_px(50.0, size[1])


def _random_splats(n, seed=0):
    rng = np.random.default_rng(seed)
    return (rng.uniform(-1, 1, (n, 3)), rng.uniform(0.02, 0.3, (n, 3)), rng.normal(size=(n, 4)),
            rng.uniform(0.2, 1.0, n), rng.uniform(0, 3, (n, 3)))


@pytest.mark.parametrize("seed", [0, 1])
def test_gl_matches_the_cpu_twin(gl_context, seed):
    """60 random anisotropic splats (unnormalised quaternions, HDR colours up to 3), 64×48: every pixel of the GL
    image within 1e-5 of the float64 brute force (float32 against float64: measured 1.5–5.5e-6)."""
    V, f = _camera()
    args = (*_random_splats(60, seed), V, f, (64, 48))
    img, st = G.render_gaussians(*args, ctx=gl_context)
    ref = G.render_reference(*args)
    assert img.shape == (48, 64, 4) and st["drawn"] == 60 and st["cut"] == 0
    assert 0.2 < ref[..., 3].mean() < 0.9                    # the case is neither empty nor opaque
    np.testing.assert_allclose(img, ref, atol=1e-5)


def test_one_flat_splat_facing_the_camera_is_its_gaussian(gl_context):
    """A splat facing the camera (σ_x = 2 σ_y, opacity 0.5) at distance d: α at the pixel centres is
    0.5 exp(−½ (x²/s_x² + y²/s_y²)) with s² = (f σ / d)² + 0.3 px² (the low-pass), to float32 precision, and the
    image's row 0 is its top (the splat sits above the centre)."""
    W, H = 41, 41
    cam = Camera(np.array([0.0, 0.0, 5.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]), 40.0, (W, H))
    V, f = cam.view_matrix(), G.focal_px(40.0, H)
    img, _ = G.render_gaussians(np.array([[0.0, 0.2, 0.0]]), np.array([[0.2, 0.1, 0.01]]),
                                np.array([[1.0, 0.0, 0.0, 0.0]]), np.array([0.5]), np.array([[1.0, 1.0, 1.0]]),
                                V, f, (W, H), ctx=gl_context)
    sx2, sy2 = (f * 0.2 / 5) ** 2 + 0.3, (f * 0.1 / 5) ** 2 + 0.3
    cy = H / 2 - f * 0.2 / 5                                   # rows from the top
    y, x = np.mgrid[0:H, 0:W] + 0.5
    a = 0.5 * np.exp(-0.5 * ((x - W / 2) ** 2 / sx2 + (y - cy) ** 2 / sy2))
    a[a < 1 / 255] = 0
    got = img[..., 3]
    inside = np.abs(x - W / 2) <= 3 * math.sqrt(sx2)
    np.testing.assert_allclose(got[inside], a[inside], rtol=2e-5, atol=2e-6)
    assert got.argmax() // W < H // 2


def test_behind_the_near_plane_and_empty_draw_nothing(gl_context):
    V, f = _camera()
    pos, sig, q, op, col = _random_splats(5)
    img, st = G.render_gaussians(pos + [0.0, 0.0, 10.0], sig, q, op, col, V, f, (64, 48), ctx=gl_context)
    assert st["drawn"] == 0 and not img.any()
    img, st = G.render_gaussians(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 4)), np.zeros(0), np.zeros((0, 3)),
                                 V, f, (64, 48), ctx=gl_context)
    assert st["drawn"] == 0 and not img.any()


def test_a_splat_wider_than_the_largest_point_is_counted(gl_context):
    V, f = _camera()
    img, st = G.render_gaussians(np.array([[0.0, 0.0, 3.0]]), np.array([[2.0, 2.0, 2.0]]), np.array([[1.0, 0, 0, 0]]),
                                 np.array([0.9]), np.ones((1, 3)), V, f, (64, 48), ctx=gl_context)
    assert st["cut"] == 1 and img[..., 3].max() > 0.5


def test_normal_quaternions_lay_the_splats_z_axis_on_the_normal():
    rng = np.random.default_rng(3)
    n = rng.normal(size=(200, 3))
    n[0], n[1], n[2] = [0, 0, 1], [0, 0, -1], [0, 0, -1 + 1e-12]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    R = quat_matrix(G.normal_quaternions(n))
    np.testing.assert_allclose(R[:, :, 2], n, atol=1e-9)
    np.testing.assert_allclose(np.einsum("nij,nik->njk", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)


def test_splats_on_surface_are_flat_along_the_normal():
    p = np.zeros((3, 3))
    n = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    s = G.splats_on_surface(p, n, np.array([0.1, 0.2, 0.4]), tangent=0.5, thickness=0.1, opacity=0.8)
    C = G.covariances(s["sigma"], s["quat"])
    for i in range(3):
        w, v = np.linalg.eigh(C[i])
        assert abs(abs(v[:, 0] @ n[i]) - 1) < 1e-9                          # the shortest axis is the normal
        np.testing.assert_allclose(np.sqrt(w), np.array([0.1, 1, 1]) * 0.5 * [0.1, 0.2, 0.4][i], rtol=1e-9)
    assert np.all(s["opacity"] == 0.8)
