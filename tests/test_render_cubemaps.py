"""render-cubemaps: face geometry against the OpenGL cube-map table, the splatter against a
brute-force reference, hole-free surfaces, automatic viewpoints covering a known set, the stage
outputs and the CLI."""

from __future__ import annotations

import json

import numpy as np

from pipeline import io
from pipeline.expansion.render_cubemaps import RenderCubemapsConfig, choose_viewpoints, normal_candidates
from pipeline.camera import cube_cameras, face_rotations
from pipeline.expansion.splats import knn_splat_radii, project, render_cube_map, seen_in_face, splat_cube_faces
from pipeline.scene.geometry import two_rooms


def gl_face_st(d):
    """OpenGL spec Table 8.19 (cube-map face selection): face index and (s, t) in [0,1]."""
    ax = np.argmax(np.abs(d), axis=1)
    sgn = np.sign(d[np.arange(len(d)), ax])
    face = ax * 2 + (sgn < 0)
    rx, ry, rz = d.T
    sc = np.select([face == k for k in range(6)], [-rz, rz, rx, rx, rx, -rx])
    tc = np.select([face == k for k in range(6)], [-ry, -ry, rz, -rz, -ry, -ry])
    ma = np.abs(d[np.arange(len(d)), ax])
    return face, (sc / ma + 1) / 2, (tc / ma + 1) / 2


def test_faces_follow_gl_cubemap_table():
    rot = face_rotations()
    assert np.allclose(np.linalg.det(rot), 1.0)  # proper rotations: right-handed cameras
    assert np.allclose(rot @ rot.transpose(0, 2, 1), np.eye(3))
    rng = np.random.default_rng(0)
    eye = np.array([1.0, -2.0, 0.5])
    d = rng.normal(size=(3000, 3))
    face, s, t = gl_face_st(d)
    cams = cube_cameras(eye[None], 64)
    assert cams["K"].shape == (6, 3, 3) and (cams["face"] == np.arange(6)).all()
    for f in range(6):
        m = face == f
        u, v, dep = project(eye + d[m] * 3.0, cams["K"][f], cams["world_to_camera"][f])
        assert (dep > 0).all()
        np.testing.assert_allclose(u / 64, s[m], atol=1e-12)  # columns = s
        np.testing.assert_allclose(v / 64, t[m], atol=1e-12)  # rows (file order) = t
        # depth along the view axis
        fwd = -cams["world_to_camera"][f][2, :3]
        np.testing.assert_allclose(dep, (d[m] * 3.0) @ fwd, rtol=1e-12)


def brute_splat(points, radii, K, w2c, size, near=1e-3, max_px=32.0):
    """Reference: for every pixel, among the splats whose screen disc contains the pixel centre (or
    whose centre lies in the pixel), the one whose sphere surface d − r·sqrt(1 − ρ²) is nearest
    (ties → lower index); returns (index, centre depth)."""
    idx = np.full((size, size), -1)
    z = np.full((size, size), np.inf, dtype=np.float32)  # depths compared in float32, as the kernel
    dc = np.zeros((size, size))
    u, v, d = project(points, K, w2c)
    for i in range(len(points)):
        if d[i] <= near:
            continue
        rp = min(K[0, 0] * radii[i] / d[i], max_px)
        for row in range(size):
            for col in range(size):
                rho2 = ((col + 0.5 - u[i]) ** 2 + (row + 0.5 - v[i]) ** 2) / (rp * rp)
                centre = (col == np.floor(u[i])) and (row == np.floor(v[i]))
                ze = np.float32(d[i] - radii[i] * np.sqrt(max(0.0, 1.0 - rho2)))
                if (rho2 <= 1 or centre) and (ze < z[row, col] or (ze == z[row, col] and i < idx[row, col])):
                    z[row, col] = ze
                    dc[row, col] = d[i]
                    idx[row, col] = i
    return idx, dc


def test_splatter_matches_bruteforce():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-2, 2, (50, 3))
    pts[:5] = pts[5:10]  # duplicates: ties must go to the lower index
    radii = rng.uniform(0.02, 0.4, 50)
    cams = cube_cameras(np.zeros((1, 3)), 16)
    z, idx = splat_cube_faces(pts, radii, cams["K"][0], cams["world_to_camera"], 16, 16)
    for f in range(6):
        ref, dc = brute_splat(pts, radii, cams["K"][f], cams["world_to_camera"][f], 16)
        np.testing.assert_array_equal(idx[f], ref)
        np.testing.assert_array_equal(z[f], dc.astype(np.float32))
    assert (z[idx < 0] == 0).all()


def test_plane_has_no_holes_and_exact_depth():
    rng = np.random.default_rng(2)
    n = 20000
    pts = np.stack([rng.uniform(-3, 3, n), rng.uniform(-3, 3, n), np.full(n, -2.0)], axis=1)
    cols = np.tile([0.2, 0.5, 0.8], (n, 1)).astype(np.float32)
    radii = knn_splat_radii(pts)
    faces, cams = render_cube_map(pts, cols, radii, np.zeros(3), 64)
    f = 5  # −Z face looks at the plane, which fills its frustum (|x|,|y| ≤ 2 at depth 2)
    assert faces[f, :, :, 3].all()
    assert (faces[f, :, :, 4] == 2.0).all()
    np.testing.assert_array_equal(faces[f, :, :, :3], np.broadcast_to(cols[0], (64, 64, 3)))


def seen_set(pts, cols, nrm, eye, size, tol=0.02):
    radii = knn_splat_radii(pts).astype(np.float64)
    faces, cams = render_cube_map(pts, cols, radii, eye, size, normals=nrm)
    seen = np.zeros(len(pts), bool)
    for f in range(6):
        s, _, _ = seen_in_face(pts, cams["K"][f], cams["world_to_camera"][f], faces[f, :, :, 4], faces[f, :, :, 3], tol,
                                 nrm, radii)
        seen |= s
    return seen


def test_auto_viewpoints_cover_both_rooms():
    pts, cols, pa, pb, nrm = two_rooms(20000)
    radii = knn_splat_radii(pts).astype(np.float64)
    over = pa | pb
    cfg = RenderCubemapsConfig(grid=4, coverage=0.95, max_views=6, normal_seeds=16)
    eyes, info = choose_viewpoints(pts, radii, over, cfg, nrm)
    assert len(eyes) == 2, info  # one room cannot see the other's patch
    assert {bool(e[0] < 2) for e in eyes} == {True, False}
    assert info["probe_coverage_after_each"][-1] >= 0.95
    seen = np.zeros(len(pts), bool)
    for e in eyes:
        s = seen_set(pts, cols, nrm, e, 128)
        room = pa if e[0] < 2 else pb
        assert not (s & (pb if e[0] < 2 else pa)).any()  # the wall hides the other room entirely
        assert (s & room).sum() >= 0.98 * room.sum()
        seen |= s
    assert (seen & over).sum() >= 0.95 * over.sum()
    # with a single view: exactly one room's patch is reachable
    eyes1, info1 = choose_viewpoints(pts, radii, over, RenderCubemapsConfig(grid=4, max_views=1, normal_seeds=16), nrm)
    assert len(eyes1) == 1
    frac = info1["probe_coverage_after_each"][0]
    room = pa if eyes1[0][0] < 2 else pb
    assert frac <= room.sum() / over.sum() + 1e-12 and frac >= 0.95 * room.sum() / over.sum()


def _write_cloud(path, pts, cols, nrm=None):
    n = len(pts)
    nrm = np.tile([0, 1, 0], (n, 1)) if nrm is None else nrm
    io.write_cloud(path, io.Cloud(pts.astype(np.float32), nrm.astype(np.float32), cols.astype(np.float32)))


def test_stage_outputs_and_cli(tmp_path, cli_run):
    pts, cols, pa, pb, nrm = two_rooms(12000)
    _write_cloud(tmp_path / "c.ply", pts, cols, nrm)
    out = tmp_path / "cubes"
    code, _, err = cli_run("render-cubemaps", tmp_path / "c.ply", "--out", out, "--size", "48",
                           "--viewpoints", "1.0,1,1;3,1,1.0", "--preview", tmp_path / "p.png")
    assert code == 0, err
    cams = io.read_npz(out / "cameras.npz", "pcrelight.cameras/1")
    assert cams["K"].shape == (12, 3, 3) and np.allclose(cams["eye"], [[1, 1, 1], [3, 1, 1]])
    assert list(cams["view"]) == [0] * 6 + [1] * 6 and list(cams["face"]) == list(range(6)) * 2
    assert io.image_channels(out / "face_011.exr") == ["R", "G", "B", "A", "Z"]
    img = io.read_image(out / "face_002.exr")  # view 0, +Y face: the ceiling at depth 1 m
    assert img.shape == (48, 48, 5) and img[..., 3].all()
    np.testing.assert_allclose(img[6:-6, 6:-6, 4], 1.0, rtol=1e-6)  # (the walls show at the rim)
    rep = json.loads((out / "report.json").read_text())
    assert rep["views"] == 2 and rep["viewpoint_mode"] == "config" and rep["coverage"] >= 0.95
    assert (tmp_path / "p.png").exists()
    # a run on identical input is identical
    first = io.read_image(out / "face_004.exr")
    code, _, err = cli_run("render-cubemaps", tmp_path / "c.ply", "--out", out, "--size", "48",
                           "--viewpoints", "1,1,1;3,1,1")
    np.testing.assert_array_equal(io.read_image(out / "face_004.exr"), first)


def test_no_overexposed_point_renders_nothing(tmp_path, cli_run):
    pts, cols, _, _, nrm = two_rooms(3000)
    _write_cloud(tmp_path / "c.ply", pts, cols * 0.5, nrm)
    code, _, err = cli_run("render-cubemaps", tmp_path / "c.ply", "--out", tmp_path / "o")
    assert code == 0, err
    cams = io.read_npz(tmp_path / "o" / "cameras.npz", "pcrelight.cameras/1")
    assert cams["K"].shape == (0, 3, 3) and not list((tmp_path / "o").glob("face_*.exr"))
    assert json.loads((tmp_path / "o" / "report.json").read_text())["skipped"] == "no overexposed point"


def test_cli_errors(tmp_path, cli_run):
    code, _, err = cli_run("render-cubemaps", tmp_path / "nope.ply", "--out", tmp_path / "o")
    assert code == 1 and "nope.ply" in err and err.count("\n") == 1
    _write_cloud(tmp_path / "c.ply", np.random.default_rng(0).uniform(size=(50, 3)), np.ones((50, 3)))
    code, _, err = cli_run("render-cubemaps", tmp_path / "c.ply", "--out", tmp_path / "o", "--viewpoints", "1,2")
    assert code == 2 and "--viewpoints" in err
    code, _, err = cli_run("render-cubemaps", tmp_path / "c.ply", "--out", tmp_path / "o", "--size", "2")
    assert code == 2 and "--size" in err


def test_normal_candidates_fit_a_slot():
    """Two parallel walls 1 m apart (y = 0 and y = 1): candidates p + h·n from the lower wall, h =
    0.2, 0.4, 0.8, 1.6 m; kept only where free by h/2 (and inside the box): h = 0.2 and 0.4."""
    g = np.linspace(0, 4, 41)
    x, z = np.meshgrid(g, g, indexing="ij")
    low = np.stack([x.ravel(), np.zeros(x.size), z.ravel()], axis=1)
    pts = np.concatenate([low, low + (0, 1.0, 0)])
    nrm = np.zeros_like(pts)
    nrm[: len(low), 1] = 1.0
    nrm[len(low):, 1] = -1.0
    seed = np.array([20 * 41 + 20])  # the lower wall's centre (2, 0, 2)
    c = normal_candidates(pts, nrm, seed, base=0.2, min_clear=0.05)
    np.testing.assert_allclose(c, [[2.0, 0.2, 2.0], [2.0, 0.4, 2.0]], atol=1e-12)


def test_gl_route_agrees_with_numba(gl_context):
    """The GL point-sprite route draws the same splats: the same point wins ≥ 99.9 % of the pixels
    (GL resolves near-ties on a 24-bit depth buffer), with the same centre depth there (to float32
rounding: the shader computes in float32 from float32 inputs)."""
    from pipeline.expansion.splats import splat_cube_faces_gl

    pts, cols, _, _, _ = two_rooms(8000)
    radii = knn_splat_radii(pts).astype(np.float64)
    cams = cube_cameras(np.array([[1.0, 1.0, 1.0], [3.0, 0.7, 1.2]]), 64)
    z1, i1 = splat_cube_faces(pts, radii, cams["K"][0], cams["world_to_camera"], 64, 64)
    z2, i2 = splat_cube_faces_gl(pts, radii, cams["K"][0], cams["world_to_camera"], 64, 64, ctx=gl_context)
    assert (i1 == i2).mean() >= 0.999 and (i2 >= 0).all()
    same = i1 == i2
    np.testing.assert_allclose(z2[same], z1[same], rtol=1e-6)  # GL: float32 arithmetic; numba: float64 rounded


def test_stray_points_do_not_move_the_viewpoints(tmp_path, cli_run):
    """10 stray points 50 m away (a scanner's strays) stretch the bounding box the viewpoint search
    fills: without outlier removal the chosen eye lands outside the rooms; with it (the default) the
    10 strays are flagged, logged and left out of the box, and the eyes are inside, one per room."""
    from pipeline.expansion.render_cubemaps import run_render_cubemaps
    from pipeline.expansion.splats import statistical_inliers

    pts, cols, pa, pb, nrm = two_rooms(20000)
    rng = np.random.default_rng(1)
    d = rng.normal(size=(10, 3))
    stray = np.array([2.0, 1.0, 1.0]) + 50.0 * d / np.linalg.norm(d, axis=1, keepdims=True)
    P = np.concatenate([pts, stray])
    keep = statistical_inliers(P, 20, 10.0)
    assert not keep[-10:].any() and keep[:-10].mean() > 0.99
    _write_cloud(tmp_path / "c.ply", P, np.concatenate([cols, np.full((10, 3), 0.3)]),
                 np.concatenate([nrm, np.tile([0, 1, 0], (10, 1))]))
    inside = lambda e: bool(((np.asarray(e) > 0) & (np.asarray(e) < (4, 2, 2))).all())  # noqa: E731
    rep = run_render_cubemaps(tmp_path / "c.ply", tmp_path / "a", RenderCubemapsConfig(
        size=48, grid=4, normal_seeds=16, outlier_neighbors=0))
    assert not all(inside(e) for e in rep["viewpoints"])  # the failure the removal prevents
    code, _, err = cli_run("render-cubemaps", tmp_path / "c.ply", "--out", tmp_path / "b", "--size", "48",
                           "--grid", "4", "--normal-seeds", "16")
    assert code == 0, err
    rep = json.loads((tmp_path / "b" / "report.json").read_text())
    assert rep["outliers"]["removed"] == 10 and "10 of 20010 points (0 overexposed) left out" in err
    assert rep["views"] == 2 and all(inside(e) for e in rep["viewpoints"])
    assert {e[0] < 2 for e in rep["viewpoints"]} == {True, False} and rep["coverage"] >= 0.95


def test_coverage_below_target_is_a_warning(tmp_path, cli_run):
    pts, cols, pa, pb, nrm = two_rooms(12000)
    _write_cloud(tmp_path / "c.ply", pts, cols, nrm)
    code, _, err = cli_run("render-cubemaps", tmp_path / "c.ply", "--out", tmp_path / "o", "--size", "32",
                           "--viewpoints", "1,1,1")  # one room only: about half the overexposed points
    assert code == 0, err
    assert "WARNING: only" in err and "of the overexposed points are seen" in err


def test_statistical_inliers_are_open3ds():
    """statistical_inliers (SciPy k-d tree, one query shared with the splat radii) keeps exactly the points Open3D's
    remove_statistical_outlier keeps — strays, an all-duplicate cluster (mean distance 0: Open3D drops it) and
    several σ — and the radii from the shared query are the same as from their own."""
    import open3d as o3d

    from pipeline.expansion.splats import knn_distances, statistical_inliers

    rng = np.random.default_rng(3)
    P = np.concatenate([rng.random((30000, 3)) * (4, 2, 2), 40 * rng.normal(size=(15, 3)),
                        np.repeat(rng.random((2, 3)), 25, axis=0), np.repeat(rng.random((1, 3)), 3, axis=0)])
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    d = knn_distances(P, 21)
    for nb, sr in ((20, 10.0), (20, 2.0), (6, 1.0)):
        _, ind = pc.remove_statistical_outlier(nb_neighbors=nb, std_ratio=sr)
        ref = np.zeros(len(P), dtype=bool)
        ref[np.asarray(ind)] = True
        assert np.array_equal(statistical_inliers(P, nb, sr), ref), (nb, sr)
        assert np.array_equal(statistical_inliers(P, nb, sr, dists=d), ref), (nb, sr)
    keep = statistical_inliers(P, 20, 10.0)
    assert keep[30000:30015].sum() < 5 and not keep[30015:30065].any()   # strays; duplicates (mean distance 0)
    assert np.array_equal(knn_splat_radii(P, dists=d), knn_splat_radii(P))
    q = np.arange(0, len(P), 5)
    assert np.array_equal(knn_splat_radii(P, query=q, dists=knn_distances(P, 17, q)), knn_splat_radii(P, query=q))
