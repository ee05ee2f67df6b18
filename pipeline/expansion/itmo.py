"""Inverse tone-mapping operators (ITMOs): the baselines of seed 000 §6.2 / Table 2.

Pure functions on arrays of **linear** Rec.709 RGB in **LDR units** (1.0 = LDR white, the
clipping level of the LDR cloud / rendering).  Inputs of shape (..., 3): an image (H, W, 3) or a
point list (N, 3).  Outputs are linear RGB in the same units, never NaN/inf (0 stays 0).

Operators and the space each one works in
-----------------------------------------
* ``landis`` — Landis 2002, "Production-ready global illumination", SIGGRAPH 2002 course 16
  (the "LANDIS" row).  Works on the **linear** luminance Y (CIE Y of linear sRGB).  Formula as in
  Banterle's HDR Toolbox ``LandisEO.m``::

      t   = ((L - R) / (L_in_max - R)) ** a          for L >= R, else 0
      L_w = L * (1 - t) + L_max * L * t

  Defaults of the toolbox: a = 2, R = 0.5.  The toolbox normalises by the image's max(L); we use
  ``L_in_max = 1`` (LDR white) so that faces and point lists are expanded identically (they agree
  whenever the input holds one clipped pixel).  ``L_max`` (the toolbox default 3000 is in cd/m² of a
  display) is the peak output in LDR units — the pipeline passes the photo's peak α·max Y(photo)
  (:func:`photo_peak`), the most favourable value a blind operator could be given.

* ``banterle`` — Banterle, Ledda, Debattista, Chalmers 2006, "Inverse tone mapping", GRAPHITE
  2006 (the "BANTERLE" row, "expand map").  Works on the **linear** luminance.  The inverse of the
  Reinhard et al. 2002 global photographic operator (toolbox ``InverseReinhard.m``)::

      L_w = L_white * L_max / 2 * (L - 1 + sqrt((1 - L)^2 + 4 L / L_white^2))      (L in [0, 1])

  (L_w(0) = 0, L_w(1) = L_max, slope L_max / L_white at black), blended with the LDR luminance by
  an *expand map* Λ in [0, 1]:  L_final = L (1 - Λ) + L_w Λ.  Λ: median-cut light samples of the
  image (2^round(log2(min(H,W)) + 2) samples, as the toolbox), their density estimated with a
  Gaussian kernel (σ from the toolbox window = min(H,W) / (2 sqrt(n))), normalised to max 1, then
  an edge-aware transfer guided by the LDR luminance.  Deviation: the edge transfer uses the guided
  filter (He et al. 2010) instead of the paper's cross-bilateral filter (same role, box filters
  only).  The toolbox demo uses L_max = 2000, L_white = 1000 cd/m²; in LDR units we default to
  L_white = L_max, so that the slope at black is 1 (well-exposed values stay ≈ unchanged and the
  curve is the exact inverse of L/(1+L) far below white).  For a point list (``banterle-pc``)
  :func:`expand_map_points` is the 3-D analogue: a Gaussian-weighted density of the luminance over
  the k nearest neighbours, normalised to max 1 (no edge transfer).

* ``rhee`` — Rhee et al. 2017 (seed 002 §4, Eq. 1–3)::

      L_i = 0.3 R' + 0.59 G' + 0.11 B'      (R', G', B' = display-encoded values in [0, 1])
      L_s = 10 L_i^10 + 1.8
      [R_o, G_o, B_o] = L_s [R, G, B]

  The luminance is computed, as published, on the **display-encoded** (sRGB transfer function)
  8-bit-style values with 002's weights; the gain is applied to the **linear** RGB (our radiance).
  Note the gain 1.8 at black: the operator brightens everything (as published).

All three are monotone non-decreasing in the input luminance for a fixed chromaticity (tests check
it) and finite on [0, 1].  Inputs above 1 (not LDR) are clipped to 1 before the operator.
"""
from __future__ import annotations

import numpy as np

from ..color import luminance, srgb_encode

RHEE_WEIGHTS = np.array([0.3, 0.59, 0.11])
METHODS = ("landis", "banterle", "rhee")

LANDIS_ALPHA = 2.0
LANDIS_THRESHOLD = 0.5


def _ldr(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb, dtype=np.float64)
    if rgb.shape[-1] != 3:
        raise ValueError(f"expected (..., 3) RGB, got shape {rgb.shape}")
    return np.clip(np.nan_to_num(rgb, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)


def change_luminance(rgb: np.ndarray, lum_old: np.ndarray, lum_new: np.ndarray) -> np.ndarray:
    """Scale RGB so that its luminance goes from lum_old to lum_new (chromaticity kept); 0 stays 0."""
    lum_old = np.asarray(lum_old, dtype=np.float64)
    safe = lum_old > 0.0
    ratio = np.where(safe, np.asarray(lum_new, dtype=np.float64) / np.where(safe, lum_old, 1.0), 0.0)
    return np.asarray(rgb, dtype=np.float64) * ratio[..., None]


def photo_peak(photo_hdr: np.ndarray, alpha: float) -> float:
    """The photo's peak luminance in the cloud's LDR units: α · max Y(photo) (at least 1)."""
    y = luminance(np.nan_to_num(np.asarray(photo_hdr, dtype=np.float64)[..., :3], nan=0.0, posinf=0.0), np.float64)
    return float(max(1.0, alpha * float(y.max(initial=0.0))))


# ----------------------------------------------------------------------------------------- Landis
def landis_curve(L, max_luminance: float, alpha: float = LANDIS_ALPHA,
                 threshold: float = LANDIS_THRESHOLD, l_in_max: float = 1.0) -> np.ndarray:
    """Landis 2002 luminance expansion (linear luminance, LDR units -> LDR units)."""
    if max_luminance < 1.0:
        raise ValueError(f"max_luminance must be ≥ 1 (LDR white), got {max_luminance}")
    if not 0.0 <= threshold < l_in_max:
        raise ValueError(f"threshold must be in [0, {l_in_max}), got {threshold}")
    if alpha <= 0:
        raise ValueError(f"alpha must be > 0, got {alpha}")
    L = np.clip(np.asarray(L, dtype=np.float64), 0.0, l_in_max)
    t = np.clip((L - threshold) / (l_in_max - threshold), 0.0, 1.0) ** alpha
    return L * (1.0 - t) + max_luminance * L * t


def landis(rgb, max_luminance: float, alpha: float = LANDIS_ALPHA,
           threshold: float = LANDIS_THRESHOLD) -> np.ndarray:
    """Landis 2002 applied to linear RGB (..., 3): the luminance is expanded, chromaticity kept."""
    x = _ldr(rgb)
    L = luminance(x, np.float64)
    return change_luminance(x, L, landis_curve(L, max_luminance, alpha, threshold))


# --------------------------------------------------------------------------------------- Banterle
def inverse_reinhard(L, max_luminance: float, l_white: float | None = None) -> np.ndarray:
    """Inverse of the Reinhard 2002 global operator (Banterle 2006 Eq. / toolbox InverseReinhard.m).

    L: linear LDR luminance in [0, 1]; returns luminance in LDR units, 0 -> 0, 1 -> max_luminance.
    """
    if max_luminance < 1.0:
        raise ValueError(f"max_luminance must be ≥ 1 (LDR white), got {max_luminance}")
    w = float(max_luminance if l_white is None else l_white)
    if w <= 0:
        raise ValueError(f"l_white must be > 0, got {w}")
    L = np.clip(np.asarray(L, dtype=np.float64), 0.0, 1.0)
    return w * max_luminance / 2.0 * (L - 1.0 + np.sqrt((1.0 - L) ** 2 + 4.0 * L / (w * w)))


def _box(x: np.ndarray, r: int) -> np.ndarray:
    from scipy.ndimage import uniform_filter

    return uniform_filter(x, size=2 * r + 1, mode="reflect")


def guided_filter(guide: np.ndarray, src: np.ndarray, radius: int, eps: float = 1e-3) -> np.ndarray:
    """Grey guided filter (He, Sun, Tang 2010): edge-aware smoothing of src steered by guide."""
    mI, mp = _box(guide, radius), _box(src, radius)
    cov = _box(guide * src, radius) - mI * mp
    var = _box(guide * guide, radius) - mI * mI
    a = cov / (var + eps)
    b = mp - a * mI
    return _box(a, radius) * guide + _box(b, radius)


def median_cut(L: np.ndarray, n_samples: int) -> np.ndarray:
    """Median-cut light samples (Debevec 2005) of a luminance image (H, W).

    Splits regions along their longer side into halves of equal luminance sum until n_samples
    regions (a power of two); returns (n, 3) [x, y, power] with (x, y) the luminance centroid in
    pixels.  Uses a summed-area table; the loop is over regions (≤ a few thousand), not pixels.
    """
    H, W = L.shape
    sat = np.zeros((H + 1, W + 1))
    sat[1:, 1:] = np.cumsum(np.cumsum(L, 0), 1)
    satx = np.zeros((H + 1, W + 1))  # for centroids: sum of L*x and L*y
    saty = np.zeros((H + 1, W + 1))
    xs = np.arange(W) + 0.5
    ys = (np.arange(H) + 0.5)[:, None]
    satx[1:, 1:] = np.cumsum(np.cumsum(L * xs, 0), 1)
    saty[1:, 1:] = np.cumsum(np.cumsum(L * ys, 0), 1)

    def rsum(s, y0, y1, x0, x1):
        return s[y1, x1] - s[y0, x1] - s[y1, x0] + s[y0, x0]

    regions = [(0, H, 0, W)]
    levels = int(round(np.log2(max(1, n_samples))))
    for _ in range(levels):
        nxt = []
        for (y0, y1, x0, x1) in regions:
            h, w = y1 - y0, x1 - x0
            if max(h, w) < 2:
                nxt.append((y0, y1, x0, x1))
                continue
            if w >= h:
                cs = sat[y1, x0 + 1:x1] - sat[y0, x0 + 1:x1] - sat[y1, x0] + sat[y0, x0]
                tot = rsum(sat, y0, y1, x0, x1)
                k = int(np.searchsorted(cs, tot / 2.0)) + 1 if tot > 0 else w // 2
                k = min(max(k, 1), w - 1)
                nxt += [(y0, y1, x0, x0 + k), (y0, y1, x0 + k, x1)]
            else:
                cs = sat[y0 + 1:y1, x1] - sat[y0 + 1:y1, x0] - sat[y0, x1] + sat[y0, x0]
                tot = rsum(sat, y0, y1, x0, x1)
                k = int(np.searchsorted(cs, tot / 2.0)) + 1 if tot > 0 else h // 2
                k = min(max(k, 1), h - 1)
                nxt += [(y0, y0 + k, x0, x1), (y0 + k, y1, x0, x1)]
        regions = nxt
    out = np.zeros((len(regions), 3))
    for i, (y0, y1, x0, x1) in enumerate(regions):
        p = rsum(sat, y0, y1, x0, x1)
        if p > 0:
            out[i] = (rsum(satx, y0, y1, x0, x1) / p, rsum(saty, y0, y1, x0, x1) / p, p)
        else:
            out[i] = ((x0 + x1) / 2.0, (y0 + y1) / 2.0, 0.0)
    return out


def expand_map_image(rgb: np.ndarray, n_samples: int | None = None) -> np.ndarray:
    """Banterle 2006 expand map Λ (H, W) in [0, 1] of a linear LDR image (H, W, 3)."""
    from scipy.ndimage import gaussian_filter

    x = _ldr(rgb)
    L = luminance(x, np.float64)
    H, W = L.shape
    if L.max(initial=0.0) <= 0.0:
        return np.zeros((H, W))
    if n_samples is None:
        n_samples = int(2 ** round(np.log2(min(H, W)) + 2))
    samples = median_cut(L, n_samples)
    samples = samples[samples[:, 2] > 0]
    counts = np.zeros((H, W))
    xi = np.clip(samples[:, 0].astype(np.int64), 0, W - 1)
    yi = np.clip(samples[:, 1].astype(np.int64), 0, H - 1)
    np.add.at(counts, (yi, xi), 1.0)
    window = max(1.0, min(H, W) / (2.0 * np.sqrt(n_samples)))
    density = gaussian_filter(counts, sigma=2.0 * window, mode="constant")
    if density.max() > 0:
        density /= density.max()
    lam = guided_filter(L, density, radius=max(1, int(round(window))), eps=1e-3)
    lam = np.clip(lam, 0.0, None)
    m = lam.max(initial=0.0)
    return lam / m if m > 0 else lam


def expand_map_points(points: np.ndarray, rgb: np.ndarray, k: int = 32, sigma: float | None = None,
                      threshold: float = 0.0) -> np.ndarray:
    """3-D analogue of the expand map for ``banterle-pc``: Λ(p) = Σ_q g(|p-q|) L_q / Σ_q g, over the
    k nearest neighbours q (Gaussian g of width sigma, default the median k-th neighbour distance
    / 2), with L_q = Y(q) where Y(q) ≥ threshold else 0; normalised to max 1."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, dtype=np.float64)
    L = luminance(_ldr(rgb), np.float64)
    L = np.where(L >= threshold, L, 0.0)
    n = len(pts)
    if n == 0 or L.max(initial=0.0) <= 0:
        return np.zeros(n)
    k = int(min(k, n))
    d, idx = cKDTree(pts).query(pts, k=k)
    d = d.reshape(n, k)
    idx = idx.reshape(n, k)
    if sigma is None:
        sigma = max(float(np.median(d[:, -1])) / 2.0, 1e-12)
    g = np.exp(-0.5 * (d / sigma) ** 2)
    lam = (g * L[idx]).sum(1) / np.maximum(g.sum(1), 1e-300)
    return lam / lam.max()


def banterle(rgb, max_luminance: float, l_white: float | None = None,
             expand_map: np.ndarray | None = None) -> np.ndarray:
    """Banterle 2006: L_final = L (1 - Λ) + inverse_reinhard(L) Λ, applied to linear RGB (..., 3).

    expand_map: Λ with the shape of rgb[..., 0]; None -> :func:`expand_map_image` for an image
    (H, W, 3), or Λ = 1 (the plain inverse operator) for any other shape (pass
    :func:`expand_map_points` for a point list).
    """
    x = _ldr(rgb)
    L = luminance(x, np.float64)
    if expand_map is None:
        expand_map = expand_map_image(x) if x.ndim == 3 else np.ones_like(L)
    lam = np.clip(np.asarray(expand_map, dtype=np.float64), 0.0, 1.0)
    if lam.shape != L.shape:
        raise ValueError(f"expand map shape {lam.shape} != image shape {L.shape}")
    Lw = inverse_reinhard(L, max_luminance, l_white)
    return change_luminance(x, L, L * (1.0 - lam) + Lw * lam)


# ------------------------------------------------------------------------------------------- Rhee
def rhee_gain(rgb) -> np.ndarray:
    """002 Eq. 1-2: L_s = 10 L_i^10 + 1.8, L_i from display-encoded RGB with weights 0.3/0.59/0.11."""
    Li = srgb_encode(_ldr(rgb), np.float64) @ RHEE_WEIGHTS
    return 10.0 * Li ** 10 + 1.8


def rhee(rgb) -> np.ndarray:
    """Rhee et al. 2017 (002 Eq. 3): linear RGB times the gain L_s."""
    x = _ldr(rgb)
    return x * rhee_gain(x)[..., None]


def apply(method: str, rgb, max_luminance: float = 1.0, points: np.ndarray | None = None,
          **kw) -> np.ndarray:
    """Dispatch: method in landis|banterle|rhee.  For banterle on a point list pass ``points`` to
    use :func:`expand_map_points`; on an image the image expand map is used."""
    if method == "landis":
        return landis(rgb, max_luminance, **kw)
    if method == "banterle":
        em = kw.pop("expand_map", None)
        if em is None and points is not None:
            em = expand_map_points(points, rgb)
        return banterle(rgb, max_luminance, expand_map=em, **kw)
    if method == "rhee":
        return rhee(rgb)
    raise ValueError(f"unknown ITMO {method!r}; expected one of {METHODS}")
