"""expose-match: α recovered from a photo made of the cloud's own HDR truth at a known scale."""
import numpy as np
import pytest

from pipeline import io
from pipeline.expose_match import (ExposeMatchConfig, apply_exposure, histogram_distance,
                                   luminance_histogram, match_exposure)


def _truth(n=40_000, seed=1):
    """HDR colours: log-uniform luminance over 1e-3…1e3 (relative), mildly coloured."""
    rng = np.random.default_rng(seed)
    lum = 10.0 ** rng.uniform(-3, 3, n)
    tint = rng.uniform(0.6, 1.4, (n, 3))
    return (lum[:, None] * tint).astype(np.float64)


def _ldr_cloud_colours(truth, e):
    """Eq. 1 of the truth at exposure e, stored as 8-bit sRGB and decoded (what read_cloud gives)."""
    enc = np.round(io.srgb_encode(np.clip(e * truth, 0, 1)) * 255.0) / 255.0
    return io.srgb_decode(enc)


@pytest.mark.parametrize("scale", [1e-6, 1.0, 1e6])
@pytest.mark.parametrize("space", ["srgb", "linear"])
def test_alpha_recovered_within_2_percent(scale, space):
    truth = _truth()
    e = 0.05  # ~1/3 of the points clip in the LDR cloud
    cloud = _ldr_cloud_colours(truth, e)
    photo = (truth * scale).reshape(200, 200, 3).astype(np.float32)
    res = match_exposure(photo, cloud, ExposeMatchConfig(hist_space=space))
    alpha_true = e / scale
    assert abs(res["alpha"] / alpha_true - 1.0) < 0.02, (res["alpha"], alpha_true, res["stop_reason"])
    # the refinement never ends above the grid's best distance and records every evaluation
    grid = res["tried_phase"] == 0
    assert res["distance"] <= res["tried_distance"][grid].min()
    assert res["iterations"] <= 50


def test_histogram_and_distance_basics():
    rgb = np.random.default_rng(0).random((1000, 3))
    h = luminance_histogram(rgb, 128)
    assert h.shape == (128,) and np.isclose(h.sum(), 1.0)
    assert histogram_distance(h, h) == 0.0
    # shifting every value by one bin moves the distance by one bin width
    a = np.zeros(128); a[10] = 1
    b = np.zeros(128); b[11] = 1
    assert np.isclose(histogram_distance(a, b), 1 / 128)


def test_apply_exposure_is_eq1():
    photo = np.array([[[0.5, 2.0, -1.0]]], dtype=np.float32)
    assert np.allclose(apply_exposure(photo, 0.8), [[[0.4, 1.0, 0.0]]])


def test_cli_end_to_end_and_bad_input(tmp_path, cli_run):
    truth = _truth(10_000)
    n = len(truth)
    rng = np.random.default_rng(2)
    pts = rng.random((n, 3)).astype(np.float32)
    nrm = np.tile(np.array([0, 1, 0], np.float32), (n, 1))
    e, s = 0.05, 1e3
    io.write_cloud(tmp_path / "cloud.ply", io.Cloud(pts, nrm, np.clip(e * truth, 0, 1).astype(np.float32)),
                   uchar_colors=True)
    io.write_image(tmp_path / "photo.exr", (truth * s).reshape(100, 100, 3))
    code, out, err = cli_run("expose-match", tmp_path / "photo.exr", tmp_path / "cloud.ply",
                             "--out", tmp_path / "exposure.npz", "--photo-ldr", tmp_path / "photo_ldr.exr",
                             "--preview", tmp_path / "prev.png")
    assert code == 0, err
    z = io.read_npz(tmp_path / "exposure.npz", "pcrelight.exposure/1")
    assert abs(float(z["alpha"]) / (e / s) - 1) < 0.02
    ldr = io.read_image(tmp_path / "photo_ldr.exr")
    photo = io.read_image(tmp_path / "photo.exr")
    assert np.allclose(ldr, np.clip(photo * float(z["alpha"]), 0, 1), atol=1e-6)
    for f in ("exposure_fit.png", "exposure.json", "prev.png"):
        assert (tmp_path / f).exists()
    # bad input: a black photo is one clear line naming the file
    io.write_image(tmp_path / "black.exr", np.zeros((4, 4, 3)))
    code, out, err = cli_run("expose-match", tmp_path / "black.exr", tmp_path / "cloud.ply",
                             "--out", tmp_path / "e2.npz", "--photo-ldr", tmp_path / "l2.exr")
    assert code == 1 and "black.exr" in err and "black" in err
    code, out, err = cli_run("expose-match", tmp_path / "missing.exr", tmp_path / "cloud.ply",
                             "--out", tmp_path / "e2.npz", "--photo-ldr", tmp_path / "l2.exr")
    assert code == 1 and "missing.exr: no such file" in err
    code, out, err = cli_run("expose-match", tmp_path / "photo.exr", tmp_path / "cloud.ply",
                             "--out", tmp_path / "e2.npz", "--photo-ldr", tmp_path / "l2.exr", "--bins", "1")
    assert code == 2 and "--bins" in err
