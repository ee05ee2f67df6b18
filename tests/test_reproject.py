"""reproject: a synthetic cloud whose faces are known exactly gets exactly the face values back,
occluded points get nothing, averaging rules (plain / 1/(Q+ε) / Q > t_h dropped), lum vs rgb
transfer, the per-point operators, pass-through, and errors through the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline import io
from pipeline.expansion import itmo
from pipeline.camera import cube_cameras

S = 24  # face size


def pixel_points(cams, f, rows, cols, depth):
    """World points that project exactly on pixel centres (rows, cols) of face f at depth d."""
    K = cams["K"][f]
    m = cams["world_to_camera"][f]
    x = (cols + 0.5 - K[0, 2]) / K[0, 0] * depth
    y = (rows + 0.5 - K[1, 2]) / K[1, 1] * depth
    cam = np.stack([x, y, -depth], axis=1)
    r, t = m[:3, :3], m[:3, 3]
    return (cam - t) @ r  # R^T (c - t)


VIS = {"splat_k": np.int32(16), "splat_scale": np.float64(1.25), "backface_cull": np.int32(0), "facing_test": np.int32(1),
       "depth_tol": np.float64(0.02), "radius_tol": np.float64(0.0)}


def write_scene(tmp, cams, cover, depth, hdr, q, method="pmatch", scale=1.0, points=None, colors=None, normals=None):
    """Faces + cameras.npz (visibility: relative tolerance 2 %, no radius term, facing test)
    and the LDR cloud; normals default to facing the first eye."""
    cdir, rdir = tmp / "cubes", tmp / "hdr"
    io.write_npz(cdir / "cameras.npz", "pcrelight.cameras/1", **cams, **VIS)
    for f in range(len(cams["K"])):
        ldr_face = np.zeros((S, S, 5), np.float32)
        ldr_face[..., 3] = cover[f]
        ldr_face[..., 4] = depth[f]
        io.write_image(cdir / f"face_{f:03d}.exr", ldr_face, channels=["R", "G", "B", "A", "Z"])
        io.write_image(rdir / f"face_{f:03d}.exr", np.concatenate([hdr[f], q[f][..., None]], axis=2).astype(np.float32),
                       channels=["R", "G", "B", "Q"])
    io.write_npz(rdir / "renderings.npz", "pcrelight.renderings/1", method=np.asarray(method),
                 scale=np.float64(scale), count=np.int32(len(cams["K"])))
    if points is not None:
        if normals is None:
            normals = cams["eye"][0] - points
            normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        io.write_cloud(tmp / "ldr.ply", io.Cloud(points.astype(np.float32), normals.astype(np.float32),
                                                 colors.astype(np.float32)))
    return cdir, rdir


@pytest.fixture
def exact_scene(tmp_path):
    rng = np.random.default_rng(0)
    cams = cube_cameras(np.array([[0.3, -0.2, 0.1]]), S)
    cover = np.zeros((6, S, S), np.float32)
    depth = np.zeros((6, S, S), np.float32)
    hdr = rng.uniform(0, 50, (6, S, S, 3)).astype(np.float32)
    q = rng.uniform(0, 0.5, (6, S, S)).astype(np.float32)
    pts, front, behind, expect, qexp = [], [], [], [], []
    for f in range(6):
        pix = rng.choice(S * S, 40, replace=False)
        rows, cols = pix // S, pix % S
        d = rng.uniform(1.0, 3.0, 40)
        depth[f, rows, cols] = d
        cover[f, rows, cols] = 1
        p_front = pixel_points(cams, f, rows[:30], cols[:30], d[:30])
        # the same rays, 1.5× farther: hidden behind the front points
        p_back = pixel_points(cams, f, rows[:10], cols[:10], d[:10] * 1.5)
        n0 = sum(len(a) for a in pts)
        pts += [p_front, p_back]
        front += list(range(n0, n0 + 30))
        behind += list(range(n0 + 30, n0 + 40))
        expect.append(hdr[f, rows[:30], cols[:30]])
        qexp.append(q[f, rows[:30], cols[:30]])
    pts = np.concatenate(pts)
    colors = np.full((len(pts), 3), 0.97)
    colors[front[::7]] = (0.5, 0.6, 0.7)  # well exposed: must keep LDR even though visible
    return dict(tmp=tmp_path, cams=cams, cover=cover, depth=depth, hdr=hdr, q=q, pts=pts, colors=colors,
                front=np.array(front), behind=np.array(behind), expect=np.concatenate(expect), qexp=np.concatenate(qexp))


def test_exact_face_values_and_occlusion(exact_scene, cli_run):
    s = exact_scene
    cdir, rdir = write_scene(s["tmp"], s["cams"], s["cover"], s["depth"], s["hdr"], s["q"], "landis", 2.5,
                             s["pts"], s["colors"])
    out = s["tmp"] / "proj.ply"
    code, _, err = cli_run("reproject", s["tmp"] / "ldr.ply", cdir, rdir, "--out", out, "--transfer", "rgb",
                           "--no-ldr-floor", "--preview", s["tmp"] / "p.png")
    assert code == 0, err
    c = io.read_cloud(out)
    over = np.ones(len(s["pts"]), bool)
    over[s["front"][::7]] = False
    fr = s["front"]
    sel = over[fr]
    np.testing.assert_array_equal(c.colors[fr[sel]], (s["expect"][sel].astype(np.float64) * 2.5).astype(np.float32))
    assert (c.source[fr[sel]] == 1).all() and (c.valid[fr] == 1).all() and (c.quality[fr[sel]] == s["qexp"][sel]).all()
    np.testing.assert_array_equal(c.colors[fr[~sel]], s["colors"][fr[~sel]].astype(np.float32))
    assert (c.source[fr[~sel]] == 0).all()
    b = s["behind"]
    assert (c.valid[b] == 0).all() and (c.source[b] == 0).all() and (c.quality[b] == np.float32(1e30)).all()
    np.testing.assert_array_equal(c.colors[b], np.float32(0.97))
    rep = json.loads((s["tmp"] / "proj.json").read_text())
    assert rep["projected"] == int(sel.sum()) and rep["invalid"] == len(b) and rep["invalid_unseen"] == len(b)
    assert rep["weighting"] == "plain"


def test_lum_transfer_keeps_chromaticity(exact_scene):
    from pipeline.expansion.reproject import ReprojectConfig, run_reproject

    s = exact_scene
    s["colors"][:] = (0.99, 0.93, 0.96)
    cdir, rdir = write_scene(s["tmp"], s["cams"], s["cover"], s["depth"], s["hdr"], s["q"], "rhee", 1.0,
                             s["pts"], s["colors"])
    run_reproject(s["tmp"] / "ldr.ply", cdir, rdir, s["tmp"] / "o.ply", ReprojectConfig(transfer="lum", ldr_floor=False))
    c = io.read_cloud(s["tmp"] / "o.ply")
    ldr = np.float32(s["colors"][0])
    y_face = io.luminance(s["expect"]).astype(np.float64)
    want = ldr.astype(np.float64)[None] * (y_face / float(io.luminance(ldr[None])[0]))[:, None]
    np.testing.assert_allclose(c.colors[s["front"]], want, rtol=1e-5)


def _two_same_faces(tmp, values, qs, method, t_h=1.0, floor=True):
    """One camera twice (F = 2): a point on pixel (5, 7) of face 0 sees both copies."""
    from pipeline.expansion.reproject import ReprojectConfig, run_reproject

    cams1 = cube_cameras(np.zeros((1, 3)), S)
    cams = {k: (np.concatenate([v[:1], v[:1]]) if k != "eye" else v) for k, v in cams1.items()}
    cams["view"] = np.zeros(2, np.int32)
    cams["face"] = np.zeros(2, np.int32)
    p = pixel_points(cams, 0, np.array([5]), np.array([7]), np.array([2.0]))
    depth = np.zeros((2, S, S), np.float32)
    depth[:, 5, 7] = 2.0
    cover = (depth > 0).astype(np.float32)
    hdr = np.zeros((2, S, S, 3), np.float32)
    q = np.zeros((2, S, S), np.float32)
    for f in range(2):
        hdr[f, 5, 7] = values[f]
        q[f, 5, 7] = qs[f]
    cdir, rdir = write_scene(tmp, cams, cover, depth, hdr, q, method, 1.0, p, np.full((1, 3), 0.95))
    rep = run_reproject(tmp / "ldr.ply", cdir, rdir, tmp / "o.ply", ReprojectConfig(transfer="rgb", t_h=t_h, ldr_floor=floor))
    return io.read_cloud(tmp / "o.ply"), rep


def test_quality_weighted_mean_for_patchmatch(tmp_path):
    v = np.array([[2.0, 4.0, 6.0], [10.0, 20.0, 30.0]], np.float32)
    c, rep = _two_same_faces(tmp_path, v, [0.01, 0.25], "pmatch")
    w = 1.0 / (np.array([0.01, 0.25]) + 1e-4)
    np.testing.assert_allclose(c.colors[0], (w[:, None] * v).sum(0) / w.sum(), rtol=1e-6)
    np.testing.assert_allclose(c.quality[0], (w * [0.01, 0.25]).sum() / w.sum(), rtol=1e-6)
    assert rep["samples_kept"] == 2


def test_plain_mean_for_operators(tmp_path):
    v = np.array([[2.0, 4.0, 6.0], [10.0, 20.0, 30.0]], np.float32)
    c, _ = _two_same_faces(tmp_path, v, [0.0, 0.0], "banterle")
    np.testing.assert_allclose(c.colors[0], v.mean(0), rtol=1e-7)


def test_samples_above_t_h_dropped(tmp_path):
    v = np.array([[2.0, 4.0, 6.0], [10.0, 20.0, 30.0]], np.float32)
    c, _ = _two_same_faces(tmp_path, v, [0.5, 1.5], "pmatch")
    np.testing.assert_allclose(c.colors[0], v[0], rtol=1e-7)
    c, rep = _two_same_faces(tmp_path, v, [1.2, 1.5], "pmatch")
    assert c.valid[0] == 0 and c.quality[0] == np.float32(1.2) and rep["invalid_all_dropped"] == 1


def test_per_point_operator_and_passthrough(tmp_path, cli_run):
    rng = np.random.default_rng(3)
    pts = rng.uniform(0, 1, (400, 3))
    cols = rng.uniform(0, 1, (400, 3))
    cols[:50] = (0.98, 0.97, 0.99)
    io.write_cloud(tmp_path / "c.ply", io.Cloud(pts.astype(np.float32), np.tile([0, 1, 0], (400, 1)).astype(np.float32),
                                                cols.astype(np.float32)))
    code, _, err = cli_run("reproject", tmp_path / "c.ply", "--method", "landis-pc", "--peak", "300",
                           "--out", tmp_path / "o.ply")
    assert code == 0, err
    c = io.read_cloud(tmp_path / "o.ply")
    over = io.luminance(c.colors * 0 + cols.astype(np.float32)) > 0.9
    np.testing.assert_allclose(c.colors[over], itmo.landis(cols.astype(np.float32)[over], 300.0), rtol=1e-6)
    np.testing.assert_array_equal(c.colors[~over], cols.astype(np.float32)[~over])
    assert (c.source[over] == 1).all() and (c.valid == 1).all()
    # no overexposed point: passes through, said so
    io.write_cloud(tmp_path / "d.ply", io.Cloud(pts.astype(np.float32), np.tile([0, 1, 0], (400, 1)).astype(np.float32),
                                                (cols * 0.5).astype(np.float32)))
    code, _, err = cli_run("reproject", tmp_path / "d.ply", tmp_path / "none", tmp_path / "none", "--out", tmp_path / "p.ply")
    assert code == 0, err
    assert json.loads((tmp_path / "p.json").read_text())["skipped"] == "no overexposed point"
    np.testing.assert_array_equal(io.read_cloud(tmp_path / "p.ply").colors, (cols * 0.5).astype(np.float32))


def test_cli_errors(exact_scene, cli_run):
    s = exact_scene
    cdir, rdir = write_scene(s["tmp"], s["cams"], s["cover"], s["depth"], s["hdr"], s["q"], "pmatch", 1.0,
                             s["pts"], s["colors"])
    io.write_npz(rdir / "renderings.npz", "pcrelight.renderings/1", method=np.asarray("pmatch"),
                 scale=np.float64(1.0), count=np.int32(5))
    code, _, err = cli_run("reproject", s["tmp"] / "ldr.ply", cdir, rdir, "--out", s["tmp"] / "o.ply")
    assert code == 1 and "renderings.npz" in err and "count 5" in err
    code, _, err = cli_run("reproject", s["tmp"] / "ldr.ply", cdir, s["tmp"] / "missing", "--out", s["tmp"] / "o.ply")
    assert code == 1 and "missing" in err
    code, _, err = cli_run("reproject", s["tmp"] / "ldr.ply", "--method", "landis-pc", "--out", s["tmp"] / "o.ply")
    assert code == 2 and "--peak" in err
    code, _, err = cli_run("reproject", s["tmp"] / "ldr.ply", cdir, rdir, "--out", s["tmp"] / "o.ply", "--min-photo-share", "2")
    assert code == 2 and "photo" in err and "share" in err and not (s["tmp"] / "o.ply").exists()
    code, _, err = cli_run("reproject", s["tmp"] / "ldr.ply", cdir, rdir, "--out", s["tmp"] / "o.ply", "--unseen", "guess")
    assert code == 2 and "unseen" in err and not (s["tmp"] / "o.ply").exists()


def test_backfacing_points_get_nothing(exact_scene):
    from pipeline.expansion.reproject import ReprojectConfig, run_reproject

    s = exact_scene
    nrm = s["cams"]["eye"][0] - s["pts"]
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    away = s["front"][1::3]
    nrm[away] *= -1.0  # these surfaces face away from the eye: not seen
    cdir, rdir = write_scene(s["tmp"], s["cams"], s["cover"], s["depth"], s["hdr"], s["q"], "landis", 1.0,
                             s["pts"], s["colors"], nrm)
    run_reproject(s["tmp"] / "ldr.ply", cdir, rdir, s["tmp"] / "o.ply", ReprojectConfig(transfer="rgb"))
    c = io.read_cloud(s["tmp"] / "o.ply")
    over = io.luminance(s["colors"][away].astype(np.float32)) > 0.9
    assert (c.valid[away[over]] == 0).all() and (c.quality[away[over]] == np.float32(1e30)).all()


def test_ldr_floor(tmp_path):
    """Samples below the LDR value (0.95): raised per channel to it (rgb), or kept with --no-ldr-floor."""
    v = np.array([[0.5, 2.0, 0.1], [0.5, 2.0, 0.1]], np.float32)
    c, rep = _two_same_faces(tmp_path, v, [0.0, 0.0], "rhee")
    np.testing.assert_allclose(c.colors[0], [0.95, 2.0, 0.95], rtol=1e-7)
    assert rep["raised_to_ldr"] == 1
    c, rep = _two_same_faces(tmp_path, v, [0.0, 0.0], "rhee", floor=False)
    np.testing.assert_allclose(c.colors[0], v[0], rtol=1e-7)


def test_photo_samples_from_a_registered_camera():
    """Direct transfer (issue 14): points seen by the registered photo take α × the photo at their
    projection (bilinear: exact on a photo linear in the pixel coordinates), points hidden behind a
    nearer surface or facing away get nothing."""
    from pipeline.camera import intrinsics, look_rotation
    from pipeline.expansion.splats import knn_splat_radii
    from pipeline.expansion.reproject import photo_samples

    rng = np.random.default_rng(3)
    wall = np.c_[rng.uniform(-3, 3, 20000), rng.uniform(-2, 2, 20000), np.full(20000, -4.0)]   # faces +z
    occ = np.c_[rng.uniform(-0.5, 0.5, 3000), rng.uniform(-0.5, 0.5, 3000), np.full(3000, -2.0)]
    pts = np.vstack([wall, occ])
    nrm = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    nrm[:500] *= -1                                                   # the first 500 wall points face away
    w, h = 96, 64
    K, R = intrinsics(60.0, (w, h)), look_rotation(np.array([0.0, 0.0, -1.0]))
    w2c = np.eye(4)
    w2c[:3, :3] = R                                                   # camera at the origin
    jj, ii = np.mgrid[0:h, 0:w]
    photo = np.stack([1 + 0.1 * ii, 2 + 0.05 * jj, 3 + 0.01 * (ii + jj)], -1).astype(np.float64)
    query = np.arange(len(wall))
    seen, val = photo_samples(pts, nrm, knn_splat_radii(pts), query, photo, K, w2c, alpha=0.5)
    c = wall @ R.T
    u, v = c[:, 0] / c[:, 2] * K[0, 0] + K[0, 2], c[:, 1] / c[:, 2] * K[1, 1] + K[1, 2]
    inside = (u > 2) & (u < w - 2) & (v > 2) & (v < h - 2)
    hidden = (np.abs(wall[:, 0]) < 0.9) & (np.abs(wall[:, 1]) < 0.9)      # behind the occluder (half-size 0.5 m at 2 m → 1 m at 4 m)
    clear = (np.abs(wall[:, 0]) > 1.2) | (np.abs(wall[:, 1]) > 1.2)
    facing = np.arange(len(wall)) >= 500
    assert not seen[~facing].any()
    assert not seen[hidden].any()
    ok = inside & clear & facing
    assert ok.sum() > 3000 and seen[ok].mean() > 0.99
    s = ok & seen
    x, y = u[s] - 0.5, v[s] - 0.5
    expect = 0.5 * np.stack([1 + 0.1 * x, 2 + 0.05 * y, 3 + 0.01 * (x + y)], -1)
    assert np.allclose(val[s], expect, rtol=1e-9, atol=1e-9)
    assert (val[~seen] == 0).all()


@pytest.mark.parametrize("unseen", ["lookalike", "ldr", "poisson", "calibrated"])
def test_unseen_points_of_a_registered_photo(exact_scene, unseen, monkeypatch):
    """--unseen: with a registered photo (exposure.npz holds its camera, here the eye of the cube map
    looking along face 0 with a 60° field of view, a constant photo of 10 at α = 0.5), the overexposed
    points it sees take α × photo = 5 in every mode; the others take the faces' look-alike samples
    (lookalike), keep their LDR value with source 0 (ldr), or are left invalid to poisson (poisson)."""
    from pipeline.expansion import reproject
    from pipeline.camera import intrinsics
    from pipeline.expansion.reproject import ReprojectConfig, run_reproject

    monkeypatch.setattr(reproject, "CALIBRATE_MIN_PAIRS", 1)    # the photo sees few points with a look-alike here
    s = exact_scene
    cdir, rdir = write_scene(s["tmp"], s["cams"], s["cover"], s["depth"], s["hdr"], s["q"], "pmatch", 1.0,
                             s["pts"], s["colors"])
    w2c = s["cams"]["world_to_camera"][0].astype(np.float64).copy()
    w2c[2] *= -1                                   # the face looks along −z; an OpenCV camera along +z
    io.write_image(s["tmp"] / "photo.exr", np.full((64, 64, 3), 10.0, np.float32))
    t = np.zeros(1)
    io.write_npz(s["tmp"] / "exposure.npz", "pcrelight.exposure/1", alpha=np.float64(0.5), log2_alpha=np.float64(-1.0),
                 distance=np.float64(0.0), tried_log2_alpha=t, tried_distance=t, tried_phase=np.zeros(1, np.int32),
                 cloud_hist=t, photo_hist=t, hist_space=np.asarray("linear"), iterations=np.int32(1),
                 photo_K=intrinsics(60.0, (64, 64)), photo_world_to_camera=w2c)
    rep = run_reproject(s["tmp"] / "ldr.ply", cdir, rdir, s["tmp"] / "o.ply", ReprojectConfig(transfer="rgb", unseen=unseen),
                        photo=s["tmp"] / "photo.exr", exposure=s["tmp"] / "exposure.npz")
    c = io.read_cloud(s["tmp"] / "o.ply")
    fr = s["front"]
    over = np.ones(len(s["pts"]), bool)
    over[fr[::7]] = False
    from_photo = np.all(np.isclose(c.colors, 5.0, rtol=1e-6), axis=1)
    assert 0 < from_photo.sum() == rep["from_photo"] < over.sum() and not from_photo[~over].any()
    in_face0 = np.zeros(len(s["pts"]), bool)
    in_face0[:40] = True                                  # face 0's points come first in the fixture
    assert not from_photo[~in_face0].any()
    other = np.zeros(len(s["pts"]), bool)
    other[fr] = True
    other &= over & ~from_photo                          # overexposed, seen by a face, not by the photo
    assert other.sum() > 100
    if unseen == "lookalike":
        assert (c.source[other] == 1).all() and (c.valid[other] == 1).all() and not np.isclose(c.colors[other], 0.97).all()
    elif unseen == "calibrated":    # the look-alikes × the median photo / look-alike ratio of the seen points
        la = run_reproject(s["tmp"] / "ldr.ply", cdir, rdir, s["tmp"] / "la.ply", ReprojectConfig(transfer="rgb", unseen="lookalike"),
                           photo=s["tmp"] / "photo.exr", exposure=s["tmp"] / "exposure.npz")
        assert la["from_photo"] == rep["from_photo"]
        cl = io.read_cloud(s["tmp"] / "la.ply")
        k = rep["calibration"]["correction_global"]
        assert rep["calibration"]["pairs"] >= 1 and k != pytest.approx(1.0, abs=1e-3)
        assert len(rep["calibration"]["clusters"]) == 1          # every LDR colour is 0.97: one region
        np.testing.assert_allclose(c.colors[other], np.maximum(cl.colors[other].astype(np.float64) * k, 0.97), rtol=1e-5)
        assert (c.source[other] == 1).all() and (c.valid[other] == 1).all()
    elif unseen == "ldr":
        np.testing.assert_array_equal(c.colors[other], np.float32(0.97))
        assert (c.source[other] == 0).all() and (c.valid[other] == 1).all() and rep["kept_ldr_unseen"] >= other.sum()
    else:
        assert (c.valid[other] == 0).all() and rep["invalid_unseen_by_photo"] == other.sum()
        # their look-alike samples unused: their LDR colour and no dropped sample, as a point no face saw
        np.testing.assert_array_equal(c.colors[other], np.float32(0.97))
        assert (c.quality[other] == np.float32(1e30)).all()
    assert (c.source[from_photo] == 1).all() and (c.valid[from_photo] == 1).all()
    # the photo alone (no faces: the planner's skip of render-cubemaps and patchmatch) gives the same bytes, except
    # with lookalike, which needs the faces
    from pipeline.errors import ConfigError

    cfg = ReprojectConfig(transfer="rgb", unseen=unseen)
    if unseen in ("lookalike", "calibrated"):
        with pytest.raises(ConfigError, match="CUBEMAPS and RENDERINGS"):
            run_reproject(s["tmp"] / "ldr.ply", None, None, s["tmp"] / "p.ply", cfg, photo=s["tmp"] / "photo.exr",
                          exposure=s["tmp"] / "exposure.npz")
    else:
        alone = run_reproject(s["tmp"] / "ldr.ply", None, None, s["tmp"] / "p.ply", cfg, photo=s["tmp"] / "photo.exr",
                              exposure=s["tmp"] / "exposure.npz")
        assert alone["faces"] == 0 and alone["from_photo"] == rep["from_photo"]
        assert (s["tmp"] / "p.ply").read_bytes() == (s["tmp"] / "o.ply").read_bytes()


def test_photo_samples_isolated_points_read_the_local_peak():
    """A lamp below the point spacing spans a pixel or two of the photo, and the registered pose is
    off by about one: three points of a 4 cm lamp 0.3 m before a 5 cm grid wall are flagged isolated
    (shrink_isolated: splat radius > 2 × their neighbours' median) and read the brightest pixel of the
    3×3 around their projection (the lamp's pixel, one to the side); the wall's points and unflagged
    reads stay bilinear."""
    from pipeline.camera import intrinsics, look_rotation
    from pipeline.expansion.splats import knn_splat_radii, shrink_isolated
    from pipeline.expansion.reproject import photo_samples

    x, y = np.meshgrid(np.arange(-40, 41) * 0.05, np.arange(-30, 31) * 0.05, indexing="ij")
    wall = np.c_[x.ravel(), y.ravel(), np.full(x.size, -4.0)]
    lamp = np.array([[0.0, 0.0, -3.7], [0.02, 0.0, -3.7], [0.0, 0.02, -3.7]])
    pts = np.vstack([wall, lamp])
    nrm = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    r = knn_splat_radii(pts).astype(np.float64)
    riso, n_iso = shrink_isolated(pts, r, 2.0)
    iso = riso < r
    assert n_iso == 3 and iso[-3:].all()
    w, h = 96, 64
    K, R = intrinsics(60.0, (w, h)), look_rotation(np.array([0.0, 0.0, -1.0]))
    w2c = np.eye(4)
    w2c[:3, :3] = R
    photo = np.full((h, w, 3), 2.0)
    c = lamp @ R.T
    u, v = c[:, 0] / c[:, 2] * K[0, 0] + K[0, 2], c[:, 1] / c[:, 2] * K[1, 1] + K[1, 2]
    photo[int(np.floor(v[0])), int(np.floor(u[0])) + 1] = 500.0         # the lamp's pixel, one to the right
    q = np.arange(len(pts))
    seen, val = photo_samples(pts, nrm, riso, q, photo, K, w2c, alpha=0.5, isolated=iso)
    assert seen[-3:].all()
    np.testing.assert_allclose(val[-3:], 250.0)
    wall_seen = seen[:-3] & ~iso[:-3]
    assert wall_seen.sum() > 3000
    far = wall_seen & (np.hypot(wall[:, 0], wall[:, 1]) > 0.5)
    np.testing.assert_allclose(val[:-3][far], 1.0)
    _, plain = photo_samples(pts, nrm, riso, q, photo, K, w2c, alpha=0.5)
    assert (plain[-3:, 0] < 250.0).all()


def test_several_photos_weighted_by_their_registration(exact_scene):
    """A set in exposure.npz (issue 25): two registered photos with the same camera (the one of
    test_unseen_points_of_a_registered_photo), photo 1 constant 10 at α·k = 0.5 (quality 0.9), photo 2 constant 40 at
    α·k = 0.2 (quality 0.3), and a dropped third: every point they see takes (0.9·5 + 0.3·8) / 1.2 = 5.75; the report
    names each photo's overexposed points and the unseen points' share of the estimated flux."""
    from pipeline.camera import intrinsics
    from pipeline.expansion.photo_set import PhotoCam, set_keys
    from pipeline.expansion.reproject import ReprojectConfig, run_reproject

    s = exact_scene
    cdir, rdir = write_scene(s["tmp"], s["cams"], s["cover"], s["depth"], s["hdr"], s["q"], "pmatch", 1.0,
                             s["pts"], s["colors"])
    w2c = s["cams"]["world_to_camera"][0].astype(np.float64).copy()
    w2c[2] *= -1
    K = intrinsics(60.0, (64, 64))
    for name, v in (("p1", 10.0), ("p2", 40.0), ("p3", 1000.0)):
        io.write_image(s["tmp"] / f"{name}.exr", np.full((64, 64, 3), v, np.float32))
    cams = [PhotoCam(s["tmp"] / "p1.exr", "pinhole", (64, 64), w2c, K, 60.0, True, 0.9, True, 1.0, 0.5),
            PhotoCam(s["tmp"] / "p2.exr", "pinhole", (64, 64), w2c, K, 60.0, True, 0.3, True, 0.4, 0.2),
            PhotoCam(s["tmp"] / "p3.exr", "pinhole", (64, 64), w2c, K, 60.0, True, 0.2, False, 1.0, 0.1)]
    t = np.zeros(1)
    io.write_npz(s["tmp"] / "exposure.npz", "pcrelight.exposure/1", alpha=np.float64(0.5), log2_alpha=np.float64(-1.0),
                 distance=np.float64(0.0), tried_log2_alpha=t, tried_distance=t, tried_phase=np.zeros(1, np.int32),
                 cloud_hist=t, photo_hist=t, hist_space=np.asarray("linear"), iterations=np.int32(1),
                 **set_keys(cams, s["tmp"]))
    rep = run_reproject(s["tmp"] / "ldr.ply", cdir, rdir, s["tmp"] / "o.ply", ReprojectConfig(transfer="rgb", unseen="ldr"),
                        photo=s["tmp"] / "p1.exr", exposure=s["tmp"] / "exposure.npz")
    c = io.read_cloud(s["tmp"] / "o.ply")
    got = np.all(np.isclose(c.colors, 5.75, rtol=1e-6), axis=1)
    assert got.sum() == rep["from_photo"] > 0 and not np.isclose(c.colors, 1000 * 0.05).any()
    assert [p["photo"] for p in rep["photos"]] == [str(s["tmp"] / "p1.exr"), str(s["tmp"] / "p2.exr")]
    assert [p["overexposed_seen"] for p in rep["photos"]] == [rep["from_photo"]] * 2
    assert rep["photos"][0]["overexposed_only_this"] == 0
    assert rep["unseen_by_photos"] > 0 and 0 < rep["unseen_flux_share"] < 1


def test_calibrated_lookalikes_per_region_of_ldr_colour():
    """--unseen calibrated's fit: two regions of different LDR colour whose look-alikes are 2× too bright
    (bluish) and 2× too dark (yellowish) where the photo saw them; the unseen points of each region are
    corrected by their own region's median ratio (robust to 10 % outliers), not by the overall one."""
    from pipeline.expansion.reproject import calibrate_lookalikes

    rng = np.random.default_rng(0)
    n = 400
    ldr = np.r_[np.tile([0.92, 0.95, 1.0], (n, 1)), np.tile([1.0, 0.96, 0.91], (n, 1))] + rng.normal(0, 0.003, (2 * n, 3))
    truth = rng.uniform(2, 20, (2 * n, 1)) * np.ones(3)
    la = truth * np.r_[np.full((n, 1), 2.0), np.full((n, 1), 0.5)]
    seen = rng.random(2 * n) < 0.5
    photo = np.where(seen[:, None], truth, 0.0)
    photo[np.flatnonzero(seen)[::10]] *= 50                                  # 10 % wild reads
    out, rep = calibrate_lookalikes(ldr, la, np.ones(2 * n, bool), photo, seen, clusters=2, seed=1)
    np.testing.assert_allclose(out[~seen], truth[~seen], rtol=1e-6)
    assert rep["pairs"] == seen.sum() and sorted(c["correction"] for c in rep["clusters"]) == pytest.approx([0.5, 2.0])
    same, _ = calibrate_lookalikes(ldr, la, np.ones(2 * n, bool), photo, seen, clusters=2, seed=1)
    assert np.array_equal(same, out)                                          # deterministic for a seed
    few = seen & (np.arange(2 * n) < 10)
    unchanged, rep = calibrate_lookalikes(ldr, la, np.ones(2 * n, bool), photo, few)
    assert rep["pairs"] < 20 and rep["correction_global"] is None and np.array_equal(unchanged, la)


def test_isolated_points_facing_away_read_their_lamp_when_in_view():
    """--isolated-sides (issue 25, the lamp room): a lamp's few points are facets of an object the cloud does not
    resolve; those facing away from the photo take the lamp's pixel (3×3 peak) when the lamp is in view and
    unoccluded, and the facets of one lamp do not hide each other. A lamp behind an opaque plate stays unseen; the
    wall is untouched; without the rule the facets facing away get nothing."""
    from pathlib import Path

    from pipeline.camera import intrinsics, look_rotation
    from pipeline.expansion.photo_set import PhotoCam, photo_values
    from pipeline.expansion.reproject import isolated_any_side
    from pipeline.expansion.splats import knn_splat_radii, shrink_isolated

    x, y = np.meshgrid(np.arange(-40, 41) * 0.05, np.arange(-30, 31) * 0.05, indexing="ij")
    wall = np.c_[x.ravel(), y.ravel(), np.full(x.size, -4.0)]
    px, py = np.meshgrid(np.arange(-8, 9) * 0.02 + 0.6, np.arange(-8, 9) * 0.02, indexing="ij")
    plate = np.c_[px.ravel(), py.ravel(), np.full(px.size, -3.0)]          # hides the second lamp
    lamp = np.array([[0.0, 0.0, -3.68], [0.03, 0.0, -3.72], [0.0, 0.03, -3.72], [0.0, -0.03, -3.72]])
    lamp2 = lamp + np.array([0.6, 0.0, 0.0])
    pts = np.vstack([wall, plate, lamp, lamp2])
    nrm = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    nl = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, -0.8], [0.0, 0.6, -0.8], [0.0, -0.6, -0.8]])   # one faces the camera
    nrm[-8:] = np.vstack([nl, nl])
    r = knn_splat_radii(pts).astype(np.float64)
    riso, n_iso = shrink_isolated(pts, r, 2.0)
    iso = riso < r
    assert iso[-8:].all() and not iso[:-8].any()
    w, h = 96, 64
    K, R = intrinsics(60.0, (w, h)), look_rotation(np.array([0.0, 0.0, -1.0]))
    w2c = np.eye(4)
    w2c[:3, :3] = R
    photo = np.full((h, w, 3), 2.0)
    for L in (lamp, lamp2):
        c = L[0] @ R.T
        photo[int(c[1] / c[2] * K[1, 1] + K[1, 2]), int(c[0] / c[2] * K[0, 0] + K[0, 2])] = 500.0
    cam = PhotoCam(Path("photo.exr"), "pinhole", (w, h), w2c, K)
    oidx = np.arange(len(wall) + len(plate), len(pts))          # the overexposed points: the lamps
    s0, v0 = photo_values(pts, nrm, riso, oidx, photo, cam, 0.5, isolated=iso[oidx])
    assert s0.tolist() == [True, False, False, False] + [False] * 4     # facing: only the first facet of lamp 1
    s1, v1, n = isolated_any_side(pts, nrm, riso, iso, oidx, photo, cam, 0.5, s0, v0)
    assert n == 3 and s1[:4].all() and not s1[4:].any()
    np.testing.assert_allclose(v1[:4], 250.0)
    np.testing.assert_array_equal(v1[0], v0[0])
    # nothing to add: unchanged
    s2, v2, n2 = isolated_any_side(pts, nrm, riso, np.zeros(len(pts), bool), oidx, photo, cam, 0.5, s0, v0)
    assert n2 == 0 and (s2 == s0).all() and (v2 == v0).all()


def test_window_peak_finds_a_lamp_a_few_pixels_off():
    """--isolated-sides reads an isolated point's peak within ± ISOLATED_WINDOW px (a registered pose a few pixels
    off a 1–2 px lamp, the lamp room's photo_lamps.exr); the 3×3 peak misses it; nothing brighter farther away is
    taken."""
    from pipeline.expansion.register_photo import peak_reads
    from pipeline.expansion.reproject import ISOLATED_WINDOW, window_peak

    photo = np.full((40, 60, 3), 2.0)
    photo[20, 33] = 500.0                        # the lamp, 3 px right of the projection
    photo[20, 37] = 900.0                        # something brighter 7 px away
    u, v = np.array([30.5]), np.array([20.5])
    np.testing.assert_allclose(peak_reads(photo, u, v), [[2.0, 2.0, 2.0]])
    np.testing.assert_allclose(window_peak(photo, u, v), [[500.0, 500.0, 500.0]])
    assert ISOLATED_WINDOW == 3
    np.testing.assert_allclose(window_peak(photo, u, v, half=1), peak_reads(photo, u, v))


def test_reads_near_a_shown_lamps_image_are_dropped():
    """--isolated-sides: a point whose projection lies within ISOLATED_WINDOW + 1 px of a shown isolated point's
    image loses that photo's read (a pose a few pixels off reads the lamp there); farther points keep theirs."""
    from pathlib import Path

    from pipeline.camera import intrinsics, look_rotation
    from pipeline.expansion.photo_set import PhotoCam
    from pipeline.expansion.reproject import ISOLATED_WINDOW, near_isolated_images

    w, h = 96, 64
    K, R = intrinsics(60.0, (w, h)), look_rotation(np.array([0.0, 0.0, -1.0]))
    w2c = np.eye(4)
    w2c[:3, :3] = R
    cam = PhotoCam(Path("photo.exr"), "pinhole", (w, h), w2c, K)
    lamp = np.array([[0.0, 0.0, -4.0]])
    ul, vl, _ = cam.project(lamp)
    px = 4.0 / K[0, 0]                              # one pixel at 4 m [m]
    pts = np.array([[dx * px, 0.0, -4.0] for dx in (1.0, ISOLATED_WINDOW + 0.5, ISOLATED_WINDOW + 2.0, 10.0)])
    q = np.array([True, True, True, False])
    got = near_isolated_images(cam, pts, q, ul, vl)
    assert got.tolist() == [0, 1]
    assert near_isolated_images(cam, pts, q, ul[:0], vl[:0]).tolist() == []
