"""Shared fixtures: a fresh GL context per test (skips cleanly without EGL), a CLI runner,
and paths to the shipped sample and ../shared."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "data_samples"
SHARED = ROOT.parent / "shared"


@pytest.fixture(autouse=True, scope="session")
def _cache_folder(tmp_path_factory):
    """The tests' cache folder (pipeline.io.cache.cache_dir: relight's object BSHs) is their own, not ~/.cache."""
    from pipeline.io.cache import CACHE_ENV

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(CACHE_ENV, str(tmp_path_factory.mktemp("cache")))
        yield


@pytest.fixture
def gl_context():
    """A fresh standalone EGL context with a bound 1×1 framebuffer; released afterwards."""
    from pipeline import gl
    from pipeline.errors import GLUnavailable

    try:
        ctx = gl.create_context()
    except GLUnavailable as e:
        pytest.skip(f"no headless GL: {e}")
    gl.bind_dummy_framebuffer(ctx)
    yield ctx
    ctx.release()


@pytest.fixture
def cli_run():
    """Run the real CLI in-process: ``cli_run("build-bsh", "x.ply", "--out", "y.npz")`` →
    (exit_code, stdout, stderr)."""
    from click.testing import CliRunner

    import cli

    def run(*args: str):
        r = CliRunner().invoke(cli.main, [str(a) for a in args], catch_exceptions=False)
        return r.exit_code, r.stdout, r.stderr

    return run


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    """The make-scene ``tiny`` preset (seed 0: scene.json, clouds, photo, truth/ references),
    built once per session into a temp folder — or taken from ``$PCRELIGHT_TINY`` (built there
    first if that folder has no scene.json yet). Returns the folder (Path)."""
    import os

    from pipeline.scene.make_scene import apply_preset, run_make_scene

    env = os.environ.get("PCRELIGHT_TINY")
    out = Path(env) if env else tmp_path_factory.mktemp("tiny_scene")
    if not (out / "scene.json").exists():
        run_make_scene(out, apply_preset("tiny", {}), preview=False)
    return out


def write_exif_photo(path: Path, rgb: np.ndarray, focal_35mm: float) -> Path:
    """An EXR photo (H, W, 3) carrying the EXIF tag FocalLengthIn35mmFilm [mm] (what phones write)."""
    import OpenImageIO as oiio

    h, w = rgb.shape[:2]
    spec = oiio.ImageSpec(w, h, 3, "float")
    spec.attribute("Exif:FocalLengthIn35mmFilm", focal_35mm)
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), spec)
    out.write_image(np.ascontiguousarray(rgb, np.float32))
    out.close()
    return path


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """Say it in the summary when the report's browser tests could not run (no Chromium and no
    PCRELIGHT_REQUIRE_CHROMIUM, which `.ci/run` sets as root): a plain `make test` would otherwise pass them by."""
    import os
    import shutil

    if not (shutil.which("chromium") or shutil.which("chromium-browser")) and not os.environ.get("PCRELIGHT_REQUIRE_CHROMIUM"):
        terminalreporter.write_line("pcrelight: chromium is not installed: the run report's browser tests "
                                    "(tests/test_report.py) were SKIPPED — apt-get install chromium, or set "
                                    "PCRELIGHT_REQUIRE_CHROMIUM=1 to make them fail", yellow=True)
