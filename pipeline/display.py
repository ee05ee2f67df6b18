"""Display end (seed 004): Reinhard's global operator with automatic exposure, bloom, vignette.

Input is linear HDR RGB (float32); output is display-referred, sRGB-encoded, in [0,1].
EXR outputs are never tone-mapped; only previews and ``relit.png`` go through here.
"""

from __future__ import annotations

import numpy as np

from .color import luminance, srgb_encode

_EPS = 1e-6


def auto_key(lum: np.ndarray) -> float:
    """Reinhard (2002, "Parameter estimation for photographic tone reproduction") key:
    a = 0.18 · 4^((2·log2 Lavg − log2 Lmin − log2 Lmax) / (log2 Lmax − log2 Lmin)),
    with Lavg the log-average luminance and Lmin/Lmax robust (1st/99th percentile) extremes."""
    l = lum[np.isfinite(lum) & (lum > 0)]
    if l.size == 0:
        return 0.18
    l2 = np.log2(l.astype(np.float64) + _EPS)
    lavg, lmin, lmax = l2.mean(), np.percentile(l2, 1), np.percentile(l2, 99)
    if lmax - lmin < 1e-6:
        return 0.18
    return float(0.18 * 4.0 ** ((2 * lavg - lmin - lmax) / (lmax - lmin)))


def bloom(rgb: np.ndarray, strength: float, lavg: float, levels: int = 4) -> np.ndarray:
    """Bright pass (luminance above the log-average), separable Gaussian blur on successively
    halved resolutions, summed back with equal weights × ``strength`` (seed 004 §2.4)."""
    if strength <= 0:
        return rgb
    from scipy import ndimage  # here: importing scipy.ndimage costs ~0.3 s of every relight, and bloom is opt-in

    lum = luminance(rgb)
    bright = rgb * (lum > lavg)[..., None]
    acc = np.zeros_like(rgb)
    cur = bright
    for lev in range(levels):
        blurred = ndimage.gaussian_filter(cur, sigma=(2.0, 2.0, 0))
        zoom = (rgb.shape[0] / blurred.shape[0], rgb.shape[1] / blurred.shape[1], 1)
        acc += ndimage.zoom(blurred, zoom, order=1)[: rgb.shape[0], : rgb.shape[1]] if lev else blurred
        if min(cur.shape[:2]) < 4:
            break
        cur = blurred[::2, ::2]
    return rgb + strength * acc / levels


def vignette(img: np.ndarray, strength: float) -> np.ndarray:
    """Darken towards the corners: factor 1 − strength·r², r = normalised distance to the centre."""
    if strength <= 0:
        return img
    h, w = img.shape[:2]
    y, x = np.mgrid[0:h, 0:w]
    r2 = ((x - (w - 1) / 2) / (w / 2)) ** 2 + ((y - (h - 1) / 2) / (h / 2)) ** 2
    return img * np.clip(1.0 - strength * r2 / 2.0, 0.0, 1.0)[..., None]


def auto_exposure(rgb: np.ndarray, mask: np.ndarray | None = None, key: float | None = None) -> tuple[float, float]:
    """(exposure, log-average luminance): exposure = key / Lavg over the ``mask`` pixels."""
    lum = luminance(rgb)
    sel = lum[mask] if mask is not None else lum.reshape(-1)
    sel = sel[sel > 0]
    lavg = float(np.exp(np.mean(np.log(sel.astype(np.float64) + _EPS)))) if sel.size else 1.0
    a = auto_key(sel) if key is None else key
    return a / max(lavg, _EPS), lavg


def reinhard(hdr: np.ndarray, mask: np.ndarray | None = None, key: float | None = None,
             exposure: float | None = None, bloom_strength: float = 0.0) -> np.ndarray:
    """Reinhard's global operator RGB/(1+RGB) per channel (seed 004 Eq. 2) after automatic
    exposure; returns linear display values in [0,1]."""
    rgb = np.maximum(np.nan_to_num(np.asarray(hdr, dtype=np.float32)), 0.0)
    auto, lavg = auto_exposure(rgb, mask, key)
    x = bloom(rgb, bloom_strength, lavg) * (auto if exposure is None else exposure)
    return x / (1.0 + x)


def tonemap(rgb: np.ndarray, mask: np.ndarray | None = None, key: float | None = None,
            exposure: float | None = None, bloom_strength: float = 0.0, vignette_strength: float = 0.0) -> np.ndarray:
    """Linear HDR (H,W,3) → sRGB-encoded [0,1]: :func:`reinhard`, optional bloom and vignette."""
    x = reinhard(rgb, mask, key, exposure, bloom_strength)
    return srgb_encode(vignette(x, vignette_strength))


def side_by_side(images: list[np.ndarray], exposure_from: int = 0, key: float | None = None) -> np.ndarray:
    """Linear HDR renders of one view, (H, W, 4) with alpha = coverage (or (H, W, 3): all covered), left to right
    as one sRGB-encoded (H, n·W, 3) row at one exposure: the automatic one of ``images[exposure_from]`` over its
    covered pixels (:func:`auto_exposure`), so that equal radiance is equal grey in every panel; uncovered pixels
    black. All images must have the same height and width."""
    if not images:
        raise ValueError("side_by_side: no images")
    shapes = {tuple(np.shape(a)[:2]) for a in images}
    if len(shapes) != 1:
        raise ValueError(f"side_by_side: images of different sizes {sorted(shapes)}")

    def split(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a = np.asarray(a, np.float32)
        cover = a[..., 3] > 0.5 if a.shape[2] >= 4 else np.ones(a.shape[:2], bool)
        return np.maximum(np.nan_to_num(a[..., :3]), 0.0) * cover[..., None], cover

    rgb, cover = split(images[exposure_from])
    expo, _ = auto_exposure(rgb, cover if cover.any() else None, key)
    return np.concatenate([tonemap(split(a)[0], exposure=expo) for a in images], axis=1)
