"""``pcrelight run --cloud SCAN --photo PHOTO --object ASSET --out DIR`` (issue 24): the placement and camera
rules on a synthetic box room, and the one command on that room's scan in the forms users bring (outliers,
a renamed asset, centimetres, a Radiance .hdr photo, Z up, LAS) giving the reference case's picture."""

from __future__ import annotations

import json
import math
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import write_exif_photo

from pipeline import io
from pipeline.run import own, place

sys.path.insert(0, str(Path(__file__).parent))
import own_inputs as oi  # noqa: E402

# small and fast: the stages' cheapest settings that still expand the lamp (its points are overexposed)
FAST = """
[render-cubemaps]
size = 32
grid = 3
normal_seeds = 4
probe_size = 32
[relight]
microbuffer = 8
"""
SIZE = "48x36"


# --------------------------------------------------------------------------- placement rules (pure)
def test_placement_rests_on_the_floor_in_the_free_space_nearest_the_centre():
    p, n, _ = oi.box_room()
    lmin, lmax = np.array([-0.25, -0.3, -0.25]), np.array([0.25, 0.3, 0.25])
    lo, hi = place.room_box(p)
    scale, sinfo = place.choose_scale(lmin, lmax, lo, hi)
    assert scale == 1.0 and "plausible" in sinfo["by"]
    pos, info = place.auto_place(p, n, lmin, lmax, scale)
    assert abs(pos[1] - 0.0) < 1e-6 and info["floor"]["points"] > 100           # on the floor (y = 0)
    assert np.linalg.norm(pos[[0, 2]]) < 0.1                                       # the room's centre is free
    M = place.to_world(pos, scale, 0.0, lmin, lmax)
    bmin, bmax = place.placed_box(M, np.array([lmin, lmax]))
    assert bmin[1] == pytest.approx(0.0, abs=1e-9) and bmax[1] == pytest.approx(0.6)
    assert place.check_placement(p, bmin, bmax, 0.0)["warnings"] == []

    # a table in the middle: the object moves out from under it to the nearest free floor that fits it
    tp, tn = oi._box_surface(np.array([-0.8, 0.0, -0.8]), np.array([0.8, 0.75, 0.8]), 0.08,
                             np.random.default_rng(1), inward=False)
    q, m = np.concatenate([p, tp]), np.concatenate([n, tn])
    pos2, info2 = place.auto_place(q, m, lmin, lmax, scale)
    assert np.abs(pos2[[0, 2]]).max() >= 0.8 + 0.25 - info2["cell_m"]                # clear of the table's footprint
    assert info2["clearance_m"] >= info2["footprint_radius_m"]
    assert np.linalg.norm(pos2[[0, 2]]) < 1.6                                      # and still near the centre
    b2 = place.placed_box(place.to_world(pos2, scale, 0.0, lmin, lmax), np.array([lmin, lmax]))
    assert place.check_placement(q, *b2, 0.0)["points_inside"] == 0


def test_placement_checks_warn_when_the_object_intersects_or_leaves_the_room():
    p, _, _ = oi.box_room()
    lmin, lmax = np.array([-0.25, 0.0, -0.25]), np.array([0.25, 0.6, 0.25])
    in_cabinet = place.placed_box(place.to_world([-0.9, 0.0, -2.0], 1.0, 0.0, lmin, lmax), np.array([lmin, lmax]))
    chk = place.check_placement(p, *in_cabinet, 0.0)
    assert chk["points_inside"] > 10 and "intersects the cloud" in chk["warnings"][0]
    outside = place.placed_box(place.to_world([50.0, 0.0, 0.0], 1.0, 0.0, lmin, lmax), np.array([lmin, lmax]))
    chk = place.check_placement(p, *outside, 0.0)
    assert chk["outside_room_m"] == pytest.approx(50.25 - 2.0, rel=1e-3) and "leaves the room" in chk["warnings"][-1]


def test_object_size_rule():
    lo, hi = np.array([-2.0, 0.0, -2.5]), np.array([2.0, 2.5, 2.5])
    s, info = place.choose_scale(np.zeros(3), np.array([60.0, 40.0, 30.0]), lo, hi)   # an asset in centimetres
    assert s == pytest.approx(place.DEFAULT_SHARE * 4.0 / 60.0) and "not plausible" in info["by"]
    s, info = place.choose_scale(np.zeros(3), np.array([0.6, 0.4, 0.3]), lo, hi, object_size=0.3)
    assert s == pytest.approx(0.5) and info["size_m"] == pytest.approx(0.3)
    M = place.to_world([1.0, 0.0, 2.0], 2.0, 90.0, np.zeros(3), np.array([1.0, 1.0, 0.5]))
    bmin, bmax = place.placed_box(M, np.array([[0, 0, 0], [1, 1, 0.5]], float))
    assert np.allclose(bmax - bmin, [1.0, 2.0, 2.0]) and np.allclose((bmin + bmax)[[0, 2]] / 2, [1.0, 2.0])


def test_auto_camera_frames_the_object_from_inside_the_room():
    p, _, _ = oi.box_room()
    bmin, bmax = np.array([-0.25, 0.0, -0.25]), np.array([0.25, 0.6, 0.25])
    cam, why = place.auto_camera(p, bmin, bmax, 40.0, 4 / 3)
    eye, target = np.array(cam["eye"]), np.array(cam["target"])
    lo, hi = place.room_box(p)
    assert np.all(eye > lo) and np.all(eye < hi) and np.allclose(target, [0.0, 0.3, 0.0])
    r = np.linalg.norm(bmax - bmin) / 2
    assert math.degrees(math.asin(r / np.linalg.norm(eye - target))) == pytest.approx(20.0 * place.FILL, rel=1e-6)
    assert why["clearance_m"] > why["spacing_m"] and eye[1] > target[1]
    # in a narrow corridor the eye moves in and the field of view widens to keep the framing
    q = p * np.array([0.25, 1.0, 1.0])
    cam2, why2 = place.auto_camera(q, bmin * [0.5, 1, 1], bmax * [0.5, 1, 1], 40.0, 4 / 3)
    e2 = np.array(cam2["eye"])
    lo2, hi2 = place.room_box(q)
    assert np.all(e2 > lo2) and np.all(e2 < hi2)
    assert why2["steps_in"] > 0 and cam2["fov_deg"] > 40.0 or why2["azimuth_deg"] in (0.0, 180.0)


def test_render_view_puts_row_zero_at_the_top():
    from pipeline.relight.gbuffer import Camera
    from pipeline.expansion.splats import render_view

    cam = Camera(np.zeros(3), np.array([0.0, 0.0, -1.0]), np.array([0.0, 1.0, 0.0]), 60.0, (40, 30))
    pts = np.array([[0.0, 0.3, -2.0], [0.5, 0.0, -2.0]])
    img = render_view(pts, np.array([[1.0, 0, 0], [0, 1.0, 0]]), np.full(2, 0.01), cam.view_matrix(), 60.0, (40, 30))
    r = np.argwhere(img[..., 0] > 0)[0]
    g = np.argwhere(img[..., 1] > 0)[0]
    f = 15 / math.tan(math.radians(30))
    assert r[0] == int(15 - f * 0.15) and g[1] == int(20 + f * 0.25)             # above the centre: upper rows
    assert img[r[0], r[1], 4] == pytest.approx(2.0) and img[..., 3].sum() == 2


def test_photo_fov_from_exif(tmp_path):
    path = write_exif_photo(tmp_path / "phone.exr", np.ones((40, 60, 3), np.float32), 28)
    fov, info = own.exif_fov(path)
    h_mm = math.hypot(36, 24) * 40 / math.hypot(60, 40)                          # 24 mm at 3:2
    assert fov == pytest.approx(math.degrees(2 * math.atan(h_mm / 56))) and "FocalLengthIn35mmFilm 28" in info["by"]
    io.write_image(tmp_path / "photo.hdr", np.ones((40, 60, 3), np.float32))
    assert own.exif_fov(tmp_path / "photo.hdr")[0] is None                        # Radiance files carry no EXIF


# --------------------------------------------------------------------------- the one command
def _run(cli_run, out: Path, cloud: Path, photo: Path, obj: Path, *extra: str):
    cfg = out.parent / "fast.toml"
    cfg.write_text(FAST)
    code, _, err = cli_run("run", cfg, "--cloud", cloud, "--photo", photo, "--object", obj, "--out", out,
                           "--size", SIZE, "-q", *extra)
    assert code == 0, err
    return json.loads((out / "run.json").read_text())


def _same_picture(a: Path, b: Path, tol: float = 0.02) -> float:
    x, y = io.read_image(a / "relit.exr"), io.read_image(b / "relit.exr")
    assert x.shape == y.shape
    mask = (x[..., 3] > 0) | (y[..., 3] > 0)
    assert ((x[..., 3] > 0) != (y[..., 3] > 0)).sum() <= 0.02 * mask.sum()       # the same object pixels
    d = float(np.abs(x[..., :3] - y[..., :3])[mask].mean() / np.abs(y[..., :3])[mask].mean())
    assert d < tol, f"mean difference {d:.4f} ≥ {tol}"
    return d


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The reference case: the box room's scan (metres, +Y up, uchar colours, no normals), photo.exr, object.glb."""
    root = tmp_path_factory.mktemp("own")
    inputs = oi.write_inputs(root / "in")
    return root, inputs


@pytest.fixture(scope="module")
def reference_run(reference):
    from click.testing import CliRunner

    import cli

    root, inputs = reference
    cfg = root / "fast.toml"
    cfg.write_text(FAST)
    r = CliRunner().invoke(cli.main, [str(a) for a in ("run", cfg, "--cloud", inputs["cloud"], "--photo", inputs["photo"],
                                                        "--object", inputs["object"], "--out", root / "ref", "--size",
                                                        SIZE, "-q")], catch_exceptions=False)
    assert r.exit_code == 0, r.stderr
    return root / "ref", json.loads((root / "ref" / "run.json").read_text())


def test_reference_run_writes_the_picture_the_composite_and_its_decisions(reference_run):
    out, rep = reference_run
    for name in ("relit.exr", "relit.png", "composite.exr", "composite.png", "scene.json", "cloud_ldr.ply"):
        assert (out / name).exists(), name
    own_ = rep["own"]
    assert own_["import"]["up"]["up"] == "y" and own_["import"]["units"]["unit"] == "m"
    assert own_["placement"]["floor"]["y"] == pytest.approx(0.0, abs=1e-6) and own_["checks"]["warnings"] == []
    assert "expose-match" in rep["order"] and not rep["stages"]["patchmatch"].get("skipped")   # the lamp is expanded
    relit = io.read_image(out / "relit.exr")
    comp = io.read_image(out / "composite.exr")
    a = relit[..., 3:4]
    assert 0.02 < a.mean() < 0.6 and comp[..., 3].min() == 1.0                  # the room fills the background
    assert np.allclose(comp[..., :3] * a, relit[..., :3] * a, atol=1e-6)           # the object is relit.exr's
    scene = json.loads((out / "scene.json").read_text())
    assert scene["object"]["file"] == "object.glb" and rep["stages"]["relight"]["config"]["seed"] == 0


def test_outliers_50_m_away_give_the_clean_scans_picture(reference, reference_run, cli_run, tmp_path):
    root, inputs = reference
    p, _, c = oi.box_room()
    rng = np.random.default_rng(3)
    d = rng.normal(size=(10, 3))
    far = 50.0 * d / np.linalg.norm(d, axis=1, keepdims=True) + [0.0, 1.25, 0.0]
    oi.write_scan(tmp_path / "noisy.ply", np.concatenate([p, far]), np.concatenate([c, rng.random((10, 3))]))
    rep = _run(cli_run, tmp_path / "out", tmp_path / "noisy.ply", inputs["photo"], inputs["object"])
    assert rep["own"]["import"]["outliers"]["removed"] == 10
    _same_picture(tmp_path / "out", reference_run[0])


def test_renamed_asset_named_by_the_config_gives_the_same_picture(reference, reference_run, cli_run, tmp_path):
    _, inputs = reference
    shutil.copy(inputs["object"], tmp_path / "my helmet copy.glb")
    cfg = tmp_path / "mine.toml"                                  # [run] cloud/photo/object instead of the flags
    cfg.write_text(f'[run]\ncloud = "{inputs["cloud"]}"\nphoto = "{inputs["photo"]}"\n'
                   f'object = "{tmp_path / "my helmet copy.glb"}"\nworkspace = "{tmp_path / "out"}"\nsize = "{SIZE}"\n' + FAST)
    code, _, err = cli_run("run", cfg, "-q")
    assert code == 0, err
    assert json.loads((tmp_path / "out" / "scene.json").read_text())["object"]["file"] == "my helmet copy.glb"
    _same_picture(tmp_path / "out", reference_run[0])


def test_centimetre_scan_gives_the_same_picture(reference, reference_run, cli_run, tmp_path):
    _, inputs = reference
    p, _, c = oi.box_room()
    oi.write_scan(tmp_path / "cm.ply", p * 100.0, c)
    rep = _run(cli_run, tmp_path / "out", tmp_path / "cm.ply", inputs["photo"], inputs["object"])
    assert rep["own"]["import"]["units"]["unit"] == "cm"
    _same_picture(tmp_path / "out", reference_run[0])


def test_z_up_scan_gives_the_same_picture(reference, reference_run, cli_run, tmp_path):
    _, inputs = reference
    p, _, c = oi.box_room()
    oi.write_scan(tmp_path / "zup.ply", np.stack([p[:, 0], -p[:, 2], p[:, 1]], axis=1), c)   # (x, y, z) → (x, −z, y)
    rep = _run(cli_run, tmp_path / "out", tmp_path / "zup.ply", inputs["photo"], inputs["object"])
    assert rep["own"]["import"]["up"]["up"] == "z"
    _same_picture(tmp_path / "out", reference_run[0])


def test_hdr_photo_gives_the_same_picture(reference, reference_run, cli_run, tmp_path):
    _, inputs = reference
    io.write_image(tmp_path / "photo.hdr", io.read_image(inputs["photo"]))
    _run(cli_run, tmp_path / "out", inputs["cloud"], tmp_path / "photo.hdr", inputs["object"])
    _same_picture(tmp_path / "out", reference_run[0])


def test_las_copy_gives_the_same_picture(reference, reference_run, cli_run, tmp_path):
    laspy = pytest.importorskip("laspy")
    from pipeline.color import srgb_encode

    _, inputs = reference
    p, _, c = oi.box_room()
    rgb = np.round(srgb_encode(np.clip(c, 0, 1)) * 255).astype(np.uint16)
    las = laspy.create(point_format=2, file_version="1.2")
    las.header.scales = [1e-4] * 3
    las.header.offsets = [0.0, 0.0, 0.0]
    las.x, las.y, las.z = p[:, 0], -p[:, 2], p[:, 1]                               # surveyors' Z up
    las.red, las.green, las.blue = rgb[:, 0] * 257, rgb[:, 1] * 257, rgb[:, 2] * 257
    las.write(str(tmp_path / "room.las"))
    rep = _run(cli_run, tmp_path / "out", tmp_path / "room.las", inputs["photo"], inputs["object"])
    assert rep["own"]["import"]["format"] == "LAS"
    _same_picture(tmp_path / "out", reference_run[0])


def test_changed_placement_or_options_rerun_what_they_change(reference, reference_run, cli_run, tmp_path):
    _, inputs = reference
    ws = tmp_path / "ws"
    shutil.copytree(reference_run[0], ws)                                          # times kept (copy2)
    rj = ws / "run.json"                                                           # the workspace moved: its paths too
    st = rj.stat()
    rj.write_text(rj.read_text().replace(str(reference_run[0]), str(ws)))
    os.utime(rj, (st.st_atime, st.st_mtime))
    rep = _run(cli_run, ws, inputs["cloud"], inputs["photo"], inputs["object"])
    assert all(e.get("skipped") for e in rep["stages"].values()) and rep["composite"].get("skipped")
    code, out, err = cli_run("run", tmp_path / "fast.toml", "--cloud", inputs["cloud"], "--photo", inputs["photo"],
                             "--object", inputs["object"], "--out", ws, "--size", SIZE, "--explain")
    assert code == 0 and "relight" in out and "up to date" in out, err                 # the imported scan's plan
    rep = _run(cli_run, ws, inputs["cloud"], inputs["photo"], inputs["object"], "--object-size", "0.3")
    ran = [v for v, e in rep["stages"].items() if not e.get("skipped")]
    assert ran == ["relight"] and not rep["composite"].get("skipped")
    assert rep["own"]["scale"]["size_m"] == pytest.approx(0.3)
    (tmp_path / "fast.toml").write_text(FAST.replace("microbuffer = 8", "microbuffer = 16"))
    code, _, err = cli_run("run", tmp_path / "fast.toml", "--cloud", inputs["cloud"], "--photo", inputs["photo"],
                           "--object", inputs["object"], "--out", ws, "--size", SIZE, "--object-size", "0.3", "-q")
    assert code == 0, err
    rep = json.loads((ws / "run.json").read_text())
    assert [v for v, e in rep["stages"].items() if not e.get("skipped")] == ["relight"]
    # given placements: half inside the cabinet, then 50 m away: warned, in run.json, and rendered where asked
    rep = _run(cli_run, ws, inputs["cloud"], inputs["photo"], inputs["object"], "--place", "-0.9,0,-2.0",
               "--rotate-y", "30")
    chk = rep["own"]["checks"]
    assert chk["points_inside"] > 0 and "intersects the cloud" in chk["warnings"][0] and chk["outside_room_m"] == 0
    assert json.loads((ws / "scene.json").read_text())["object"]["to_world"][0][3] != 0
    rep = _run(cli_run, ws, inputs["cloud"], inputs["photo"], inputs["object"], "--place", "0,0,0")
    assert rep["own"]["checks"]["warnings"] == []                                  # resting on the floor: no warning
    rep = _run(cli_run, ws, inputs["cloud"], inputs["photo"], inputs["object"], "--place", "50,0,0")
    assert rep["own"]["checks"]["outside_room_m"] > 45 and "leaves the room" in rep["own"]["checks"]["warnings"][-1]


def test_usage_and_input_errors_are_one_line(reference, cli_run, tmp_path):
    _, inputs = reference
    base = ["run", "--cloud", inputs["cloud"], "--object", inputs["object"], "--out", tmp_path / "o"]
    code, _, err = cli_run(*base, "--photo", inputs["photo"], "--photo", tmp_path / "nope.exr")
    assert code == 1 and err.strip() == f"pcrelight: {tmp_path / 'nope.exr'}: no such file (the photo)"
    (tmp_path / "empty").mkdir()
    code, _, err = cli_run(*base, "--photo", tmp_path / "empty")
    assert code == 1 and len(err.strip().splitlines()) == 1 and "without any HDR photo" in err, err
    code, _, err = cli_run(*base)
    assert code == 2 and "--cloud needs --photo" in err and len(err.strip().splitlines()) == 1
    code, _, err = cli_run("run", "--cloud", tmp_path / "nope.ply", "--photo", inputs["photo"], "--object",
                           inputs["object"], "--out", tmp_path / "o")
    assert code == 1 and err.strip() == f"pcrelight: {tmp_path / 'nope.ply'}: no such file (the scan)"
    (tmp_path / "room.obj").write_text("v 0 0 0\n")                    # a scan of a suffix no reader has
    code, _, err = cli_run("run", "--cloud", tmp_path / "room.obj", "--photo", inputs["photo"], "--object",
                           inputs["object"], "--out", tmp_path / "o")
    assert code == 1 and err.strip().startswith(f"pcrelight: {tmp_path / 'room.obj'}: unknown scan format '.obj' "
                                                "(known: .ply, .pcd,") and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()
    code, _, err = cli_run(*base, "--photo", inputs["object"])
    assert code == 1 and "the photo must be HDR" in err
    (tmp_path / "broken.glb").write_bytes(b"glTF not really")
    code, _, err = cli_run("run", "--cloud", inputs["cloud"], "--photo", inputs["photo"], "--object",
                           tmp_path / "broken.glb", "--out", tmp_path / "o")
    assert code == 1 and err.startswith(f"pcrelight: {tmp_path / 'broken.glb'}: ") and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()                                          # refused before anything is written
    code, _, err = cli_run("run")
    assert code == 2 and "run needs CONFIG_TOML" in err
    # --explain before the scan is imported: the plan from the inputs' headers, nothing written (issue 45)
    code, out, err = cli_run(*base, "--photo", inputs["photo"], "--explain")
    n = len(io.read_cloud(inputs["cloud"]).points) if str(inputs["cloud"]).endswith(".ply") else None
    assert code == 0 and "not imported yet" in out and "  import: " in out and "  relight: " in out, (out, err)
    assert n is None or f"{n} points in its header" in out, out
    assert "expose-match: " in out and "decided after the import" in out
    assert not (tmp_path / "o").exists()


def test_ignored_gltf_textures_are_named_in_a_warning(tmp_path, caplog):
    import logging

    import trimesh
    from PIL import Image

    im = Image.new("RGB", (4, 4), (128, 128, 255))
    mat = trimesh.visual.material.PBRMaterial(name="visor", baseColorFactor=[200, 200, 200, 255], normalTexture=im,
                                              occlusionTexture=im, emissiveFactor=[1.0, 0.5, 0.0])
    tm = trimesh.Trimesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float), np.array([[0, 1, 2]]), process=False,
                         visual=trimesh.visual.TextureVisuals(uv=np.array([[0, 0], [1, 0], [0, 1]], float), material=mat))
    (tmp_path / "helmet.glb").write_bytes(tm.export(file_type="glb"))
    with caplog.at_level(logging.WARNING, logger="pcrelight.io"):
        io.read_object(tmp_path / "helmet.glb")
    text = caplog.text
    assert "occlusion map (occlusionTexture) ignored (not applied yet) in material(s) visor" in text
    assert "emissi" not in text and "normal" not in text   # emission and normal maps are applied (tests/test_gltf.py)
    # an extension the reader does not apply: named too (the JSON chunk rewritten with extensionsUsed)
    import struct

    raw = (tmp_path / "helmet.glb").read_bytes()
    clen = struct.unpack_from("<I", raw, 12)[0]
    js = json.loads(raw[20:20 + clen])
    js["extensionsUsed"] = ["KHR_texture_transform", "KHR_materials_clearcoat"]
    body = json.dumps(js).encode()
    body += b" " * (-len(body) % 4)
    rest = raw[20 + clen:]
    out = b"glTF" + struct.pack("<II", 2, 12 + 8 + len(body) + len(rest)) + struct.pack("<II", len(body), 0x4E4F534A) + body + rest
    (tmp_path / "tt.glb").write_bytes(out)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="pcrelight.io"):
        io.read_object(tmp_path / "tt.glb")
    assert "glTF extension KHR_materials_clearcoat ignored (not applied yet: no clear coat layer)" in caplog.text
    assert "KHR_texture_transform" not in caplog.text             # read (tests/test_gltf.py)


def test_scene_options_without_a_scan_are_refused(cli_run, tmp_path):
    (tmp_path / "r.toml").write_text("[run]\n")
    code, _, err = cli_run("run", tmp_path / "r.toml", "--inputs", tmp_path, "--out", tmp_path / "o", "--place", "1,0,1")
    assert code == 2 and "--place applies to your own scan: give --cloud" in err


def test_several_photos_on_an_inputs_folder_are_the_run_s_set(cli_run, tmp_path):
    """`run --photo a --photo b` (or a folder of them) on an inputs folder: the workspace's photo set, declared as
    expose-match's, patchmatch's and reproject's inputs; a missing one is one line, exit 1, before anything runs."""
    from pipeline.run.stages import STAGE, RunConfig, workspace_of

    for name in ("b.exr", "a.exr", "notes.txt"):
        (tmp_path / "set" / name).parent.mkdir(exist_ok=True)
        (tmp_path / "set" / name).write_bytes(b"")
    ws = workspace_of(RunConfig(inputs=str(tmp_path), photo=(str(tmp_path / "set"),)))
    assert ws.photos == (tmp_path / "set" / "a.exr", tmp_path / "set" / "b.exr") and ws.photo == ws.photos[0]
    for verb in ("expose-match", "patchmatch", "reproject"):
        assert set(ws.photos) <= set(STAGE[verb].inputs(ws))
    one = workspace_of(RunConfig(inputs=str(tmp_path), photo=(str(tmp_path / "set" / "a.exr"),)))
    assert one.photos == (one.photo,) and one.photo_files == ()                 # a set of one: the single-photo path
    (tmp_path / "r.toml").write_text("[run]\n")
    from pipeline import io

    n = 50                                                 # a cloud with overexposed points: the photos are needed
    io.write_cloud(tmp_path / "cloud_ldr.ply", io.Cloud(np.random.default_rng(0).random((n, 3)).astype(np.float32),
                                                        np.tile(np.float32([0, 1, 0]), (n, 1)), np.ones((n, 3), np.float32)))
    code, _, err = cli_run("run", tmp_path / "r.toml", "--inputs", tmp_path, "--workspace", tmp_path / "w", "--photo",
                           tmp_path / "set" / "a.exr", "--photo", tmp_path / "x.exr", "--to", "patchmatch")
    assert code == 1 and err.strip().splitlines()[-1].startswith(f"pcrelight: {tmp_path / 'x.exr'}: no such file"), err


def test_e57_copy_gives_the_same_picture(reference, reference_run, cli_run, tmp_path):
    pye57 = pytest.importorskip("pye57")
    from pipeline.color import srgb_encode

    _, inputs = reference
    p, _, c = oi.box_room()
    rgb = np.round(srgb_encode(np.clip(c, 0, 1)) * 255).astype(np.uint8)
    e = pye57.E57(str(tmp_path / "room.e57"), mode="w")                           # E57: metres, Z up as surveyed
    e.write_scan_raw({"cartesianX": p[:, 0], "cartesianY": -p[:, 2], "cartesianZ": p[:, 1],
                      "colorRed": rgb[:, 0], "colorGreen": rgb[:, 1], "colorBlue": rgb[:, 2]})
    e.close()
    rep = _run(cli_run, tmp_path / "out", tmp_path / "room.e57", inputs["photo"], inputs["object"])
    assert rep["own"]["import"]["format"] == "E57" and rep["own"]["import"]["up"]["up"] == "z"
    _same_picture(tmp_path / "out", reference_run[0])


def test_photo_fov_precedence(tmp_path):
    path = write_exif_photo(tmp_path / "phone.exr", np.ones((40, 60, 3), np.float32), 28)
    exif = own.exif_fov(path)[0]
    assert own.photo_fov_for(own.OwnConfig(photo_fov=55.0), path, 70.0)[0] == 55.0          # --photo-fov
    assert own.photo_fov_for(own.OwnConfig(), path, 70.0)[0] == 70.0                        # [expose-match]
    assert own.photo_fov_for(own.OwnConfig(), path, 0.0)[0] == pytest.approx(exif)          # EXIF
    io.write_image(tmp_path / "p.hdr", np.ones((4, 4, 3), np.float32))
    assert own.photo_fov_for(own.OwnConfig(), tmp_path / "p.hdr", 0.0)[0] == 0.0             # unknown
