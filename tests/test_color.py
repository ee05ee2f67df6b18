"""pipeline/color.py: the one luminance, sRGB and exposure, bit-identical to the arithmetic each
module used before; and no import loop through io/display."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import colour
import numpy as np
import pytest

from pipeline import color

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def samples():
    rng = np.random.default_rng(3)
    rgb = np.concatenate([rng.random((20000, 3)), rng.random((20000, 3)) * 1e-3, rng.random((20000, 3)) * 50.0])
    grid = np.linspace(0.0, 1.0, 200001)
    return rgb, grid


def test_luminance_float32_and_float64_are_the_former_formulas_bit_for_bit(samples):
    rgb, _ = samples
    w = colour.models.RGB_COLOURSPACE_sRGB.matrix_RGB_to_XYZ[1]
    was_io = (np.asarray(rgb, dtype=np.float32) @ w.astype(np.float32)).astype(np.float32)  # io.luminance
    was_itmo = np.asarray(rgb, dtype=np.float64) @ np.asarray(w, dtype=np.float64)          # itmo.luminance
    y32, y64 = color.luminance(rgb), color.luminance(rgb, np.float64)
    assert y32.dtype == np.float32 and y64.dtype == np.float64
    assert np.array_equal(y32, was_io) and np.array_equal(y64, was_itmo)
    np.testing.assert_allclose(color.luminance(np.eye(3)), [0.2126, 0.7152, 0.0722], atol=1e-4)


def test_y_weights_are_colour_sciences_row_bit_for_bit_without_importing_it():
    """color.REC709_Y (a constant: importing colour-science costs 1–2 s of every stage's start) is exactly
    colour-science's CIE Y row of the linear sRGB → XYZ matrix; luminance needs no colour-science import."""
    w = colour.models.RGB_COLOURSPACE_sRGB.matrix_RGB_to_XYZ[1]
    assert w.dtype == color.y_weights().dtype == np.float64
    assert np.array_equal(color.y_weights(), w) and color.y_weights().tobytes() == np.asarray(w).tobytes()
    code = ("import sys, numpy as np; from pipeline import color; color.luminance(np.ones((4, 3))); "
            "color.overexposed_mask(np.ones((4, 3)), 0.9); color.srgb_encode(np.ones(3)); color.srgb_decode(np.ones(3)); "
            "print('colour' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.strip() == "False"


def test_srgb_is_colour_science_and_the_piecewise_formula_bit_for_bit(samples):
    _, x = samples
    piecewise = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)  # former itmo.srgb_encode
    assert np.array_equal(color.srgb_encode(x, np.float64), piecewise)
    assert np.array_equal(color.srgb_encode(x), np.asarray(colour.models.eotf_inverse_sRGB(x), np.float32))
    assert np.array_equal(color.srgb_encode(np.array([-1.0, 2.0])), np.array([0.0, 1.0], np.float32))  # clipped
    assert np.array_equal(color.srgb_decode(x), np.asarray(colour.models.eotf_sRGB(x), np.float32))
    np.testing.assert_allclose(color.srgb_decode(color.srgb_encode(x, np.float64), np.float64), x, atol=1e-12)


def test_exposure_is_eq1_and_the_stages_share_it():
    from pipeline.expansion import expose_match, patchmatch

    photo = np.array([[[0.5, 2.0, -1.0, 7.0]]], np.float32)  # a 4th channel is ignored
    out = color.apply_exposure(photo, 0.8)
    assert out.dtype == np.float32 and out.shape == (1, 1, 3)
    assert np.array_equal(out, np.float32([[[0.4, 1.0, 0.0]]]))
    assert expose_match.apply_exposure is color.apply_exposure is patchmatch.apply_exposure


def test_one_definition_of_each_colour_function():
    from pipeline import display, io
    from pipeline.expansion import itmo, reproject

    assert io.luminance is itmo.luminance is reproject.luminance is display.luminance is color.luminance
    assert io.srgb_encode is itmo.srgb_encode is color.srgb_encode and io.srgb_decode is color.srgb_decode


def test_no_import_loop_through_io_and_display():
    tree = ast.parse((ROOT / "pipeline" / "color.py").read_text())
    relative = [n for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.level > 0]
    assert relative == []  # color imports nothing of pcrelight
    code = "import sys, pipeline.display; print('pipeline.io' in sys.modules)"
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert r.stdout.strip() == "False"  # display no longer needs io
