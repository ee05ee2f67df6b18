"""ITMO baselines against their published formulas (hand-evaluated at chosen points)."""
import numpy as np
import pytest

from pipeline.expansion import itmo


def grey(v):
    v = np.asarray(v, dtype=np.float64)
    return np.stack([v, v, v], -1)


def test_luminance_weights_are_cie_y():
    assert np.allclose(itmo.luminance(np.eye(3)), [0.2126, 0.7152, 0.0722], atol=1e-4)


def test_landis_against_formula():
    M = 50.0
    # below the threshold 0.5: identity
    assert np.isclose(itmo.landis_curve(0.3, M), 0.3)
    # L = 0.75: t = ((0.75-0.5)/0.5)^2 = 0.25; L_w = 0.75*0.75 + 50*0.75*0.25
    assert np.isclose(itmo.landis_curve(0.75, M), 0.75 * 0.75 + 50 * 0.75 * 0.25)
    assert np.isclose(itmo.landis_curve(1.0, M), M)
    out = itmo.landis(grey([0.75]), M)
    assert np.allclose(out, 0.75 * 0.75 + 50 * 0.75 * 0.25)


def test_inverse_reinhard_against_formula():
    M, w = 100.0, 40.0
    L = 0.6
    expect = w * M / 2 * (L - 1 + np.sqrt((1 - L) ** 2 + 4 * L / w ** 2))
    assert np.isclose(itmo.inverse_reinhard(L, M, w), expect)
    assert np.isclose(itmo.inverse_reinhard(1.0, M, w), M)
    assert itmo.inverse_reinhard(0.0, M, w) == 0.0
    # default L_white = L_max: far below white it inverts Reinhard L/(1+L)
    assert np.isclose(itmo.inverse_reinhard(0.01, 1e6), 0.01 / 0.99, rtol=1e-3)


def test_banterle_blend_with_given_map():
    M = 30.0
    rgb = grey([0.2, 0.95])
    lam = np.array([0.0, 0.5])
    out = itmo.banterle(rgb, M, expand_map=lam)
    Lw = itmo.inverse_reinhard(0.95, M)
    assert np.allclose(out[0], 0.2)
    assert np.allclose(out[1], 0.95 * 0.5 + Lw * 0.5)


def test_rhee_against_formula():
    lin = np.array([0.5, 0.2, 0.9])
    enc = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)
    Li = 0.3 * enc[0] + 0.59 * enc[1] + 0.11 * enc[2]
    assert np.allclose(itmo.rhee(lin[None]), lin * (10 * Li ** 10 + 1.8))
    assert np.allclose(itmo.rhee(grey([1.0])), 11.8)
    assert np.allclose(itmo.rhee(grey([0.0])), 0.0)


@pytest.mark.parametrize("method", itmo.METHODS)
def test_monotone_and_finite(method):
    v = np.linspace(0.0, 1.0, 2001)
    out = itmo.apply(method, grey(v), max_luminance=200.0, expand_map=np.ones_like(v)) \
        if method == "banterle" else itmo.apply(method, grey(v), max_luminance=200.0)
    assert np.all(np.isfinite(out))
    y = itmo.luminance(out)
    assert np.all(np.diff(y) >= -1e-12)
    # nothing at 0, finite at 1, NaN input does not propagate
    assert y[0] == 0.0
    bad = itmo.apply(method, np.array([[np.nan, 1.0, np.inf]]), max_luminance=200.0)
    assert np.all(np.isfinite(bad))


def test_expand_map_image_peaks_at_the_light():
    img = np.full((64, 64, 3), 0.1)
    img[10:16, 40:46] = 1.0  # a clipped light
    lam = itmo.expand_map_image(img)
    assert lam.shape == (64, 64) and np.all(np.isfinite(lam))
    assert 0.0 <= lam.min() and lam.max() == pytest.approx(1.0)
    assert lam[13, 43] > 0.9 and lam[13, 43] > 3 * lam[55, 5]
    out = itmo.banterle(img, 100.0)
    assert itmo.luminance(out)[13, 43] > 10.0
    # far from the light the blend stays near the inverse Reinhard's slope-1 region: 0.1 -> ~0.11
    assert np.allclose(out[55, 5], img[55, 5], rtol=0.15)


def test_median_cut_equal_energy():
    rng = np.random.default_rng(0)
    L = rng.random((32, 48))
    s = itmo.median_cut(L, 16)
    assert len(s) == 16
    assert np.isclose(s[:, 2].sum(), L.sum())
    assert s[:, 2].std() / s[:, 2].mean() < 0.2


def test_expand_map_points():
    pts = np.stack([np.linspace(0, 1, 200), np.zeros(200), np.zeros(200)], 1)
    rgb = grey(np.where(pts[:, 0] > 0.8, 1.0, 0.1))
    lam = itmo.expand_map_points(pts, rgb, k=8)
    assert lam.max() == pytest.approx(1.0)
    assert lam[-1] > 0.9 and lam[0] < 0.2
