"""Error metrics against a reference, one home for every measurement (evaluate's Table 2, make-scene's checks of
its own truth, trade, the benches): cloud colour errors, block means of images, relative RMS and mean ratio of
block means with the reference's own noise, z-scores of two noisy estimates, SSIM. Linear Rec.709 values; block
sizes in pixels."""

from __future__ import annotations

from typing import Any

import numpy as np

_LOG_EPS = 1e-4  # [LDR units] floor of log10 luminance (1/10000 of LDR white)


def cloud_metrics(colors: np.ndarray, truth: np.ndarray, over: np.ndarray,
                  in_range: np.ndarray | None = None, visible: np.ndarray | None = None) -> dict[str, float]:
    """RMS (all points, overexposed points, overexposed points whose true luminance lies within the
    photo's range, overexposed points the photo sees) and log10-luminance RMS, inputs in LDR units."""
    from .color import luminance

    d2 = (colors.astype(np.float64) - truth.astype(np.float64)) ** 2
    ly = np.log10(np.maximum(luminance(colors), _LOG_EPS)) - np.log10(np.maximum(luminance(truth), _LOG_EPS))
    over = over.astype(bool)
    sel = over & in_range if in_range is not None else None
    return {
        "cloud_rms": float(np.sqrt(d2.mean())),
        "cloud_rms_over": float(np.sqrt(d2[over].mean())) if over.any() else float("nan"),
        **({"cloud_rms_over_in_range": float(np.sqrt(d2[sel].mean())) if sel.any() else float("nan"),
            "n_over_in_range": int(sel.sum())} if sel is not None else {}),
        **({"cloud_rms_over_visible": float(np.sqrt(d2[over & visible].mean())) if (over & visible).any() else float("nan"),
            "n_over_visible": int((over & visible).sum())} if visible is not None else {}),
        "log_rms": float(np.sqrt(np.mean(ly.astype(np.float64) ** 2))),
        "n_points": int(len(colors)),
        "n_over": int(over.sum()),
    }


def precise_metrics(colors: np.ndarray, precise: dict[str, np.ndarray], e: float, over: np.ndarray,
                    in_range: np.ndarray | None = None) -> dict[str, float]:
    """The cloud against ``truth/cloud_precise.npz`` (a subset of points re-baked to a few % with
    independent paths), in LDR units (× e): RMS on the subset, on its overexposed points and on
    those within the photo's range, each with the precise truth's own noise there (√mean
    variance; subtract it in quadrature to judge)."""
    idx = precise["index"]
    d2 = (colors[idx].astype(np.float64) - e * precise["colors"]) ** 2
    v = precise["var"] * e * e
    o = over.astype(bool)[idx]
    sets = {"": np.ones(len(idx), bool), "_over": o}
    if in_range is not None:
        sets["_over_in_range"] = o & in_range.astype(bool)[idx]
    out: dict[str, float] = {}
    for suf, m in sets.items():
        out[f"precise_rms{suf}"] = float(np.sqrt(d2[m].mean())) if m.any() else float("nan")
        out[f"precise_noise{suf}"] = float(np.sqrt(v[m].mean())) if m.any() else float("nan")
        out[f"n_precise{suf}"] = int(m.sum())
    return out


def _block_sums(img: np.ndarray, mask: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Per k×k block (tiled from the top-left corner; a partial last row/column of blocks is
    dropped): the sum of ``img`` over the block's pixels inside ``mask`` (nb, C) and their count (nb,)."""
    a = np.asarray(img, np.float64)
    a = a[..., None] if a.ndim == 2 else a
    m = np.asarray(mask, bool)
    h, w = (m.shape[0] // k) * k, (m.shape[1] // k) * k
    mm = m[:h, :w]
    s = (a[:h, :w] * mm[..., None]).reshape(h // k, k, w // k, k, a.shape[-1]).sum(axis=(1, 3))
    n = mm.reshape(h // k, k, w // k, k).sum(axis=(1, 3))
    return s.reshape(-1, a.shape[-1]), n.reshape(-1)


def block_means(img: np.ndarray, mask: np.ndarray, k: int, min_pixels: int | None = None) -> np.ndarray:
    """Means of ``img`` (H,W[,C]) over the pixels inside ``mask`` of each k×k block (tiled from the
    top-left corner; a partial last row/column of blocks is dropped) holding at least
    ``min_pixels`` of them (default k²: blocks entirely inside the mask): (n_blocks, C) float64.
    k = 1 gives the masked pixels themselves."""
    s, n = _block_sums(img, mask, k)
    keep = n >= (k * k if min_pixels is None else max(1, min_pixels))
    return s[keep] / n[keep, None]


def _compare_level(est, ref, ref_var, est_var, mask, k: int, min_pixels: int | None = None) -> dict[str, float]:
    need = k * k if min_pixels is None else max(1, min_pixels)
    se, n = _block_sums(est, mask, k)
    keep = n >= need
    n = n[keep].astype(np.float64)
    A, B = se[keep] / n[:, None], _block_sums(ref, mask, k)[0][keep] / n[:, None]
    if len(B) == 0:
        nan = float("nan")
        return {"n": 0, "mean_ratio": nan, "mean_ratio_rgb": [nan] * A.shape[-1], "mean_ratio_noise": nan, "rms": nan,
                "ref_noise": nan, "est_noise": nan, "rms_corrected": nan}
    scale = max(float(np.sqrt(np.mean(B ** 2))), 1e-300)
    rms = float(np.sqrt(np.mean((A - B) ** 2))) / scale
    # variance of a block mean of independent pixel estimates: Σ pixel variances / n²
    RV = _block_sums(ref_var, mask, k)[0][keep] / (n * n)[:, None] if ref_var is not None else np.zeros_like(B)
    EV = _block_sums(est_var, mask, k)[0][keep] / (n * n)[:, None] if est_var is not None else np.zeros_like(B)
    rn, en = float(np.sqrt(np.mean(RV))) / scale, float(np.sqrt(np.mean(EV))) / scale
    # the mean ratio's own noise (the reference's, 1σ): √Σ var(Σ pixels) / Σ reference
    tot = float((B * n[:, None]).sum())
    mrn = float(np.sqrt((RV * (n * n)[:, None]).sum())) / tot if tot != 0 else float("nan")
    with np.errstate(divide="ignore", invalid="ignore"):
        rgb = [float(x) for x in (A * n[:, None]).sum(0) / (B * n[:, None]).sum(0)]
    return {"n": int(len(B)), "mean_ratio": float(A.mean() / B.mean()) if B.mean() != 0 else float("nan"),
            "mean_ratio_rgb": rgb,
            "mean_ratio_noise": mrn, "rms": rms, "ref_noise": rn, "est_noise": en,
            "rms_corrected": float(np.sqrt(max(0.0, rms * rms - rn * rn - en * en)))}


def compare_to_reference(est: np.ndarray, ref: np.ndarray, mask: np.ndarray, ref_var: np.ndarray | None = None,
                         est_var: np.ndarray | None = None, block: int = 4,
                         min_pixels: int | None = None) -> dict[str, float]:
    """The one comparison of an estimate with a Monte-Carlo reference (both linear RGB, (H,W,3);
    variances = variance of each pixel's mean, as the ``*_var.exr`` files hold), over ``mask``.

    At two scales, per pixel and on ``block``×``block`` block means (blocks entirely inside the mask):
    ``mean_ratio`` = Σest / Σref (the bias; 1 = none), ``mean_ratio_rgb`` the same per channel, ``rms`` = ‖est − ref‖ / ‖ref‖ (RMS over
    pixels and channels, relative to the reference's RMS), ``ref_noise`` (``est_noise``) = the
    reference's (estimate's) own standard error on the same scale, √mean(var)/‖ref‖ (a block
    mean's variance is the mean pixel variance / block²), and ``rms_corrected`` =
    √max(0, rms² − ref_noise² − est_noise²): the RMS error against the noise-free truth, since
    E[(est − ref)²] = (est − truth)² + var(ref) + var(est) for independent estimates (an
    estimate of the squared error, unbiased before the clamp at 0); ``mean_ratio_noise`` = the
    reference's 1σ noise on the mean ratio. A block's means are over its pixels inside the mask;
    blocks with fewer than ``min_pixels`` of them (default block²: only blocks entirely inside)
    are left out. Block keys carry the suffix ``_block``; ``n_pixels`` and ``n_blocks`` count what
    was compared."""
    m = np.asarray(mask, bool)
    est, ref = np.asarray(est)[..., :3], np.asarray(ref)[..., :3]
    rv = None if ref_var is None else np.asarray(ref_var)[..., :3]
    ev = None if est_var is None else np.asarray(est_var)[..., :3]
    px = _compare_level(est, ref, rv, ev, m, 1)
    bl = _compare_level(est, ref, rv, ev, m, int(block), min_pixels)
    out: dict[str, float] = {"block": int(block), "n_pixels": px.pop("n"), "n_blocks": bl.pop("n")}
    out.update(px)
    out.update({f"{k}_block": v for k, v in bl.items()})
    return out


def zscores(a: np.ndarray, var_a: np.ndarray, b: np.ndarray, var_b: np.ndarray) -> np.ndarray:
    """(a − b) / √(var_a + var_b) per element: two independent estimates of one quantity agree
    when |z| > 3 for about 0.3 % of them (Gaussian); 0 where both variances are 0 and a = b."""
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    s = np.sqrt(np.asarray(var_a, np.float64) + np.asarray(var_b, np.float64))
    return np.divide(d, s, out=np.where(d == 0, 0.0, np.copysign(np.inf, d)), where=s > 0)


def image_metrics(img: np.ndarray, ref: np.ndarray, mask: np.ndarray, block: int = 4) -> dict[str, float]:
    """Relative RMS over the object's pixels (‖img − ref‖ / ‖ref‖), mean ratio and the relative
    RMS of ``block``² block means (:func:`compare_to_reference`), and SSIM of the tone-mapped images."""
    from skimage.metrics import structural_similarity

    from .display import reinhard

    m = mask.astype(bool)
    if not m.any():
        return {"rms": float("nan"), "ssim": float("nan"), "mean_ratio": float("nan"), "rms_block": float("nan")}
    c = compare_to_reference(img, ref, m, block=block)
    rel = c["rms"]
    from .display import auto_exposure

    exp, _ = auto_exposure(ref, m)  # one exposure for both, from the reference
    a = reinhard(img, exposure=exp) * m[..., None]
    b = reinhard(ref, exposure=exp) * m[..., None]
    ssim = float(structural_similarity(a, b, channel_axis=2, data_range=1.0, win_size=min(7, *a.shape[:2]) | 1))
    return {"rms": rel, "ssim": ssim, "mean_ratio": c["mean_ratio"], "rms_block": c["rms_block"]}
