"""Colour: the one place for luminance, the sRGB transfer functions and the exposure of Eq. 1.

Conventions: RGB is linear Rec.709 / sRGB primaries (D65); luminance is CIE Y (colour-science's row
of the sRGB → XYZ matrix: 0.2126, 0.7152, 0.0722, held here as constants); sRGB encoding is IEC 61966-2-1
(colour-science's ``eotf_inverse_sRGB`` / ``eotf_sRGB``, bit-identical to the piecewise formula on float64). This
module imports nothing of pcrelight, so ``io`` → ``display`` → ``color`` has no loop.
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.typing import DTypeLike


# The CIE Y row of the linear sRGB (Rec.709 primaries, D65) → XYZ matrix, float64: colour-science's
# ``colour.models.RGB_COLOURSPACE_sRGB.matrix_RGB_to_XYZ[1]`` exactly (tests/test_color.py checks it bit for bit).
# A constant, so that the stages need not import colour-science (~1–2 s) for the luminance alone.
REC709_Y = (0.2126, 0.7152, 0.0722)


@functools.cache
def y_weights() -> np.ndarray:
    """The CIE Y weights of linear Rec.709 RGB (:data:`REC709_Y`), float64 (3,), read-only."""
    w = np.asarray(REC709_Y, dtype=np.float64)
    w.setflags(write=False)
    return w


def luminance(rgb: np.ndarray, dtype: DTypeLike = np.float32) -> np.ndarray:
    """CIE Y of linear RGB (..., 3) → (...), computed and returned in ``dtype`` (the input and the
    weights are cast to it first: float32 by default, float64 where the caller works in float64)."""
    return np.asarray(rgb, dtype=dtype) @ y_weights().astype(dtype)


def radiance_scale(rgb: np.ndarray) -> float:
    """The cloud's own radiance unit: the median CIE Y (float64) of its points with Y > 0, or 1.0 when none has
    any light. Thresholds on radiance that are multiples of it (build-bsh's t_c) make the result independent of
    the radiance's unit: scaling every colour by c scales it by c (to float rounding), and a dark majority of
    black points does not zero it."""
    y = luminance(np.asarray(rgb).reshape(-1, 3), np.float64)
    y = y[y > 0]
    return float(np.median(y)) if y.size else 1.0


# The overexposure threshold t_l on LDR luminance (the core paper's 0.9): the one definition; the stages' ``t_l``
# options default to it, and make-scene's truth, import's warning, expose-match's log and the registration's
# saturated pixels use it.
T_L = 0.9


# an LDR channel at the top of its range: clipped (its true value unknown), whatever the luminance; the photo
# registration drops or down-weights such points and pixels
CLIPPED = 0.99


def clipped_mask(rgb: np.ndarray) -> np.ndarray:
    """(...) bool: the colours (..., 3 or more channels, linear LDR) with a channel ≥ :data:`CLIPPED`."""
    return np.asarray(rgb)[..., :3].max(axis=-1) >= CLIPPED


def overexposed_mask(colors: np.ndarray, t_l: float = T_L) -> np.ndarray:
    """(N,) bool: the points whose LDR luminance (CIE Y of linear RGB, float32) exceeds ``t_l`` (default
    :data:`T_L`)."""
    return luminance(colors) > t_l


def srgb_encode(v: np.ndarray, dtype: DTypeLike = np.float32) -> np.ndarray:
    """Linear values, clipped to [0, 1] → sRGB-encoded [0, 1] (computed in float64, returned in ``dtype``): IEC
    61966-2-1's piecewise curve, bit for bit colour-science's ``eotf_inverse_sRGB`` (tests/test_color.py), written
    out so that writing a PNG does not import colour-science (~1.1 s of every relight)."""
    x = np.clip(np.asarray(v, dtype=np.float64), 0.0, 1.0)
    return np.asarray(np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055), dtype=dtype)


def srgb_decode(v: np.ndarray, dtype: DTypeLike = np.float32) -> np.ndarray:
    """sRGB-encoded values in [0, 1] → linear (computed in float64, returned in ``dtype``): the inverse curve,
    bit for bit colour-science's ``eotf_sRGB`` (tests/test_color.py)."""
    x = np.asarray(v, dtype=np.float64)
    return np.asarray(np.where(x <= 12.92 * 0.0031308, x / 12.92, np.power((x + 0.055) / 1.055, 2.4)), dtype=dtype)


def apply_exposure(photo: np.ndarray, alpha: float) -> np.ndarray:
    """Eq. 1 of the core paper: clamp(α · I_HDR, 0, 1) per channel of the first three channels,
    computed in float64, returned as float32 (what photo_ldr.exr stores)."""
    return np.clip(np.asarray(photo[..., :3], dtype=np.float64) * alpha, 0.0, 1.0).astype(np.float32)
