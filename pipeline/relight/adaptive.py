"""Image-space adaptive shading (paper 001 §3.3, for every gatherer): shade a coarse grid of the covered
pixels, refine where the result or the G-buffer is not coherent, and fill the rest by joint bilateral
upsampling on the G-buffer.

Levels: pixels on a ``step``-grid (4 by default: a 4×4 initial grid, as 001) plus one pixel of every block
the grid misses; a block whose corner samples disagree — a corner missing (silhouette), luminances whose
max / min exceeds 1 + ε, or normals more than ``normal_cos`` apart — gets the grid of half the step inside it,
down to every pixel. A pixel left is interpolated from the four corners of the coherent block it lies in,
weighted bilinearly and by normal agreement (:func:`interpolate_blocks`; the G-buffer-guided bilateral
:func:`upsample` fills what that cannot).

Pure functions on (H, W) arrays; linear radiance, metres.
"""

from __future__ import annotations

from typing import Callable

import numpy as np


def _lum(rgb: np.ndarray) -> np.ndarray:
    return rgb @ np.array([0.2126, 0.7152, 0.0722])


def initial(mask: np.ndarray, step: int) -> np.ndarray:
    """(H, W) bool: covered pixels on the step-grid, plus the first covered pixel (row-major) of every
    step×step block with covered pixels but no grid pixel."""
    H, W = mask.shape
    sel = np.zeros_like(mask)
    sel[::step, ::step] = True
    sel &= mask
    hb, wb = -(-H // step), -(-W // step)
    pad = np.zeros((hb * step, wb * step), bool)
    pad[:H, :W] = mask
    blocks = pad.reshape(hb, step, wb, step).transpose(0, 2, 1, 3).reshape(hb, wb, step * step)
    has = blocks.any(-1)
    hit = np.zeros((hb * step, wb * step), bool)
    hit[:H, :W] = sel
    hitb = hit.reshape(hb, step, wb, step).transpose(0, 2, 1, 3).reshape(hb, wb, -1).any(-1)
    by, bx = np.nonzero(has & ~hitb)
    k = blocks[by, bx].argmax(-1)
    sel[by * step + k // step, bx * step + k % step] = True
    return sel


def incoherent_blocks(shaded: np.ndarray, rad: np.ndarray, normal: np.ndarray, mask: np.ndarray, step: int,
                      eps: float, normal_cos: float) -> np.ndarray:
    """(hb, wb) bool: step×step blocks (top-left on the grid) to refine: covered, and a corner (the grid
    pixels at the block's four corners) missing or unshaded, or the corners' luminance max/min > 1 + eps, or
    two corners' normals with a dot below ``normal_cos``."""
    H, W = mask.shape
    hb, wb = -(-H // step), -(-W // step)
    ys, xs = np.arange(hb) * step, np.arange(wb) * step
    lum = _lum(rad.astype(np.float64))
    pad = np.zeros((hb * step, wb * step), bool)
    pad[:H, :W] = mask
    covered = pad.reshape(hb, step, wb, step).any((1, 3))
    bad = np.zeros((hb, wb), bool)
    lo = np.full((hb, wb), np.inf)
    hi = np.full((hb, wb), -np.inf)
    nrm = []
    for dy in (0, step):
        for dx in (0, step):
            y, x = ys + dy, xs + dx
            inside = (y[:, None] < H) & (x[None, :] < W)
            yy, xx = np.minimum(y, H - 1), np.minimum(x, W - 1)
            ok = inside & shaded[yy[:, None], xx[None, :]]
            bad |= ~ok & inside                          # a corner off the object or not shaded: a silhouette
            L = np.where(ok, lum[yy[:, None], xx[None, :]], np.nan)
            lo = np.fmin(lo, L)
            hi = np.fmax(hi, L)
            nrm.append(np.where(ok[..., None], normal[yy[:, None], xx[None, :]], np.nan))
    with np.errstate(invalid="ignore", divide="ignore"):
        bad |= hi > (1 + eps) * lo                     # scale-free: radiance × c refines the same blocks
        for i in range(4):
            for j in range(i + 1, 4):
                d = (nrm[i] * nrm[j]).sum(-1)
                bad |= d < normal_cos
    return bad & covered


def upsample(rad: np.ndarray, shaded: np.ndarray, mask: np.ndarray, normal: np.ndarray, position: np.ndarray,
             radius: int, sigma_px: float | None = None) -> np.ndarray:
    """Fill the covered, unshaded pixels of ``rad`` (H, W, 3) from the shaded ones within ``radius`` pixels:
    weights exp(−d²/2σ²) · max(0, n·n_j)⁸ · exp(−|p − p_j|²/2h²) (σ = radius/2 pixels, h = the median distance
    between neighbouring pixels' positions × radius). A pixel with no weighted neighbour takes its nearest
    shaded one's value. Only the pixels to fill are visited: (2·radius + 1)² gathers of their neighbours."""
    H, W = mask.shape
    todo = mask & ~shaded
    if not todo.any():
        return rad
    out = rad.astype(np.float64).copy()
    sig = sigma_px or max(radius / 2.0, 0.5)
    dp = np.linalg.norm(np.diff(position, axis=1), axis=-1)
    both = mask[:, 1:] & mask[:, :-1]
    h = (float(np.median(dp[both])) if both.any() else 1.0) * radius + 1e-30
    r = radius
    Wp = W + 2 * r                                       # the padded image's row length: neighbours off the image
    P = np.pad(position.astype(np.float64), ((r, r), (r, r), (0, 0))).reshape(-1, 3)   # read as unshaded zeros
    N = np.pad(normal.astype(np.float64), ((r, r), (r, r), (0, 0))).reshape(-1, 3)
    R = np.pad(rad.astype(np.float64), ((r, r), (r, r), (0, 0))).reshape(-1, 3)
    S = np.pad(shaded, r).reshape(-1)
    y, x = np.nonzero(todo)
    base = (y + r) * Wp + (x + r)
    p0, n0 = position[y, x], normal[y, x]
    n = y.size
    acc = np.zeros((n, 3))
    wsum = np.zeros(n)
    best = np.full(n, np.inf)
    near = np.zeros((n, 3))
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            j = base + (dy * Wp + dx)
            s = S[j]
            if not s.any():
                continue
            d2 = dy * dy + dx * dx
            Rj = R[j]
            nn = np.maximum((N[j] * n0).sum(-1), 0.0) ** 8
            pp = ((P[j] - p0) ** 2).sum(-1)
            w = np.where(s, np.exp(-d2 / (2 * sig * sig)) * nn * np.exp(-pp / (2 * h * h)), 0.0)
            acc += w[:, None] * Rj
            wsum += w
            closer = s & (d2 < best)
            best = np.where(closer, d2, best)
            near = np.where(closer[:, None], Rj, near)
    ok = wsum > 1e-12
    out[y[ok], x[ok]] = acc[ok] / wsum[ok, None]
    rest = ~ok & np.isfinite(best)
    out[y[rest], x[rest]] = near[rest]
    return out.astype(rad.dtype)


def interpolate_blocks(rad: np.ndarray, shaded: np.ndarray, level: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fill every unshaded pixel whose ``level`` s > 0 (it lies in a coherent s×s block, top-left on the
    s-grid) from its block's four corners: bilinear weights × max(0, n·n_c)⁸ over the shaded corners. Returns
    (image, filled mask)."""
    H, W = shaded.shape
    out = rad.astype(np.float64).copy()
    todo = ~shaded & (level > 0)
    y, x = np.nonzero(todo)
    if y.size == 0:
        return rad, todo
    sl = level[y, x]
    y0, x0 = (y // sl) * sl, (x // sl) * sl
    fy, fx = (y - y0) / sl, (x - x0) / sl
    acc = np.zeros((y.size, 3))
    wsum = np.zeros(y.size)
    for dy, wy in ((0, 1 - fy), (1, fy)):
        for dx, wx in ((0, 1 - fx), (1, fx)):
            cy, cx = y0 + dy * sl, x0 + dx * sl
            ok = (cy < H) & (cx < W)
            cy, cx = np.minimum(cy, H - 1), np.minimum(cx, W - 1)
            ok &= shaded[cy, cx]
            w = np.where(ok, wy * wx * np.maximum((normal[cy, cx] * normal[y, x]).sum(-1), 0.0) ** 8, 0.0)
            acc += w[:, None] * rad[cy, cx]
            wsum += w
    good = wsum > 1e-12
    out[y[good], x[good]] = acc[good] / wsum[good, None]
    filled = np.zeros_like(todo)
    filled[y[good], x[good]] = True
    return out.astype(rad.dtype), filled


def shade_adaptive(shade: Callable[[np.ndarray], np.ndarray], mask: np.ndarray, normal: np.ndarray,
                   position: np.ndarray, eps: float, step: int = 4, normal_cos: float = 0.9,
                   min_step: int = 1) -> tuple[np.ndarray, dict]:
    """Radiance (H, W, 3) over ``mask`` with ``shade(flat_pixel_indices) → (n, 3)`` called once per level on the
    new pixels only, down to the grid of ``min_step`` (1: every pixel where the result is not coherent; the
    composite's smooth change by the object stops at 2). A pixel left unshaded is interpolated from the corners of the coherent block it lies in
    (:func:`interpolate_blocks`: a shadow edge inside a refined block never leaks into it), else by
    :func:`upsample`. Returns the image and stats (pixels shaded per level, share shaded)."""
    H, W = mask.shape
    rad = np.zeros((H, W, 3), np.float32)
    shaded = np.zeros((H, W), bool)
    level = np.zeros((H, W), np.int64)                 # the size of the coherent block a pixel was left in
    new = initial(mask, step)
    region = np.ones((H, W), bool)                     # pixels in the blocks refined at the previous level
    levels = []
    s = step
    while True:
        idx = np.flatnonzero(new.reshape(-1))
        if idx.size:
            rad.reshape(-1, 3)[idx] = shade(idx)
        shaded |= new
        levels.append(int(idx.size))
        if s <= min_step:
            level[region & (level == 0)] = s           # the finest grid's blocks: interpolated from their corners
            break
        bad = incoherent_blocks(shaded, rad, normal, mask, s, eps, normal_cos) & region[::s, ::s]
        inb = np.repeat(np.repeat(bad, s, 0), s, 1)[:H, :W]
        level[region & ~inb & (level == 0)] = s
        s2 = s // 2
        grid = np.zeros((H, W), bool)
        grid[::s2, ::s2] = True
        new = grid & inb & mask & ~shaded
        region = inb
        s = s2
    img, filled = interpolate_blocks(rad, shaded, np.where(mask, level, 0), normal)
    rest = shaded | filled
    img = upsample(img, rest, mask, normal, position, radius=step)
    n = int(mask.sum())
    return img, {"levels": levels, "shaded": int(shaded.sum()), "covered": n,
                 "shaded_share": float(shaded.sum() / max(n, 1))}


def upsample_reference(rad: np.ndarray, shaded: np.ndarray, mask: np.ndarray, normal: np.ndarray, position: np.ndarray,
                       radius: int, sigma_px: float | None = None) -> np.ndarray:
    """:func:`upsample`'s twin: the implementation before issue 23s (every pixel of the image visited at every
    offset), which :func:`upsample` (the pixels to fill only) reproduces bit for bit (tests/test_adaptive.py; the
    speed of the two: bench/speed/bench_upsample.py)."""
    H, W = mask.shape
    out = rad.astype(np.float64).copy()
    todo = mask & ~shaded
    if not todo.any():
        return rad
    sig = sigma_px or max(radius / 2.0, 0.5)
    dp = np.linalg.norm(np.diff(position, axis=1), axis=-1)
    both = mask[:, 1:] & mask[:, :-1]
    h = (float(np.median(dp[both])) if both.any() else 1.0) * radius + 1e-30
    acc = np.zeros((H, W, 3))
    wsum = np.zeros((H, W))
    best = np.full((H, W), np.inf)
    near = np.zeros((H, W, 3))
    P = np.pad(position.astype(np.float64), ((radius, radius), (radius, radius), (0, 0)))
    N = np.pad(normal.astype(np.float64), ((radius, radius), (radius, radius), (0, 0)))
    R = np.pad(rad.astype(np.float64), ((radius, radius), (radius, radius), (0, 0)))
    S = np.pad(shaded, radius)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            sl = (slice(radius + dy, radius + dy + H), slice(radius + dx, radius + dx + W))
            s = S[sl] & todo
            if not s.any():
                continue
            d2 = dy * dy + dx * dx
            nn = np.maximum((N[sl] * normal).sum(-1), 0.0) ** 8
            pp = ((P[sl] - position) ** 2).sum(-1)
            w = np.where(s, np.exp(-d2 / (2 * sig * sig)) * nn * np.exp(-pp / (2 * h * h)), 0.0)
            acc += w[..., None] * R[sl]
            wsum += w
            closer = s & (d2 < best)
            best = np.where(closer, d2, best)
            near = np.where(closer[..., None], R[sl], near)
    ok = todo & (wsum > 1e-12)
    out[ok] = acc[ok] / wsum[ok, None]
    rest = todo & ~ok & np.isfinite(best)
    out[rest] = near[rest]
    return out.astype(rad.dtype)
