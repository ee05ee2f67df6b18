"""Image-space adaptive shading (pipeline/relight/adaptive.py): exact where the image is what the
interpolation reproduces, refined where it is not, and never shading a pixel twice."""

from __future__ import annotations

import numpy as np

from pipeline.relight.adaptive import initial, shade_adaptive, upsample, upsample_reference


def _scene(H=40, W=52):
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    mask = (yy - H / 2) ** 2 + (xx - W / 2) ** 2 < (0.45 * min(H, W)) ** 2
    pos = np.stack([xx * 0.01, yy * 0.01, np.zeros_like(xx)], -1)
    nrm = np.zeros((H, W, 3))
    nrm[..., 2] = 1.0
    return mask, pos, nrm


def test_initial_grid_covers_every_block():
    mask, _, _ = _scene()
    sel = initial(mask, 4)
    assert not (sel & ~mask).any()
    H, W = mask.shape
    for by in range(0, H, 4):
        for bx in range(0, W, 4):
            if mask[by:by + 4, bx:bx + 4].any():
                assert sel[by:by + 4, bx:bx + 4].any()


def test_constant_image_is_exact_and_cheap():
    mask, pos, nrm = _scene()
    calls = []

    def shade(idx):
        calls.append(idx)
        return np.full((len(idx), 3), 0.7, np.float32)

    img, st = shade_adaptive(shade, mask, nrm, pos, eps=0.05)
    np.testing.assert_allclose(img[mask], 0.7, rtol=1e-6)
    assert np.all(img[~mask] == 0)
    done = np.concatenate(calls)
    assert len(np.unique(done)) == len(done)                        # no pixel shaded twice
    assert st["shaded_share"] < 0.5                                   # the silhouette blocks only, refined


def test_an_edge_is_refined_to_every_pixel_and_the_ramp_is_interpolated():
    mask, pos, nrm = _scene()
    H, W = mask.shape
    truth = np.zeros((H, W, 3), np.float32)
    yy, xx = np.mgrid[0:H, 0:W]
    truth[...] = (0.2 + 0.01 * xx)[..., None]                         # a gentle ramp …
    truth[xx >= 30] *= 4.0                                            # … and a hard edge at x = 30
    img, st = shade_adaptive(lambda idx: truth.reshape(-1, 3)[idx], mask, nrm, pos, eps=0.2)
    edge = mask & (np.abs(xx - 29.5) <= 1)
    np.testing.assert_array_equal(img[edge], truth[edge])            # shaded, not interpolated, at the edge
    err = np.abs(img[mask] - truth[mask]) / truth[mask]
    assert err.max() < 0.05 and st["shaded_share"] < 0.8


def test_upsample_does_not_blend_across_normals():
    mask, pos, nrm = _scene()
    H, W = mask.shape
    nrm[:, W // 2:] = [1.0, 0.0, 0.0]                                 # a crease
    rad = np.where((np.arange(W) < W // 2)[None, :, None], 1.0, 5.0).astype(np.float32) * np.ones((H, W, 3), np.float32)
    shaded = np.zeros((H, W), bool)
    shaded[::4, ::4] = True
    shaded &= mask
    out = upsample(rad, shaded, mask, nrm, pos, radius=4)
    left = mask & (np.arange(W) < W // 2)[None, :]
    np.testing.assert_allclose(out[left], 1.0, rtol=1e-6)


def test_upsample_visits_only_the_pixels_to_fill_bit_for_bit():
    """Random G-buffers (ragged mask, sparse shaded pixels — some with no shaded neighbour —, random normals,
    positions and radiance, float32 and float64, several radii): the same bytes as the every-pixel version."""
    rng = np.random.default_rng(23)
    for k, (H, W, radius, dtype, share) in enumerate([(37, 53, 4, np.float32, 0.15), (64, 48, 2, np.float64, 0.3),
                                                      (29, 31, 4, np.float32, 0.03), (40, 40, 1, np.float32, 0.5)]):
        mask = rng.random((H, W)) < 0.8
        mask[: H // 3, : W // 3] = False                                  # a hole: pixels with no shaded neighbour
        shaded = mask & (rng.random((H, W)) < share)
        nrm = rng.normal(size=(H, W, 3))
        nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
        nrm = 0.3 * nrm + [0.0, 0.0, 1.0]                                  # mostly facing +z …
        nrm[rng.random((H, W)) < 0.1] *= -1                                # … some not: pixels left to the nearest
        nrm = nrm.astype(dtype)
        yy, xx = np.mgrid[0:H, 0:W] * 0.01
        pos = (np.stack([xx, yy, np.zeros_like(xx)], -1) + rng.normal(scale=0.003, size=(H, W, 3))).astype(dtype)
        rad = (np.exp(rng.normal(size=(H, W, 3))) * mask[..., None]).astype(dtype)
        rad[mask & ~shaded] = 0
        got = upsample(rad, shaded, mask, nrm, pos, radius=radius)
        want = upsample_reference(rad, shaded, mask, nrm, pos, radius=radius)
        assert got.dtype == want.dtype
        assert got.tobytes() == want.tobytes(), k
        assert (got[mask & ~shaded] != 0).any()                           # something was filled
