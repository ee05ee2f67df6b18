"""pipeline/camera.py: the camera model table (pinhole, equirect, fisheye) and its conventions."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline import camera


def _params(model: str, size) -> dict:
    return {"pinhole": {"K": camera.intrinsics(60.0, size)}, "equirect": {}, "fisheye": {"fov_deg": 180.0}}[model]


@pytest.mark.parametrize("model", sorted(camera.MODELS))
def test_every_model_projects_its_own_pixel_centres_back(model):
    size = (40, 20) if model == "equirect" else (36, 24)
    p = _params(model, size)
    d = camera.MODELS[model].directions(size, **p)
    assert d.shape == (size[1], size[0], 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    u, v, ok = camera.MODELS[model].project(d.reshape(-1, 3), size, **p)
    gu, gv = np.meshgrid(np.arange(size[0]) + 0.5, np.arange(size[1]) + 0.5)
    inside = ok.reshape(size[1], size[0])
    if model == "fisheye":       # the corners lie outside the 180° circle
        r = np.hypot(gu - size[0] / 2, gv - size[1] / 2)
        assert np.array_equal(inside, r <= min(size) / 2)
    else:
        assert inside.all()
    np.testing.assert_allclose(u.reshape(inside.shape)[inside], gu[inside], atol=1e-9)
    np.testing.assert_allclose(v.reshape(inside.shape)[inside], gv[inside], atol=1e-9)


def test_the_models_agree_on_the_axes():
    """OpenCV axes for every model: the image centre looks along +z, the top row towards −y, the right
    column towards +x (equirect: the centre column is +z, a quarter turn right is +x, row 0 the zenith −y)."""
    dirs = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    u, v, ok = camera.equirect_project(dirs, (360, 180))
    np.testing.assert_allclose(u[:2], [180.0, 270.0])
    np.testing.assert_allclose(v, [90.0, 90.0, 0.0])
    u, v, ok = camera.fisheye_project(dirs, (100, 100), 180.0)
    np.testing.assert_allclose([u[0], v[0]], [50.0, 50.0])
    np.testing.assert_allclose([u[1], v[1], u[2], v[2]], [100.0, 50.0, 50.0, 0.0])
    assert ok[0] and ok[2] and not ok[1]          # u = 100 is the right edge: outside the image
    K = camera.intrinsics(90.0, (100, 100))
    u, v, ok = camera.pinhole_project(np.array([[0.0, 0.0, 1.0], [0.6, -0.6, 1.0], [0.0, 0.0, -1.0]]), (100, 100), K)
    np.testing.assert_allclose([u[0], v[0], u[1], v[1]], [50.0, 50.0, 80.0, 20.0])
    assert ok.tolist() == [True, True, False]


def test_pinhole_model_is_the_photo_rays_and_projection():
    """The pinhole model's world rays are make-scene's camera_rays; projecting a world point along one
    lands on that pixel's centre."""
    size = (16, 12)
    M = camera.look_at((0.3, 1.2, -0.4), (2.0, 0.9, 1.0), (0.0, 1.0, 0.0))
    K = camera.intrinsics(55.0, size)
    o, d = camera.camera_rays(M, K, size)
    eye, dirs = camera.world_rays("pinhole", size, M, K=K)
    np.testing.assert_allclose(eye, o[0], atol=1e-12)
    np.testing.assert_allclose(dirs.reshape(-1, 3), d, atol=1e-12)
    u, v, dist, ok = camera.project_points("pinhole", o + 2.5 * d, size, M, K=K)
    gu, gv = np.meshgrid(np.arange(size[0]) + 0.5, np.arange(size[1]) + 0.5)
    assert ok.all()
    np.testing.assert_allclose(u, gu.reshape(-1), atol=1e-9)
    np.testing.assert_allclose(v, gv.reshape(-1), atol=1e-9)
    np.testing.assert_allclose(dist, 2.5, atol=1e-9)


def test_look_rotation_looks_along_forward_with_world_up_on_top():
    f = np.array([0.3, -0.2, 0.9])
    R = camera.look_rotation(f)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R[2], f / np.linalg.norm(f), atol=1e-12)   # camera +z = forward
    assert R[1] @ np.array([0.0, 1.0, 0.0]) < 0                            # camera +y (down) points down


def test_cube_cameras_look_along_the_gl_face_table():
    cams = camera.cube_cameras(np.array([[1.0, 2.0, 3.0]]), 8)
    fwd = -cams["world_to_camera"][:, 2, :3]            # GL cameras look down their −z
    np.testing.assert_allclose(fwd, [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], atol=1e-12)
    assert len(camera.FACE_NAMES) == 6
