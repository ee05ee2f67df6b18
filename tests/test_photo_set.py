"""Several photos of one room (issue 25, pipeline/expansion/photo_set.py): the set through expose-match, a photo of another
room dropped, exposures that disagree warned about, a panorama placed with --photo-at.

The registrations are replaced by the true poses (the registration itself is tested in test_register_photo.py
and measured in its docstring; a real one takes about a minute per photo here): each photo's α is then computed
by the real exposure step at that pose (``exposure_from_pose``), and the overlap between photos, the joint fit,
the dropping and the warnings are the real code."""
from __future__ import annotations

import numpy as np
import pytest

from pipeline import camera, io
from pipeline.expansion import register_photo as rp
from tests.test_register_photo import nearest_mean, render_photo, synthetic_room

E = 0.5                     # LDR cloud = clamp(E × HDR)
SIZE, FOV = (160, 120), 60.0
POSES = {"a": (np.array([3.1, 1.55, 1.2]), np.array([-1.0, -0.15, -0.35]), 3.0),     # eye, forward, photo scale k
         "b": (np.array([0.5, 1.6, -1.0]), np.array([-1.0, -0.1, 0.25]), 1.5)}


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """The synthetic room's LDR cloud, photos a and b (overlapping views of the window wall) at different
    exposures, and a photo of something else (a smooth random image)."""
    tmp = tmp_path_factory.mktemp("photo_set")
    pts, nrm, hdr = synthetic_room(60_000)
    ldr = np.round(np.clip(E * hdr, 0, 1) * 255) / 255
    io.write_cloud(tmp / "cloud.ply", io.Cloud(pts.astype(np.float32), nrm.astype(np.float32), ldr.astype(np.float32)))
    dense, _, dense_hdr = synthetic_room(300_000, seed=1)
    K = camera.intrinsics(FOV, SIZE)
    truth = {}
    for name, (eye, fwd, k) in POSES.items():
        R = camera.look_rotation(fwd / np.linalg.norm(fwd))
        img = (k * render_photo(dense, dense_hdr, R, eye, K, SIZE)).astype(np.float32)
        io.write_image(tmp / f"{name}.exr", img)
        truth[name] = (R, eye, k, img)
    from scipy.ndimage import gaussian_filter

    other = gaussian_filter(np.random.default_rng(5).random((SIZE[1], SIZE[0], 3)), (4, 4, 0)) * 20
    io.write_image(tmp / "other.exr", other.astype(np.float32))
    return dict(tmp=tmp, pts=pts, nrm=nrm, ldr=ldr, hdr=hdr, K=K, truth=truth, other=other.astype(np.float32), dense=dense,
                dense_hdr=dense_hdr)


def _fake_registration(room, wrong: dict[str, float] | None = None):
    """registered_exposure at the true pose of each photo (α by the real exposure step there), NCC 0.9; the
    photo of something else: NCC 0.21 (what an unrelated image scored, register_photo's docstring)."""
    def reg(points, colors, normals, rgb, fov):
        for name, (R, eye, k, img) in room["truth"].items():
            if rgb.shape == img.shape and np.allclose(rgb, np.maximum(img, 0)):   # (the reader clips negatives)
                ex = rp.exposure_from_pose(points, colors, rgb, room["K"], R, eye, normals=normals)
                w2c = np.eye(4)
                w2c[:3, :3], w2c[:3, 3] = R, -R @ eye
                a = float(ex["alpha_sum"]) * (wrong or {}).get(name, 1.0)
                return dict(alpha=a, ncc=0.9, cover=0.9, blocks=int(ex["blocks"]), points=int(ex["points"]),
                            mad_ln=float(ex["mad_ln"]), world_to_camera=w2c, K=room["K"], eye=eye, seconds=0.0)
        return dict(alpha=0.3, ncc=0.21, cover=0.5, blocks=40, points=900, mad_ln=0.4, world_to_camera=np.eye(4),
                    K=room["K"], eye=np.zeros(3), seconds=0.0)
    return reg


def _expose(room, cli_run, monkeypatch, names, out, wrong=None, extra=()):
    from pipeline.expansion import expose_match as em

    monkeypatch.setattr(em, "registered_exposure", _fake_registration(room, wrong))
    t = room["tmp"]
    return cli_run("expose-match", *[t / f"{n}.exr" for n in names], t / "cloud.ply", "--out", t / f"{out}.npz",
                   "--photo-ldr", t / f"{out}_ldr.exr", "--photo-fov", str(FOV), *extra)


def test_a_photo_of_another_room_is_dropped_with_a_warning_naming_it(room, cli_run, monkeypatch):
    code, _, err = _expose(room, cli_run, monkeypatch, ["a", "other", "b"], "e3")
    assert code == 0, err
    t = room["tmp"]
    drop = [ln for ln in err.splitlines() if "dropped from the set" in ln]
    assert len(drop) == 1 and str(t / "other.exr") in drop[0] and "NCC 0.210" in drop[0], err
    assert "disagree" not in err
    ex = io.read_npz(t / "e3.npz", "pcrelight.exposure/1")
    assert ex["photos_kept"].tolist() == [1, 0, 1] and str(ex["alpha_source"]) == "joint"
    ka, kb = POSES["a"][2], POSES["b"][2]
    # photo i in cloud units = α·k_i·photo_i: α ≈ E/k_a (a is the reference), k_b ≈ k_a/k_b
    assert float(ex["alpha"]) == pytest.approx(E / ka, rel=0.05)
    assert ex["photos_scale"][2] == pytest.approx(ka / kb, rel=0.03) and ex["photos_scale"][0] == 1.0
    rep = io.read_json(t / "e3.json")
    pair = rep["joint"]["pairs"][0]
    assert pair["points_both"] > 500 and pair["ratio"] == pytest.approx(kb / ka, rel=0.03)   # α_a/α_b from the overlap
    # the recorded set resolves back to the files (patchmatch and reproject read it)
    from pipeline.expansion.photo_set import read_set

    cams = read_set(ex, t / "e3.npz")
    assert [c.path.resolve() for c in cams] == [(t / n).resolve() for n in ("a.exr", "other.exr", "b.exr")]
    R, eye = room["truth"]["b"][:2]
    assert np.allclose(cams[2].world_to_camera[:3, :3], R) and np.allclose(cams[2].eye, eye)


def test_exposures_that_disagree_beyond_their_error_are_warned(room, cli_run, monkeypatch):
    code, _, err = _expose(room, cli_run, monkeypatch, ["a", "b"], "e2w", wrong={"b": 1.25})
    assert code == 0, err
    warn = [ln for ln in err.splitlines() if "exposures disagree" in ln]
    t = room["tmp"]
    assert len(warn) == 1 and str(t / "a.exr") in warn[0] and str(t / "b.exr") in warn[0], err
    rep = io.read_json(t / "e2w.json")
    assert rep["joint"]["disagree"][0]["register_ratio"] == pytest.approx(POSES["b"][2] / POSES["a"][2] / 1.25, rel=0.05)
    code, _, err = _expose(room, cli_run, monkeypatch, ["a", "b"], "e2", wrong={"b": 1.03})   # within the error: quiet
    assert code == 0 and "exposures disagree" not in err, err


def _render_equirect(points, rgb, eye, size):
    """Reference equirect render of a point cloud from ``eye`` (world-aligned, :func:`pipeline.expansion.photo_set.placed_camera`'s
    axes): per pixel the mean colour of the points within 5 % of the nearest distance."""
    from pipeline.camera import PANORAMA_ROTATION

    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = PANORAMA_ROTATION, -PANORAMA_ROTATION @ eye
    u, v, d, ok = camera.project_points("equirect", points, size, w2c)
    w, h = size
    col, row = np.clip(np.floor(u).astype(int), 0, w - 1), np.clip(np.floor(v).astype(int), 0, h - 1)
    return nearest_mean((row * w + col)[ok], d[ok], rgb[ok], size)


def test_a_panorama_placed_at_its_centre(room, cli_run):
    """--photo-model equirect --photo-at: α from the points the panorama sees (the real exposure step), the
    camera stored; a fisheye without --photo-at: one line, exit 2, nothing written."""
    t = room["tmp"]
    eye, k = np.array([0.5, 1.7, 0.3]), 2.0
    pano = (k * _render_equirect(room["dense"], room["dense_hdr"], eye, (256, 128))).astype(np.float32)
    io.write_image(t / "pano.exr", pano)
    code, _, err = cli_run("expose-match", t / "pano.exr", t / "cloud.ply", "--out", t / "p.npz", "--photo-ldr",
                           t / "p_ldr.exr", "--photo-model", "equirect", "--photo-at", "0.5,1.7,0.3")
    assert code == 0, err
    ex = io.read_npz(t / "p.npz", "pcrelight.exposure/1")
    assert str(ex["alpha_source"]) == "placed" and float(ex["alpha"]) == pytest.approx(E / k, rel=0.05)
    assert str(ex["photos_model"][0]) == "equirect" and ex["photos_kept"].tolist() == [1]
    assert np.allclose(-ex["photos_world_to_camera"][0, :3, :3].T @ ex["photos_world_to_camera"][0, :3, 3], eye)
    code, _, err = cli_run("expose-match", t / "pano.exr", t / "cloud.ply", "--out", t / "q.npz", "--photo-ldr",
                           t / "q_ldr.exr", "--photo-model", "fisheye", "--photo-fov", "170")
    assert code == 2 and not (t / "q.npz").exists()
    assert [ln for ln in err.splitlines() if ln.startswith("pcrelight: ")][0].count("--photo-at") >= 1, err
    # a panorama without --photo-at under --alpha-from histogram (no registration): one line, exit 2, nothing written
    code, _, err = cli_run("expose-match", t / "pano.exr", t / "cloud.ply", "--out", t / "h.npz", "--photo-ldr",
                           t / "h_ldr.exr", "--photo-model", "equirect", "--alpha-from", "histogram")
    assert code == 2 and not (t / "h.npz").exists() and not (t / "h_ldr.exr").exists()
    assert [ln for ln in err.splitlines() if ln.startswith("pcrelight: ")][0].count("--photo-at") >= 1, err


def test_a_placed_panorama_turned_off_the_worlds_axes_gets_its_yaw_and_a_wrong_centre_is_refused(room, cli_run):
    """--photo-at gives the centre, not the yaw (a 360° camera's is never the scan's): the yaw is searched at the
    centre, so a panorama turned by 84° gives the same α as the world-aligned one; a centre the cloud contradicts
    (2 m off) is refused in one line naming the photo, exit 1, nothing written (issue 45: α was 72 % low, silently)."""
    from pipeline.expansion.register_photo import level_rotation

    t = room["tmp"]
    eye, k = np.array([0.5, 1.7, 0.3]), 2.0
    pano = (k * _render_equirect(room["dense"], room["dense_hdr"], eye, (256, 128))).astype(np.float32)
    turned = np.roll(pano, 60, axis=1)               # 60 of 256 columns: 84.4°
    io.write_image(t / "turned.exr", turned)
    code, _, err = cli_run("expose-match", t / "turned.exr", t / "cloud.ply", "--out", t / "y.npz", "--photo-ldr",
                           t / "y_ldr.exr", "--photo-model", "equirect", "--photo-at", "0.5,1.7,0.3")
    assert code == 0, err
    ex = io.read_npz(t / "y.npz", "pcrelight.exposure/1")
    assert float(ex["alpha"]) == pytest.approx(E / k, rel=0.05)
    R = ex["photos_world_to_camera"][0, :3, :3]
    yaws = np.degrees([np.arccos(np.clip((np.trace(R.T @ level_rotation(np.radians(y))) - 1) / 2, -1, 1))
                       for y in (84.375,)])
    assert yaws[0] < 2.0, R                          # within 2° of the turn
    code, _, err = cli_run("expose-match", t / "turned.exr", t / "cloud.ply", "--out", t / "w.npz", "--photo-ldr",
                           t / "w_ldr.exr", "--photo-model", "equirect", "--photo-at", "2.5,1.7,0.3")
    lines = [ln for ln in err.splitlines() if ln.startswith("pcrelight: ")]
    assert code == 1 and len(lines) == 1 and str(t / "turned.exr") in lines[0] and "contradicts" in lines[0], err
    assert not (t / "w.npz").exists() and not (t / "w_ldr.exr").exists()


def test_a_panorama_without_its_centre_is_registered(room, cli_run):
    """--photo-model equirect without --photo-at: the panorama is registered against the cloud (the real
    register_panorama: a level panorama's centre and yaw), α from the points it sees; the camera, its NCC and its
    registration (centre, yaw, seconds) recorded in exposure.npz and the report. On a 20 000-point cloud of the room
    (the fixture's 60 000: 1.7 cm, 0.04° off, NCC 0.95, 33 CPU s), to keep the test short."""
    t = room["tmp"]
    pts, nrm, hdr = synthetic_room(20_000, seed=2)
    io.write_cloud(t / "cloud20k.ply", io.Cloud(pts.astype(np.float32), nrm.astype(np.float32),
                                                (np.round(np.clip(E * hdr, 0, 1) * 255) / 255).astype(np.float32)))
    eye, k, turn = np.array([0.5, 1.7, 0.3]), 2.0, 40
    pano = np.roll(k * _render_equirect(room["dense"], room["dense_hdr"], eye, (256, 128)), turn, axis=1)
    io.write_image(t / "pano_turned.exr", pano.astype(np.float32))
    code, _, err = cli_run("expose-match", t / "pano_turned.exr", t / "cloud20k.ply", "--out", t / "r.npz", "--photo-ldr",
                           t / "r_ldr.exr", "--photo-model", "equirect")
    assert code == 0, err
    assert "panorama registered" in err
    ex = io.read_npz(t / "r.npz", "pcrelight.exposure/1")
    assert str(ex["alpha_source"]) == "register" and float(ex["alpha"]) == pytest.approx(E / k, rel=0.05)
    assert ex["photos_kept"].tolist() == [1] and ex["photos_registered"].tolist() == [1]
    w2c = ex["photos_world_to_camera"][0]
    assert np.linalg.norm(-w2c[:3, :3].T @ w2c[:3, 3] - eye) < 0.05
    yaw = 360.0 * turn / 256
    assert np.allclose(w2c[:3, :3], rp.level_rotation(np.radians(yaw)), atol=np.radians(0.2))
    reg = io.read_json(t / "r.json")["photos"][0]["registration"]
    print(f"registered panorama: centre {np.round(reg['eye'], 3)} ({100 * np.linalg.norm(np.asarray(reg['eye']) - eye):.1f} cm "
          f"off), yaw {reg['yaw_deg']:.3f}° (turn {yaw:.3f}°), NCC {reg['ncc']:.3f}, cover {reg['cover']:.2f}, {reg['seconds']:.0f} s")
    assert reg["yaw_deg"] == pytest.approx(yaw, abs=0.2) and reg["ncc"] == pytest.approx(float(ex["photos_quality"][0]))
    assert reg["ncc"] > 0.8 and reg["seconds"] > 0


def _fake_panorama(ncc: float, eye=(0.5, 1.7, 0.3), alpha: float = 0.25):
    """registered_panorama's dict for a panorama found at ``eye`` (yaw 0) with NCC ``ncc`` (what register_panorama
    gave the synthetic room's panorama on this cloud: 0.95; another room's panorama: 0.08–0.14, test_register_photo)."""
    def reg(points, colors, normals, pano):
        w2c = np.eye(4)
        w2c[:3, :3] = rp.level_rotation(0.0)
        w2c[:3, 3] = -w2c[:3, :3] @ np.asarray(eye, float)
        return dict(alpha=alpha, ncc=ncc, cover=0.9 if ncc > 0.5 else 0.5, blocks=60, points=5000, mad_ln=0.05,
                    world_to_camera=w2c, K=np.zeros((3, 3)), eye=np.asarray(eye, float), yaw_deg=0.0, margin=0.2,
                    seconds=0.0)
    return reg


def test_a_panorama_of_another_room_is_dropped_from_a_set_and_refused_alone(room, cli_run, monkeypatch, tmp_path):
    """A registered panorama whose registration is not confident (NCC 0.1): in a set with photo a it is dropped with
    a WARNING naming it (photo a kept alone); alone it is refused in one line naming it, exit 1, nothing written.
    A confident one in the set (no --photo-at: registered) is kept beside photo a."""
    from pipeline.expansion import expose_match as em

    pano = (2.0 * _render_equirect(room["dense"], room["dense_hdr"], np.array([0.5, 1.7, 0.3]), (256, 128)))
    io.write_image(tmp_path / "pano.exr", pano.astype(np.float32))
    monkeypatch.setattr(em, "registered_exposure", _fake_registration(room))
    a = room["tmp"] / "a.exr"
    args = ("--photo-fov", str(FOV), "--photo-model", "pinhole,equirect")
    monkeypatch.setattr(em, "registered_panorama", _fake_panorama(0.1))
    code, _, err = cli_run("expose-match", a, tmp_path / "pano.exr", room["tmp"] / "cloud.ply", "--out",
                           tmp_path / "d.npz", "--photo-ldr", tmp_path / "d_ldr.exr", *args)
    assert code == 0, err
    drop = [ln for ln in err.splitlines() if "dropped from the set" in ln]
    assert len(drop) == 1 and str(tmp_path / "pano.exr") in drop[0] and "NCC 0.100" in drop[0], err
    ex = io.read_npz(tmp_path / "d.npz", "pcrelight.exposure/1")
    assert ex["photos_kept"].tolist() == [1, 0] and str(ex["alpha_source"]) == "register"
    code, _, err = cli_run("expose-match", tmp_path / "pano.exr", room["tmp"] / "cloud.ply", "--out", tmp_path / "s.npz",
                           "--photo-ldr", tmp_path / "s_ldr.exr", "--photo-model", "equirect")
    assert code == 1 and not (tmp_path / "s.npz").exists()
    lines = [ln for ln in err.splitlines() if ln.startswith("pcrelight: ")]
    assert len(lines) == 1 and str(tmp_path / "pano.exr") in lines[0] and "NCC 0.100" in lines[0], err
    monkeypatch.setattr(em, "registered_panorama", _fake_panorama(0.95))
    code, _, err = cli_run("expose-match", a, tmp_path / "pano.exr", room["tmp"] / "cloud.ply", "--out",
                           tmp_path / "k.npz", "--photo-ldr", tmp_path / "k_ldr.exr", *args)
    assert code == 0, err
    ex = io.read_npz(tmp_path / "k.npz", "pcrelight.exposure/1")
    assert ex["photos_kept"].tolist() == [1, 1] and ex["photos_registered"].tolist() == [1, 1]
    assert str(ex["alpha_source"]) == "joint" and ex["photos_quality"][1] == pytest.approx(0.95)


def test_panorama_values_of_the_points_it_sees():
    """photo_values on an equirect photo: a seen point reads the panorama at its direction (a photo linear in
    the pixel coordinates: exact up to bilinear interpolation); points hidden behind a nearer wall or facing
    away read nothing."""
    from pipeline.expansion.photo_set import photo_values, placed_camera
    from pipeline.expansion.splats import knn_splat_radii

    rng = np.random.default_rng(4)
    wall = np.c_[rng.uniform(-3, 3, 20000), rng.uniform(-2, 2, 20000), np.full(20000, 4.0)]        # faces −z, at +z 4 m
    occ = np.c_[rng.uniform(-0.5, 0.5, 3000), rng.uniform(-0.5, 0.5, 3000), np.full(3000, 2.0)]
    pts = np.vstack([wall, occ])
    nrm = np.tile([0.0, 0.0, -1.0], (len(pts), 1))
    nrm[:500] *= -1
    w, h = 512, 256
    jj, ii = np.mgrid[0:h, 0:w]
    photo = np.stack([1 + 0.01 * ii, 2 + 0.02 * jj, np.full((h, w), 3.0)], -1)
    cam = placed_camera("pano.exr", "equirect", (w, h), (0.0, 0.0, 0.0))
    q = np.arange(len(wall))
    seen, val = photo_values(pts, nrm, knn_splat_radii(pts), q, photo, cam, 0.5)
    u, v, _ = cam.project(wall)
    hidden = (np.abs(wall[:, 0]) < 0.9) & (np.abs(wall[:, 1]) < 0.9)
    clear = (np.abs(wall[:, 0]) > 1.2) | (np.abs(wall[:, 1]) > 1.2)
    facing = np.arange(len(wall)) >= 500
    assert not seen[~facing].any() and not seen[hidden].any()
    assert seen[clear & facing].mean() > 0.99
    s = seen & clear
    expect = 0.5 * np.stack([1 + 0.01 * (u[s] - 0.5), 2 + 0.02 * (v[s] - 0.5), np.full(s.sum(), 3.0)], -1)
    assert np.allclose(val[s], expect, rtol=1e-9, atol=1e-9)


def test_joint_fit_is_the_weighted_least_squares():
    from pipeline.expansion.photo_set import joint_fit

    # two photos: registrations 1.0 and 2.0 (±2 %), the overlap says α_0/α_1 = 0.5 exactly (±0.5 %, floored to 2 %)
    f = joint_fit([1.0, 2.0], [0.02, 0.02], {(0, 1): {"ln_ratio": np.log(0.5), "error": 0.005}})
    assert np.allclose(f["alpha"], [1.0, 2.0]) and f["disagree"] == []
    f = joint_fit([1.0, 3.0], [0.02, 0.02], {(0, 1): {"ln_ratio": np.log(0.5), "error": 0.005}})
    assert len(f["disagree"]) == 1 and f["disagree"][0][:2] == (0, 1)
    assert f["alpha"][1] / f["alpha"][0] == pytest.approx(12 ** (1 / 3), rel=1e-9)   # a0 = ln 1.5 / 3, a1 = a0 + ln 12 / 3


def test_a_set_of_one_is_the_single_photo_path(room, cli_run, monkeypatch, tmp_path):
    """One photo given as a folder holding it writes the same bytes as the photo given alone, and the single-photo
    keys (no ``photos*``: patchmatch and reproject take today's path). Measured against main's code (02f6c25) on
    the tiny chain (`run` of configs/demo.toml with test_stage_by_hand's sizes): every data file byte-identical."""
    import shutil

    (tmp_path / "one").mkdir()
    shutil.copy(room["tmp"] / "a.exr", tmp_path / "one" / "a.exr")
    from pipeline.expansion import expose_match as em

    monkeypatch.setattr(em, "registered_exposure", _fake_registration(room))
    outs = []
    for k, photo in enumerate((room["tmp"] / "a.exr", tmp_path / "one")):
        code, _, err = cli_run("expose-match", photo, room["tmp"] / "cloud.ply", "--out", tmp_path / f"{k}.npz",
                               "--photo-ldr", tmp_path / f"{k}.exr", "--photo-fov", str(FOV))
        assert code == 0, err
        outs.append(((tmp_path / f"{k}.npz").read_bytes(), (tmp_path / f"{k}.exr").read_bytes()))
    assert outs[0] == outs[1]
    ex = io.read_npz(tmp_path / "0.npz", "pcrelight.exposure/1")
    assert "photos" not in ex and "photo_world_to_camera" in ex and str(ex["alpha_source"]) == "register"


# ----------------------------------------------------------------------------- a registered set: no faces
def _registered_set(tiny, ws, cli_run) -> list:
    """expose-match's outputs for the tiny scene's photos as one set, each at its true camera (what the
    registrations give, without their minutes): α the first photo's true α, k_i the true ratios, NCC 0.9."""
    from pipeline.measure.evaluate import photo_truths

    phs = photo_truths(tiny)[:2]
    files = [tiny / p["file"] for p in phs]
    ws.mkdir(parents=True, exist_ok=True)
    code, _, err = cli_run("expose-match", *files, tiny / "cloud_ldr.ply", "--out", ws / "exposure.npz",
                           "--photo-ldr", ws / "photo_ldr.exr", "-q")
    assert code == 0, err
    ex = io.read_npz(ws / "exposure.npz", "pcrelight.exposure/1")
    trs = [io.read_npz(tiny / p["truth"], "pcrelight.truth/1") for p in phs]
    at = np.array([float(t["alpha_true"]) for t in trs])
    ex.update(alpha=np.float64(at[0]), photos_registered=np.ones(2, np.uint8), photos_kept=np.ones(2, np.uint8),
              photos_world_to_camera=np.stack([t["photo_world_to_camera"] for t in trs]).astype(np.float64),
              photos_K=np.stack([t["photo_K"] for t in trs]).astype(np.float64), photos_scale=at / at[0],
              photos_quality=np.full(2, 0.9))
    io.write_npz(ws / "exposure.npz", "pcrelight.exposure/1", **ex)
    return files


def test_a_registered_set_needs_no_faces_and_gives_the_same_cloud(tiny_scene, cli_run, tmp_path):
    """Two photos, both registered, --unseen poisson: the plan skips render-cubemaps and patchmatch, reproject
    transfers both photos alone, and cloud_proj.ply / cloud_hdr.ply are byte-identical to the full chain's
    (``--no-plan``: cube maps, PatchMatch against both photos, the same direct transfer)."""
    import json

    for name in ("plan", "full"):
        files = _registered_set(tiny_scene, tmp_path / name, cli_run)
        (tmp_path / f"{name}.toml").write_text(
            f'seed = 0\n[run]\ninputs = "{tiny_scene}"\nworkspace = "{tmp_path / name}"\n'
            f'photo = [{", ".join(repr(str(f)) for f in files)}]\n[render-cubemaps]\nsize = 48\n'
            '[patchmatch]\nmethod = "pmatch"\niterations = 2\n')
    code, out, err = cli_run("run", tmp_path / "plan.toml", "--explain", "-q", "--from", "render-cubemaps", "--to", "poisson")
    assert code == 0, err
    by = {ln.split()[0]: ln for ln in out.splitlines()[1:]}
    for v in ("render-cubemaps", "patchmatch"):
        assert by[v].startswith(f"{v:<16} skipped: no cube maps, no PatchMatch: the photo is registered"), by[v]
    code, _, err = cli_run("run", tmp_path / "plan.toml", "--from", "render-cubemaps", "--to", "poisson", "-q")
    assert code == 0, err
    code, _, err = cli_run("run", tmp_path / "full.toml", "--from", "render-cubemaps", "--to", "poisson", "--no-plan", "-q")
    assert code == 0, err
    assert not (tmp_path / "plan" / "hdr_faces").exists() and (tmp_path / "full" / "hdr_faces" / "renderings.npz").exists()
    proj = json.loads((tmp_path / "plan" / "cloud_proj.json").read_text())
    full = json.loads((tmp_path / "full" / "cloud_proj.json").read_text())
    assert proj["faces"] == 0 and full["faces"] > 0
    assert [p["overexposed_seen"] for p in proj["photos"]] == [p["overexposed_seen"] for p in full["photos"]]
    assert len(proj["photos"]) == 2 and all(p["overexposed_seen"] > 0 for p in proj["photos"])
    assert full["invalid_unseen_by_photo"] > 0 and proj["invalid"] == full["invalid"] > 0
    for f in ("cloud_proj.ply", "cloud_hdr.ply"):
        assert (tmp_path / "plan" / f).read_bytes() == (tmp_path / "full" / f).read_bytes(), f


def test_a_set_mixing_a_panorama_and_a_pinhole_photo(room, cli_run, monkeypatch, tmp_path):
    """--photo-model pinhole,equirect: photo a registered, the panorama placed at its --photo-at; both kept,
    one α with k_pano from their overlap; reproject without faces (the set is registered) gives the overexposed
    points each sees their α·k × photo value, weighted across the two models (NCC 0.9 and 1 for the placed
    panorama), and cloud_proj.json counts each photo's points. A model count that is neither one nor one per photo:
    one line, exit 2."""
    eye, k = np.array([0.5, 1.7, 0.3]), 2.0
    pano = (k * _render_equirect(room["dense"], room["dense_hdr"], eye, (256, 128))).astype(np.float32)
    io.write_image(tmp_path / "pano.exr", pano)
    from pipeline.expansion import expose_match as em

    monkeypatch.setattr(em, "registered_exposure", _fake_registration(room))
    a = room["tmp"] / "a.exr"
    args = ("--out", tmp_path / "m.npz", "--photo-ldr", tmp_path / "m_ldr.exr", "--photo-fov", str(FOV),
            "--photo-at", "0.5,1.7,0.3")
    code, _, err = cli_run("expose-match", a, tmp_path / "pano.exr", room["tmp"] / "cloud.ply", *args,
                           "--photo-model", "pinhole,equirect")
    assert code == 0, err
    ex = io.read_npz(tmp_path / "m.npz", "pcrelight.exposure/1")
    assert [str(m) for m in ex["photos_model"]] == ["pinhole", "equirect"] and ex["photos_kept"].tolist() == [1, 1]
    assert str(ex["alpha_source"]) == "joint" and float(ex["alpha"]) == pytest.approx(E / POSES["a"][2], rel=0.05)
    assert ex["photos_scale"][1] == pytest.approx(POSES["a"][2] / k, rel=0.05)
    rep = io.read_json(tmp_path / "m.json")
    assert [p["model"] for p in rep["photos"]] == ["pinhole", "equirect"] and rep["joint"]["pairs"][0]["points_both"] > 500
    code, _, err = cli_run("reproject", room["tmp"] / "cloud.ply", "--out", tmp_path / "proj.ply", "--photo", a,
                           "--photo", tmp_path / "pano.exr", "--exposure", tmp_path / "m.npz")
    assert code == 0, err
    pj = io.read_json(tmp_path / "proj.json")
    assert [p["model"] for p in pj["photos"]] == ["pinhole", "equirect"]
    assert [p["weight"] for p in pj["photos"]] == pytest.approx([0.9, 1.0])
    assert all(p["overexposed_seen"] > 500 for p in pj["photos"]) and pj["from_photo"] >= pj["photos"][0]["overexposed_seen"]
    proj = io.read_cloud(tmp_path / "proj.ply")
    from pipeline.color import luminance

    seen = (proj.source == 1) & (proj.valid == 1)
    y, yt = luminance(proj.colors[seen].astype(np.float64)), luminance(E * room["hdr"][seen])
    assert seen.sum() == pj["from_photo"] and np.median(np.abs(y / yt - 1)) < 0.1     # α·k × photo ≈ the true E × HDR
    # the weights across the models: the panorama 10 % brighter moves a point both see by (0.9 + 1.1) / 1.9
    io.write_image(tmp_path / "pano11.exr", (1.1 * pano).astype(np.float32))
    code, _, err = cli_run("reproject", room["tmp"] / "cloud.ply", "--out", tmp_path / "proj11.ply", "--photo", a,
                           "--photo", tmp_path / "pano11.exr", "--exposure", tmp_path / "m.npz", "--no-ldr-floor")
    assert code == 0, err
    code, _, err = cli_run("reproject", room["tmp"] / "cloud.ply", "--out", tmp_path / "proj10.ply", "--photo", a,
                           "--photo", tmp_path / "pano.exr", "--exposure", tmp_path / "m.npz", "--no-ldr-floor")
    assert code == 0, err
    p10, p11 = io.read_cloud(tmp_path / "proj10.ply"), io.read_cloud(tmp_path / "proj11.ply")
    both = (p10.source == 1) & (p10.valid == 1) & (luminance(p10.colors.astype(np.float64)) > 0)
    assert both.sum() > 500
    ratio = luminance(p11.colors[both].astype(np.float64)) / luminance(p10.colors[both].astype(np.float64))
    # NCC-weighted mean: 1.0526 (equal weights would give 1.05, photo a alone 1, the panorama alone 1.1)
    assert np.median(ratio) == pytest.approx((0.9 + 1.0 * 1.1) / 1.9, abs=5e-4)
    code, _, err = cli_run("expose-match", a, tmp_path / "pano.exr", room["tmp"] / "cloud.ply", *args,
                           "--photo-model", "pinhole,equirect,equirect")
    assert code == 2 and "3 models for 2 photos" in err
