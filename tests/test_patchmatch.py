"""Generalized PatchMatch: SSD against a brute-force reference, known warps recovered, determinism,
and the stage through the real CLI (pmatch and an ITMO) on a synthetic cube-map folder."""
import math

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter, map_coordinates

from pipeline import io
from pipeline.expansion import itmo
from pipeline.expansion.patchmatch import generalized_patchmatch, patch_distance, transfer


def _texture(h, w, seed=0):
    rng = np.random.default_rng(seed)
    T = np.stack([gaussian_filter(rng.random((h, w)), 2.0) * 0.6 + gaussian_filter(rng.random((h, w)), 6.0) * 2.0
                  for _ in range(3)], -1)
    return (T - T.min()) / (T.max() - T.min())


def _sample(T, X, Y):
    """Independent bilinear reference: scipy map_coordinates, order 1, edge-replicated."""
    return np.stack([map_coordinates(T[..., k], [np.atleast_1d(Y) - 0.5, np.atleast_1d(X) - 0.5], order=1,
                                     mode="nearest") for k in range(T.shape[2])], -1)


def _warp(T, theta, s, off, n):
    """Source n×n with S(p) = T(c_t + s R(θ) (p - c_s)); returns S and the true target centres X, Y."""
    ys, xs = np.mgrid[0:n, 0:n] + 0.5
    dx, dy = xs - n / 2, ys - n / 2
    c, si = math.cos(theta), math.sin(theta)
    X = T.shape[1] / 2 + off[0] + s * (c * dx - si * dy)
    Y = T.shape[0] / 2 + off[1] + s * (si * dx + c * dy)
    S = _sample(T, X.ravel(), Y.ravel()).reshape(n, n, 3)
    return S, X, Y


def test_patch_distance_matches_bruteforce():
    rng = np.random.default_rng(3)
    S = rng.random((15, 17, 3))
    T = rng.random((23, 21, 3))
    M = (rng.random((15, 17)) > 0.3).astype(np.uint8)
    half = 2
    for _ in range(25):
        px, py = int(rng.integers(0, 17)), int(rng.integers(0, 15))
        M[py, px] = 1
        tx, ty = rng.uniform(0, 21), rng.uniform(0, 23)
        th, sc = rng.uniform(-math.pi, math.pi), rng.uniform(0.5, 2.0)
        acc, n = 0.0, 0
        for dy in range(-half, half + 1):
            for dx in range(-half, half + 1):
                sx, sy = px + dx, py + dy
                if 0 <= sx < 17 and 0 <= sy < 15 and M[sy, sx]:
                    X = tx + sc * (math.cos(th) * dx - math.sin(th) * dy)
                    Y = ty + sc * (math.sin(th) * dx + math.cos(th) * dy)
                    acc += float(((S[sy, sx] - _sample(T, X, Y)[0]) ** 2).sum())
                    n += 1
        got = patch_distance(S, M, T, px, py, tx, ty, th, sc, half, n, np.inf)
        assert got == pytest.approx(acc / (3 * n), rel=1e-10, abs=1e-14)
        # early termination: a bound below the true value gives inf, above it the exact value
        if acc > 0:
            assert patch_distance(S, M, T, px, py, tx, ty, th, sc, half, n, 0.5 * acc / (3 * n)) == np.inf


def test_identical_patches_have_zero_ssd():
    T = _texture(48, 48)
    S = T[10:30, 5:25].copy()
    ys, xs = np.mgrid[0:20, 0:20]
    init = np.stack([xs + 5 + 0.5, ys + 10 + 0.5, np.zeros((20, 20)), np.ones((20, 20))], -1)
    nnf, dist = generalized_patchmatch(S, T, iterations=2, patch_size=5, seed=4, init=init)
    assert np.all(dist == 0.0)
    assert np.array_equal(nnf, init)


@pytest.mark.parametrize("theta,scale,off", [(45, 1.0, (5, -7)), (-45, 1.5, (-4, 3)), (30, 0.67, (8, 6)),
                                             (-20, 1.25, (0, 0))])
def test_known_warp_recovered(theta, scale, off):
    T = _texture(128, 128, seed=1)
    n = 64 if scale >= 1 else 90
    S, X, Y = _warp(T, math.radians(theta), scale, off, n)
    nnf, dist = generalized_patchmatch(S, T, iterations=6, patch_size=7, seed=2)
    err = np.hypot(nnf[..., 0] - X, nnf[..., 1] - Y)
    h = 3  # interior: the whole patch inside the source
    inner = err[h:-h, h:-h]
    assert np.mean(inner <= 1.0) >= 0.95, np.mean(inner <= 1.0)
    ok = inner <= 1.0
    dth = (nnf[h:-h, h:-h, 2] - math.radians(theta) + math.pi) % (2 * math.pi) - math.pi
    assert np.median(np.abs(dth[ok])) < math.radians(3)
    assert np.median(np.abs(np.log(nnf[h:-h, h:-h, 3][ok] / scale))) < 0.03


def test_deterministic_for_seed_and_thread_count():
    import numba

    T = _texture(64, 64, seed=5)
    S, _, _ = _warp(T, 0.3, 1.1, (2, 1), 32)
    a = generalized_patchmatch(S, T, iterations=3, patch_size=5, seed=11)
    prev = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        b = generalized_patchmatch(S, T, iterations=3, patch_size=5, seed=11)
    finally:
        numba.set_num_threads(prev)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    c = generalized_patchmatch(S, T, iterations=0, patch_size=5, seed=12)
    d = generalized_patchmatch(S, T, iterations=0, patch_size=5, seed=11)
    assert not np.array_equal(c[0], d[0])


def test_transfer_reads_the_photo_at_the_nnf():
    P = np.random.default_rng(0).random((10, 12, 3)) * 100
    nnf = np.zeros((2, 2, 4))
    nnf[..., 0] = [[0.5, 3.5], [11.5, 6.5]]
    nnf[..., 1] = [[0.5, 2.5], [9.5, 4.5]]
    out = transfer(P, nnf, np.ones((2, 2), np.uint8))
    assert np.allclose(out[0, 0], P[0, 0]) and np.allclose(out[0, 1], P[2, 3])
    assert np.allclose(out[1, 0], P[9, 11]) and np.allclose(out[1, 1], P[4, 6])


# ------------------------------------------------------------------------------ the stage (CLI)
def _scene(tmp_path):
    """photo.exr (HDR, a bright light region), exposure.npz, and one cube face that is a mirrored
    crop of clamp(α photo) — plus the truth HDR of every face pixel."""
    rng = np.random.default_rng(7)
    tex = _texture(96, 96, seed=9)
    photo = tex * 0.8
    yy, xx = np.mgrid[0:96, 0:96]
    light = (xx - 50) ** 2 / 90 + (yy - 40) ** 2 / 50 < 1.0
    photo = photo.copy()
    photo[light] = 20.0 + 60.0 * tex[light]  # HDR values of the light, structured
    alpha = 0.9
    ldr = np.clip(alpha * photo, 0, 1)
    face_true = photo[16:80, 20:84]           # 64×64 crop holding the light
    face = np.clip(alpha * face_true, 0, 1)[:, ::-1]  # the GL cube face is a mirror image
    cov = np.ones((64, 64), np.float32)
    cov[:3, :] = 0                            # a strip without coverage
    cub = tmp_path / "cub"
    cub.mkdir()
    io.write_npz(cub / "cameras.npz", "pcrelight.cameras/1", K=np.eye(3)[None], world_to_camera=np.eye(4)[None],
                 resolution=np.array([[64, 64]], np.int32), view=np.zeros(1, np.int32),
                 face=np.zeros(1, np.int32), eye=np.zeros((1, 3)))
    io.write_image(cub / "face_000.exr", np.dstack([face * cov[..., None], cov, cov * 2.0]),
                   channels=["R", "G", "B", "A", "Z"])
    io.write_image(tmp_path / "photo.exr", photo.astype(np.float32))
    io.write_image(tmp_path / "photo_ldr.exr", ldr.astype(np.float32))
    io.write_npz(tmp_path / "exposure.npz", "pcrelight.exposure/1", alpha=np.float64(alpha),
                 log2_alpha=np.float64(np.log2(alpha)), distance=np.float64(0.0), tried_log2_alpha=np.zeros(1),
                 tried_distance=np.zeros(1), tried_phase=np.zeros(1, np.int32), cloud_hist=np.ones(4) / 4,
                 photo_hist=np.ones(4) / 4, hist_space=np.asarray("srgb"), iterations=np.int32(0))
    return face, cov, face_true[:, ::-1], alpha, light[16:80, 20:84][:, ::-1]


def test_cli_pmatch_recovers_hdr_of_the_light(tmp_path, cli_run):
    face, cov, truth, alpha, light = _scene(tmp_path)
    code, out, err = cli_run("patchmatch", tmp_path / "cub", "--photo", tmp_path / "photo.exr",
                             "--photo-ldr", tmp_path / "photo_ldr.exr", "--exposure", tmp_path / "exposure.npz",
                             "--out", tmp_path / "hdr", "--iterations", "5", "--seed", "3",
                             "--preview", tmp_path / "pm.png")
    assert code == 0, err
    r = io.read_npz(tmp_path / "hdr" / "renderings.npz", "pcrelight.renderings/1")
    assert str(r["method"]) == "pmatch" and float(r["scale"]) == alpha and int(r["count"]) == 1
    assert io.image_channels(tmp_path / "hdr" / "face_000.exr") == ["R", "G", "B", "Q"]
    img = io.read_image(tmp_path / "hdr" / "face_000.exr")
    sel = light & (cov > 0)
    sel[:6] = False  # the light pixels whose patches are complete
    rel = np.abs(img[..., :3][sel] - truth[sel]) / truth[sel]
    assert np.median(rel) < 0.02, np.median(rel)
    assert np.all(img[..., 3][cov == 0] == np.float32(1e30))
    q = img[..., 3][(cov > 0)]
    assert np.all(q[q < 1e29] >= 0) and np.all(q[q < 1e29] <= 1)
    # the same seed gives the same bytes of pixels
    code, _, err = cli_run("patchmatch", tmp_path / "cub", "--photo", tmp_path / "photo.exr",
                           "--photo-ldr", tmp_path / "photo_ldr.exr", "--exposure", tmp_path / "exposure.npz",
                           "--out", tmp_path / "hdr2", "--iterations", "5", "--seed", "3")
    assert code == 0, err
    assert np.array_equal(io.read_image(tmp_path / "hdr2" / "face_000.exr"), img)


@pytest.mark.parametrize("method", ["landis", "banterle", "rhee"])
def test_cli_itmo_matches_the_operator(tmp_path, cli_run, method):
    face, cov, *_ = _scene(tmp_path)
    code, out, err = cli_run("patchmatch", tmp_path / "cub", "--method", method, "--max-luminance", "40",
                             "--out", tmp_path / "o")
    assert code == 0, err
    r = io.read_npz(tmp_path / "o" / "renderings.npz", "pcrelight.renderings/1")
    assert float(r["scale"]) == 1.0 and str(r["method"]) == method
    img = io.read_image(tmp_path / "o" / "face_000.exr")
    f = io.read_image(tmp_path / "cub" / "face_000.exr")[..., :3].astype(np.float64)
    expect = itmo.apply(method, f, max_luminance=40.0)
    c = cov > 0
    assert np.allclose(img[..., :3][c], expect[c], rtol=1e-5, atol=1e-6)
    assert np.all(img[..., 3][c] == 0) and np.all(img[..., 3][~c] == np.float32(1e30))


def test_cli_bad_inputs(tmp_path, cli_run):
    _scene(tmp_path)
    code, _, err = cli_run("patchmatch", tmp_path / "nowhere", "--photo", tmp_path / "photo.exr",
                           "--exposure", tmp_path / "exposure.npz", "--out", tmp_path / "o")
    assert code == 1 and "nowhere" in err
    code, _, err = cli_run("patchmatch", tmp_path / "cub", "--out", tmp_path / "o")
    assert code == 2 and "--photo" in err
    code, _, err = cli_run("patchmatch", tmp_path / "cub", "--photo", tmp_path / "photo.exr",
                           "--exposure", tmp_path / "exposure.npz", "--out", tmp_path / "o", "--patch-size", "4")
    assert code == 2 and "--patch-size" in err
    (tmp_path / "cub" / "face_000.exr").write_bytes(b"garbage")
    code, _, err = cli_run("patchmatch", tmp_path / "cub", "--method", "rhee", "--max-luminance", "5",
                           "--out", tmp_path / "o")
    assert code == 1 and "face_000.exr" in err


@pytest.mark.parametrize("theta,scale", [(40, 1.3), (-30, 0.7)])
def test_pyramid_recovers_warp(theta, scale):
    from pipeline.expansion.patchmatch import pyramid_patchmatch

    T = _texture(128, 128, seed=6)
    n = 64 if scale >= 1 else 90
    S, X, Y = _warp(T, math.radians(theta), scale, (3, -2), n)
    nnf, dist = pyramid_patchmatch(S, T, levels=3, iterations=4, patch_size=7, seed=5)
    err = np.hypot(nnf[..., 0] - X, nnf[..., 1] - Y)[3:-3, 3:-3]
    assert np.mean(err <= 1.0) >= 0.95, np.mean(err <= 1.0)


def test_upsample_nnf_is_exact_for_a_similarity():
    from pipeline.expansion.patchmatch import upsample_nnf

    th, s = 0.4, 1.3
    H, W = 10, 12
    ys, xs = np.mgrid[0:H // 2, 0:W // 2] + 0.5

    def f(x, y, k):  # a similarity transform evaluated at (x, y) of a level with pixel size k
        return (40 / k + s * (math.cos(th) * x - math.sin(th) * y), 30 / k + s * (math.sin(th) * x + math.cos(th) * y))

    cx, cy = f(xs, ys, 2)
    coarse = np.stack([cx, cy, np.full_like(cx, th), np.full_like(cx, s)], -1)
    fine = upsample_nnf(coarse, H, W, 1000, 1000)
    fy, fx = np.mgrid[0:H, 0:W] + 0.5
    ex, ey = f(fx, fy, 1)
    assert np.allclose(fine[..., 0], ex) and np.allclose(fine[..., 1], ey)


def test_vote_equals_truth_for_exact_similarity_on_a_linear_photo():
    from pipeline.expansion.patchmatch import vote

    H, W, th, s = 20, 24, 0.5, 1.2
    yy, xx = np.mgrid[0:60, 0:60] + 0.5
    P = np.stack([3 + 0.5 * xx + 0.25 * yy, 100 + xx, 7 + 2 * yy], -1)  # linear: bilinear sampling is exact
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    cx = 30 + s * (math.cos(th) * (xs - 12) - math.sin(th) * (ys - 10))
    cy = 30 + s * (math.sin(th) * (xs - 12) + math.cos(th) * (ys - 10))
    nnf = np.stack([cx, cy, np.full_like(cx, th), np.full_like(cx, s)], -1)
    act = np.ones((H, W), np.uint8)
    expect = np.stack([3 + 0.5 * cx + 0.25 * cy, 100 + cx, 7 + 2 * cy], -1)
    assert np.allclose(vote(P, nnf, act, 5), expect, rtol=1e-5)
    assert np.allclose(transfer(P, nnf, act), expect, rtol=1e-5)


def test_only_what_the_scene_requires(tmp_path, cli_run):
    """A face without overexposed pixels is skipped (LDR/α kept, Q = 1e30); no faces → count 0."""
    face, cov, truth, alpha, light = _scene(tmp_path)
    dark = np.clip(face * 0.5, 0, 0.5)
    io.write_image(tmp_path / "cub" / "face_000.exr", np.dstack([dark, cov, cov]), channels=["R", "G", "B", "A", "Z"])
    args = ["--photo", tmp_path / "photo.exr", "--exposure", tmp_path / "exposure.npz"]
    code, _, err = cli_run("patchmatch", tmp_path / "cub", *args, "--out", tmp_path / "o")
    assert code == 0, err
    rep = io.read_json(tmp_path / "o" / "report.json")
    assert rep["faces"][0]["skipped"] == "no overexposed pixel" and rep["faces"][0]["matched"] == 0
    img = io.read_image(tmp_path / "o" / "face_000.exr")
    assert np.all(img[..., 3] == np.float32(1e30))
    c = cov > 0
    assert np.allclose(img[..., :3][c] * alpha, dark[c], rtol=1e-5)
    empty = tmp_path / "empty"
    empty.mkdir()
    io.write_npz(empty / "cameras.npz", "pcrelight.cameras/1", K=np.zeros((0, 3, 3)), world_to_camera=np.zeros((0, 4, 4)),
                 resolution=np.zeros((0, 2), np.int32), view=np.zeros(0, np.int32), face=np.zeros(0, np.int32),
                 eye=np.zeros((0, 3)))
    code, _, err = cli_run("patchmatch", empty, *args, "--out", tmp_path / "o2")
    assert code == 0, err
    r = io.read_npz(tmp_path / "o2" / "renderings.npz", "pcrelight.renderings/1")
    assert int(r["count"]) == 0 and io.read_json(tmp_path / "o2" / "report.json")["skipped"] == "no faces"


def _photo_of_something_else(shape, path):
    """scikit-image's astronaut (a photo of something else), linearised and resized to ``shape``."""
    import skimage.data
    from skimage.transform import resize

    im = skimage.data.astronaut()[..., :3].astype(np.float64) / 255.0
    lin = np.where(im <= 0.04045, im / 12.92, ((im + 0.055) / 1.055) ** 2.4)
    io.write_image(path, (resize(lin, shape, anti_aliasing=True) * 3.7).astype(np.float32))


def test_photo_that_does_not_fit_is_detected(tiny_scene, tmp_path, cli_run):
    """The tiny scene's own photo fits its cloud's cube maps; a photo of something else gives a
    WARNING naming the figures, and with --strict the one-line error (exit 1, no renderings.npz)."""
    cloud = tiny_scene / "cloud_ldr.ply"
    code, _, err = cli_run("render-cubemaps", cloud, "--out", tmp_path / "cub", "--size", "128")
    assert code == 0, err
    other = tmp_path / "other.exr"
    _photo_of_something_else(io.read_image(tiny_scene / "photo.exr").shape[:2], other)
    fits = {}
    for name, photo in (("own", tiny_scene / "photo.exr"), ("other", other)):
        d = tmp_path / name
        code, _, err = cli_run("expose-match", photo, cloud, "--out", d / "exposure.npz", "--photo-ldr", d / "ldr.exr")
        assert code == 0, err
        args = ("patchmatch", tmp_path / "cub", "--photo", photo, "--photo-ldr", d / "ldr.exr",
                "--exposure", d / "exposure.npz", "--iterations", "2")
        code, _, err = cli_run(*args, "--out", d / "hdr")
        assert code == 0, err
        r = io.read_npz(d / "hdr" / "renderings.npz", "pcrelight.renderings/1")
        fits[name] = (int(r["fit_ok"]), float(r["fit_fraction"]), float(r["fit_median_q"]), err)
        if name == "other":
            code, out, err = cli_run(*args, "--out", d / "strict", "--strict")
            assert code == 1
            line = f"pcrelight: {photo}: the photo does not fit the cloud's cube maps"
            assert line in err and "WARNING" not in err.split(line)[1], err
            assert not (d / "strict" / "renderings.npz").exists()
    assert fits["own"][0] == 1 and "does not fit" not in fits["own"][3], fits["own"][:3]
    assert fits["other"][0] == 0 and "WARNING" in fits["other"][3] and "does not fit" in fits["other"][3]
    assert fits["own"][1] > 1.5 * fits["other"][1] and fits["other"][2] > 3 * fits["own"][2], (fits["own"][:3], fits["other"][:3])
