"""merge-brackets: a bracket set synthesised from the shipped HDR photo through a known response curve
(E·t clipped to 1, gamma 1/2.2, 8-bit) is merged back to that photo (up to one scale: the merge's unit is
relative), with the times from --times or from each file's EXIF ExposureTime."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline import io

from conftest import SAMPLES

TIMES = (1 / 64, 1 / 16, 1 / 4, 1.0, 4.0)   # [s]: the photo's 1st…99th percentile luminance 0.013…15 in range


def _response(e: np.ndarray) -> np.ndarray:
    """The known camera: 8-bit codes of clip(E·t, 0, 1)^(1/2.2)."""
    return np.round(np.clip(e, 0.0, 1.0) ** (1 / 2.2) * 255).astype(np.uint8)


def _write(path: Path, codes: np.ndarray, exposure_time: float | None = None) -> None:
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(codes.shape[1], codes.shape[0], 3, "uint8")
    if exposure_time is not None:
        spec.attribute("ExposureTime", float(exposure_time))
    if path.suffix == ".jpg":
        spec.attribute("Compression", "jpeg:100")
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(codes) and out.close()


@pytest.fixture(scope="module")
def brackets(tmp_path_factory):
    photo = io.read_image(SAMPLES / "photo.exr")[..., :3].astype(np.float64)
    d = tmp_path_factory.mktemp("brackets")
    paths = []
    for t in TIMES:
        p = d / f"b_{t:g}.png"
        _write(p, _response(photo * t))
        paths.append(p)
    return photo, paths


def _well_exposed(photo: np.ndarray) -> np.ndarray:
    ok = np.zeros(photo.shape[:2], bool)
    for t in TIMES:
        v = np.clip(photo * t, 0, 1) ** (1 / 2.2)
        ok |= ((v > 0.1) & (v < 0.9)).all(axis=2)
    return ok


@pytest.mark.parametrize("method, median_tol, p95_tol", [("debevec", 0.01, 0.03), ("robertson", 0.12, 0.25)])
def test_merge_recovers_the_photo_up_to_one_scale(brackets, tmp_path, cli_run, method, median_tol, p95_tol):
    """Measured (photo.exr, 384×256, 5 brackets 2 stops apart): Debevec 0.51 % median, 1.98 % 95th percentile
    relative error on the pixels some bracket exposes well, response within −3.0 / +1.2 % of E^2.2;
    OpenCV's Robertson 8.4 % / 18.4 % (its response 0.91…1.22× E^2.2): Debevec is the default."""
    photo, paths = brackets
    out = tmp_path / "photo.exr"
    code, _, err = cli_run("merge-brackets", *paths, "--out", out, "--times", ",".join(f"{t!r}" for t in TIMES),
                           "--method", method, "--preview", tmp_path / "p.png")
    assert code == 0, err
    hdr = io.read_image(out).astype(np.float64)
    assert hdr.shape == photo.shape and (tmp_path / "p.png").exists()
    ok = _well_exposed(photo)
    assert ok.mean() > 0.99
    scale = np.median((hdr / photo)[ok])
    rel = np.abs(hdr[ok] / (scale * photo[ok]) - 1.0)
    assert np.median(rel) < median_tol and np.percentile(rel, 95) < p95_tol, (np.median(rel), np.percentile(rel, 95))
    rep = io.read_json(tmp_path / "photo.json")
    assert rep["times_from"] == "--times" and rep["times"] == pytest.approx(list(TIMES))
    resp = np.asarray(rep["response"])              # E·t per 8-bit code: ∝ code^2.2 for this camera
    z = np.arange(256) / 255.0
    mid = (z > 0.05) & (z < 0.95)
    ratio = resp[mid] / (z[mid, None] ** 2.2)
    assert ratio.shape == (int(mid.sum()), 3)
    if method == "debevec":
        assert np.all(np.abs(ratio / np.median(ratio) - 1) < 0.04)


def test_times_come_from_exif(brackets, tmp_path, cli_run):
    """The same shots as JPEG with EXIF ExposureTime: merged without --times as with them, byte for byte."""
    photo, _ = brackets
    paths = []
    for t in TIMES:
        p = tmp_path / f"b_{t:g}.jpg"
        _write(p, _response(photo * t), exposure_time=t)
        paths.append(p)
    assert io.image_attributes(paths[0], ("ExposureTime",))["ExposureTime"] == pytest.approx(TIMES[0])
    code, _, err = cli_run("merge-brackets", *paths, "--out", tmp_path / "exif.exr")
    assert code == 0, err
    code, _, err = cli_run("merge-brackets", *paths, "--out", tmp_path / "given.exr",
                           "--times", ",".join(f"{t!r}" for t in TIMES))
    assert code == 0, err
    assert io.read_json(tmp_path / "exif.json")["times_from"] == "EXIF ExposureTime"
    assert (tmp_path / "exif.exr").read_bytes() == (tmp_path / "given.exr").read_bytes()


def _last(err: str) -> str:
    return err.rstrip("\n").splitlines()[-1]


def test_bad_bracket_sets_are_one_line_and_write_nothing(brackets, tmp_path, cli_run):
    photo, paths = brackets
    out = tmp_path / "o.exr"
    code, _, err = cli_run("merge-brackets", *paths, "--out", out)            # PNGs carry no exposure time
    assert code == 1 and _last(err) == f"pcrelight: {paths[0]}: no exposure time in its EXIF (ExposureTime): " \
                                       "give every photo's with --times"
    code, _, err = cli_run("merge-brackets", *paths, "--out", out, "--times", "1,2")
    assert code == 2 and "--times gives 2 exposure time(s) for 5 photos" in _last(err)
    code, _, err = cli_run("merge-brackets", *paths[:2], "--out", out, "--times", "1,-2")
    assert code == 2 and "--times must all be > 0" in _last(err)
    code, _, err = cli_run("merge-brackets", paths[0], "--out", out, "--times", "1")
    assert code == 2 and "two or more photos" in _last(err)
    small = tmp_path / "small.png"
    _write(small, _response(photo[:32, :32]))
    code, _, err = cli_run("merge-brackets", paths[0], small, "--out", out, "--times", "1,2")
    assert code == 1 and _last(err).startswith(f"pcrelight: {small}: size 32x32 differs")
    code, _, err = cli_run("merge-brackets", paths[0], SAMPLES / "photo.exr", "--out", out, "--times", "1,2")
    assert code == 1 and "an HDR image, not a bracket shot" in _last(err)
    assert not out.exists() and not (tmp_path / "o.json").exists()
