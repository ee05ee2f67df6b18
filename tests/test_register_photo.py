"""register_photo (issue 14 experiment): pose and α of a photo from the LDR cloud — a synthetic
room with a known pose and exposure, and the shipped sample against its truth.npz."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline import camera, io
from pipeline.expansion import register_photo as rp
from tests.conftest import SAMPLES


def synthetic_room(n: int = 120_000, seed: int = 0):
    """A 12 × 4 × 8 m box (points on its inner faces, normals inward) with a smooth luminance
    texture, three coloured hangings and a bright window; returns points, normals, HDR radiance."""
    rng = np.random.default_rng(seed)
    lo, hi = np.array([-6.0, 0.0, -4.0]), np.array([6.0, 4.0, 4.0])
    ext = hi - lo
    faces = [(a, s) for a in range(3) for s in (0, 1)]
    area = np.array([np.prod(np.delete(ext, a)) for a, _ in faces])
    which = rng.choice(len(faces), size=n, p=area / area.sum())
    p = lo + rng.random((n, 3)) * ext
    nrm = np.zeros((n, 3))
    for k, (a, s) in enumerate(faces):
        m = which == k
        p[m, a] = hi[a] if s else lo[a]
        nrm[m, a] = -1.0 if s else 1.0
    x, y, z = p.T
    lum = 0.3 * (1.2 + np.sin(1.3 * x + 0.4) * np.cos(0.9 * z) + 0.5 * np.sin(2.1 * y + 0.7 * x))
    rgb = np.repeat(lum[:, None], 3, axis=1) * np.array([1.0, 0.95, 0.85])
    for (c0, c1, y0, y1, axis, side), col in [((-5, -3, 1.0, 3.5, 2, 1), (0.9, 0.1, 0.1)),
                                              ((0, 2, 0.5, 3.0, 2, 1), (0.1, 0.8, 0.15)),
                                              ((-2, 1, 1.0, 3.0, 2, 0), (0.15, 0.2, 0.9)),
                                              ((-3, 1, 1.0, 3.0, 0, 0), (12.0, 12.0, 11.0))]:
        u = x if axis == 2 else z
        on = (np.abs(p[:, axis] - (hi[axis] if side else lo[axis])) < 1e-9) & (u > c0) & (u < c1) & (y > y0) & (y < y1)
        rgb[on] = col
    return p, nrm, rgb


def render_photo(points, rgb, R, eye, K, size):
    """Reference pinhole render (OpenCV camera) of a point cloud: per pixel the mean colour of the
    points within 5 % of the nearest depth (independent of the cube-map code)."""
    w, h = size
    c = (points - eye) @ R.T
    ok = c[:, 2] > 0.05
    uv = c[ok] @ K.T
    col, row = np.floor(uv[:, 0] / uv[:, 2]).astype(int), np.floor(uv[:, 1] / uv[:, 2]).astype(int)
    d, cc = c[ok, 2], rgb[ok]
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    return nearest_mean((row * w + col)[inside], d[inside], cc[inside], size)


def nearest_mean(pix, d, rgb, size):
    """(h, w, 3) image: per pixel index ``pix`` the mean colour of the points within 5 % of its nearest depth ``d``."""
    w, h = size
    zmin = np.full(w * h, np.inf)
    np.minimum.at(zmin, pix, d)
    front = d <= zmin[pix] * 1.05
    img = np.zeros((w * h, 3))
    np.add.at(img, pix[front], rgb[front])
    cnt = np.bincount(pix[front], minlength=w * h)
    return (img / np.maximum(cnt, 1)[:, None]).reshape(h, w, 3)


def test_rotation_helpers():
    R = camera.look_rotation(np.array([0.0, 0.0, -1.0]))
    assert np.allclose(R, [[1, 0, 0], [0, -1, 0], [0, 0, -1]])  # OpenCV: x right, y down, z forward
    assert np.isclose(np.linalg.det(R), 1.0)
    R2 = rp.rotvec_perturb(R, np.array([0.0, 0.0, np.radians(7.0)]))
    assert rp.pose_error(R2, np.zeros(3), R, np.ones(3)) == pytest.approx((7.0, np.sqrt(3)))
    d = rp.fibonacci_directions(500)
    assert np.allclose(np.linalg.norm(d, axis=1), 1) and np.abs(d.mean(axis=0)).max() < 0.01


def test_synthetic_room_known_pose_and_exposure():
    pts, nrm, hdr = synthetic_room()
    e, k = 0.5, 3.0                                   # LDR = clip(e·L), photo = k·L → α = e / k
    ldr = np.round(np.clip(e * hdr, 0, 1) * 255) / 255
    eye = np.array([3.1, 1.55, 1.2])
    R = rp.rotvec_perturb(camera.look_rotation(np.array([-1.0, -0.15, -0.35]), np.radians(3.0)), np.zeros(3))
    size, fov = (128, 96), 60.0
    K = camera.intrinsics(fov, size)
    dense, _, dense_hdr = synthetic_room(600_000, seed=1)     # the photo: an independent, denser sample
    photo = k * render_photo(dense, dense_hdr, R, eye, K, size)
    assert (photo.sum(axis=-1) == 0).mean() < 0.03
    reg = rp.register(pts, ldr, photo, fov, grid=5, n_dirs=400, top=3, normals=nrm)
    rot_err, pos_err = rp.pose_error(reg.R, reg.eye, R, eye)
    ex = rp.exposure_from_pose(pts, ldr, photo, K, reg.R, reg.eye, block_px=8, normals=nrm)
    print(f"synthetic: {rot_err:.2f} deg, {pos_err:.3f} m, NCC {reg.score:.3f}, alpha {ex['alpha_sum'] / (e / k):.4f}× "
          f"({ex['blocks']} blocks, {reg.seconds:.1f} s)")
    # measured (02:02 UTC): 2.61°, 0.386 m, α_sum −3.3 %; the score's maximum is itself off the truth
    # here (NCC 0.928 found vs 0.914 at the true pose, 128²): a smooth texture lets translation and
    # rotation trade off.  Bounds = measured + headroom.
    assert rot_err < 4.0 and pos_err < 0.6
    assert ex["alpha_sum"] == pytest.approx(e / k, rel=0.05)


# (photo, truth file) of the shipped sample.  Measured 03:37–03:41 UTC (point refinement; see the module
# docstring): pose 0.48° 0.13 m / 0.34° 0.08 m / 0.09° 0.02 m; α_sum +0.6 / −2.2 / −2.0 %, α (median of
# blocks) +0.5 / −2.4 / −3.9 %; at the TRUE pose α_sum +0.0 / −1.9 / −1.1 %: the α step's own noise on
# this sample (64-spp cloud) is the limit now, not the pose.  Eq. 1: −47 / −56 / −83 %.
SHIPPED = [("photo.exr", "truth.npz"), ("photo_lights.exr", "truth_lights.npz"), ("photo_sun.exr", "truth_sun.npz")]


def shipped(photo_name, truth):
    tr = io.read_npz(SAMPLES / "truth" / truth, "pcrelight.truth/1")
    cloud = io.read_cloud(SAMPLES / "cloud_ldr.ply")
    photo = io.read_image(SAMPLES / photo_name)[..., :3].astype(np.float64)
    W = tr["photo_world_to_camera"]
    return (tr, cloud.points.astype(np.float64), cloud.colors.astype(np.float64), cloud.normals.astype(np.float64),
            photo, W[:3, :3], -W[:3, :3].T @ W[:3, 3])


@pytest.mark.parametrize("photo_name,truth", SHIPPED)
def test_shipped_alpha_at_the_true_pose(photo_name, truth):
    """The exposure step alone: with the photo's true camera, α_sum within 2.5 % of alpha_true."""
    tr, pts, col, nrm, photo, R, eye = shipped(photo_name, truth)
    ex = rp.exposure_from_pose(pts, col, photo, tr["photo_K"], R, eye, normals=nrm)
    assert ex["blocks"] > 100
    assert ex["alpha_sum"] / float(tr["alpha_true"]) == pytest.approx(1.0, abs=0.025)


# photo.exr misses the 2 % on the sample re-baked with the 24 576 cap (07:00 UTC): pose 0.83° / 0.12 m,
# α_sum +2.45 % (+1.17 % even at the TRUE pose: the exposure step's own scatter, ±1–2.5 % from view to
# view on this cloud; on the previous bake the same photo gave +0.05 %). Issue 14's α target is not met
# there; the test says so (strict: it fails when the photo comes within 2 %).
@pytest.mark.parametrize("photo_name,truth", SHIPPED)
def test_shipped_sample_pose_and_alpha(photo_name, truth):
    """data_samples (small preset, 200 000 points, photos 384×256 at 70°): the registered pose and
    α_sum against the photo's truth file (never given to the registration), and the confidence
    fields of a good registration."""
    tr, pts, col, nrm, photo, R_true, eye_true = shipped(photo_name, truth)
    reg = rp.register(pts, col, photo, 70.0, normals=nrm)
    rot_err, pos_err = rp.pose_error(reg.R, reg.eye, R_true, eye_true)
    K = camera.intrinsics(70.0, (photo.shape[1], photo.shape[0]))
    ex = rp.exposure_from_pose(pts, col, photo, K, reg.R, reg.eye, normals=nrm)
    a = ex["alpha_sum"] / float(tr["alpha_true"])
    print(f"{photo_name}: {rot_err:.2f} deg, {pos_err:.3f} m, alpha_sum {a:.4f}× true, "
          f"alpha {ex['alpha'] / float(tr['alpha_true']):.4f}×, score {reg.score:.3f}, {reg.points} points, "
          f"cover {reg.cover:.2f}, margin {reg.margin:.3f}, {reg.seconds:.0f} s")
    # measured on the sample re-baked with the 24 576 cap (2026-12-02 ~07:20 UTC, expose-match's run of
    # the same function): 0.83° / 0.12 m, 0.29° / 0.05 m (the new 'lights' camera), sun ~0.05 m; α_sum
    # +2.45 / −1.02 / −0.87 % with the cube-map visibility; with exposure_from_pose's surfel visibility
    # (default since 2026-12-02 13:00 UTC: the grazing floor counts) +1.92 / −0.32 / −0.74 %; NCC 0.829 /
    # 0.919 / 0.960. (Previous bake, 16 384 cap: 0.40° / 0.034 m, 0.43° / 0.048 m, 0.15° / 0.041 m; α_sum
    # +0.05 / −0.48 / −0.08 %.) The 2 %: the test asserts it.
    assert rot_err < 1.5 and pos_err < 0.4
    assert a == pytest.approx(1.0, abs=0.02)
    assert reg.score > 0.45 and reg.points > 2000 and reg.cover > 0.6
    # (no bound on reg.margin: it is not a confidence signal — an unrelated image's margin, 0.07–0.15,
    # is no lower than a good photo's, 0.021 / 0.073 / 0.956 on the re-baked data_samples)


def test_refine_points_recovers_a_perturbed_pose():
    """The point refinement alone, from the true pose of photo_sun.exr moved by 3° and 0.5 m (the
    size of the cube-map stage's errors): back within 0.5° and 0.15 m (measured 04:08 UTC: 0.09°,
    0.022 m)."""
    tr, pts, col, nrm, photo, R_true, eye_true = shipped(*SHIPPED[2])
    R0 = rp.rotvec_perturb(R_true, np.radians(3.0) * np.array([0.6, -0.64, 0.48]))
    e0 = eye_true + 0.5 * np.array([0.48, 0.6, -0.64])
    f = rp.refine_points(pts, col, photo, tr["photo_K"], R0, e0, normals=nrm, sigmas_px=(8.0, 4.0, 2.0, 1.0))
    rot_err, pos_err = rp.pose_error(f.R, f.eye, R_true, eye_true)
    print(f"refine_points: {rot_err:.2f} deg, {pos_err:.3f} m, score {f.score:.3f}")
    assert rot_err < 0.5 and pos_err < 0.15


def test_unrelated_image_scores_low():
    """Confidence: a photo of something else (skimage's astronaut, linearised and scaled, 256×128)
    registered against the shipped cloud is not taken by expose-match's auto rule: measured 04:10 UTC
    final score 0.29 with this grid-5 lattice (0.21 with the default lattice, 91 s) on the previous
    bake; the shipped photos 0.60 / 0.73 / 0.90.  The coarser lattice keeps the test short."""
    from skimage import data

    img = (data.astronaut()[::2, ::2].astype(np.float64) / 255.0) ** 2.2 * 3.0
    _, pts, col, nrm, _, _, _ = shipped(*SHIPPED[0])
    reg = rp.register(pts, col, img[64:192], 70.0, normals=nrm, grid=5)
    print(f"unrelated: score {reg.score:.3f}, {reg.points} points, cover {reg.cover:.2f}, margin {reg.margin:.3f}")
    # on the sample re-baked with the 24 576 cap (08:05 UTC) the final score alone no longer separates it:
    # 0.462 (≥ expose-match's 0.45), matched on a corner of the photo (751 points, cover 0.50); the
    # shipped photos cover ≥ 0.6. expose-match's auto rule (NCC, cover, blocks) must reject it.
    from pipeline.expansion.expose_match import ExposeMatchConfig

    cfg = ExposeMatchConfig()
    assert reg.score < cfg.min_register_ncc or reg.cover < cfg.min_register_cover


def test_surfel_visibility_sees_a_grazing_floor_and_not_behind_a_panel():
    """surfel_visible (the registered photo's visibility in reproject): a floor seen at grazing
    incidence from eye height 1.7 m (the shipped photos' case) is seen, the floor hidden behind a
    1 m panel is not, and points facing away are not.  Truth by geometry: the ray over the panel's
    top (1 m at 6 m) reaches the floor only beyond 14.6 m, so behind the panel means |x| < |z|/6."""
    rng = np.random.default_rng(11)
    n = 40_000
    floor = np.c_[rng.uniform(-6, 6, n), np.zeros(n), rng.uniform(-12, -2, n)]
    panel = np.c_[rng.uniform(-1, 1, 4000), rng.uniform(0, 1, 4000), np.full(4000, -6.0)]
    pts = np.vstack([floor, panel])
    nrm = np.vstack([np.tile([0.0, 1.0, 0.0], (n, 1)), np.tile([0.0, 0.0, 1.0], (4000, 1))])
    nrm[:1000] *= -1                                           # the first 1000 floor points face down
    from pipeline.expansion.splats import knn_splat_radii

    eye = np.array([0.0, 1.7, 0.0])
    seen = rp.surfel_visible(pts, nrm, knn_splat_radii(pts), eye, np.arange(n))
    x, z = floor[:, 0], floor[:, 2]
    up = np.arange(n) >= 1000
    behind = (z < -6.3) & (np.abs(x) < 0.9 * np.abs(z) / 6)
    clear = up & ((z > -5.7) | (np.abs(x) > 1.2 * np.abs(z) / 6))
    assert not seen[~up].any()
    assert not seen[behind & up].any()
    assert seen[clear].mean() > 0.99
    far = clear & (np.hypot(x, z) > 7)                          # incidence cos < 0.24
    assert far.sum() > 10_000 and seen[far].mean() > 0.99


def test_surfel_visibility_casts_against_the_discs_near_the_rays_only():
    """surfel_visible builds its ray-casting scene from the discs that may meet a ray to a query point
    (:func:`register_photo._discs_near_rays`): the same answers as with every disc, for a frustum-like set of
    query points and for all of them; the cull leaves out most of the room for a narrow set."""
    from pipeline.expansion.splats import knn_splat_radii

    pts, nrm, _ = synthetic_room(60_000, seed=2)
    rng = np.random.default_rng(5)                   # a panel in the room hides part of the wall behind it
    panel = np.c_[np.full(3000, -1.0), rng.uniform(1.0, 2.2, 3000), rng.uniform(0.0, 1.0, 3000)]
    pts, nrm = np.vstack([pts, panel]), np.vstack([nrm, np.tile([1.0, 0.0, 0.0], (3000, 1))])
    r = knn_splat_radii(pts)
    eye = np.array([1.0, 1.6, 0.5])
    d = pts - eye
    narrow = np.flatnonzero((d[:, 0] < 0) & (np.abs(d[:, 2]) < 0.5 * -d[:, 0]) & (np.abs(d[:, 1]) < 0.4 * -d[:, 0]))
    everything = lambda P, rad, e, tg: np.ones(len(P), dtype=bool)  # noqa: E731
    for q in (narrow, np.arange(len(pts))):
        got = rp.surfel_visible(pts, nrm, r, eye, q)
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(rp, "_discs_near_rays", everything)
            ref = rp.surfel_visible(pts, nrm, r, eye, q)
        assert np.array_equal(got, ref) and 0.5 < ref.mean() < 0.99
    assert rp._discs_near_rays(pts, 0.8 * r.astype(float), eye, pts[narrow]).mean() < 0.35


def test_smooth_features_in_chunks_and_the_register_subset():
    """smooth_features gives the same numbers whatever its chunk of pairs; register_subset is fixed, sorted and
    None at or below the cap."""
    pts, _, hdr = synthetic_room(20_000, seed=4)
    col = np.clip(0.5 * hdr, 0, 1)
    sig = 0.05 + 0.1 * np.random.default_rng(0).random(len(pts))
    assert np.array_equal(rp.smooth_features(pts, col, sig, chunk=1_111), rp.smooth_features(pts, col, sig))
    assert rp.register_subset(500_000) is None and rp.register_subset(10, 0) is None
    a, b = rp.register_subset(3_000_000), rp.register_subset(3_000_000)
    assert len(a) == rp.MAX_REGISTER_POINTS and np.array_equal(a, b) and (np.diff(a) > 0).all()


# ----------------------------------------------------------------------------- panoramas (issue 25)
def test_level_rotation_is_the_placed_panorama_turned_about_up():
    """level_rotation(0) is the placed panorama's axes; at yaw ψ the centre column looks along (sin ψ, 0, cos ψ)
    and the zenith row stays world +Y; turning by ψ moves every point W·ψ/2π columns right (np.roll by k columns is
    a turn of 2π·k/W; best_yaw reads it off the shift)."""
    from pipeline.camera import PANORAMA_ROTATION

    assert np.array_equal(rp.level_rotation(0.0), PANORAMA_ROTATION)
    psi = np.radians(52.0)
    R = rp.level_rotation(psi)
    assert np.allclose(R.T @ [0, 0, 1], [np.sin(psi), 0, np.cos(psi)]) and np.allclose(R.T @ [0, -1, 0], [0, 1, 0])
    w2c0, w2c = np.eye(4), np.eye(4)
    w2c0[:3, :3], w2c[:3, :3] = PANORAMA_ROTATION, R
    d = np.random.default_rng(0).normal(size=(50, 3))
    u0, _, _, _ = camera.project_points("equirect", d, (256, 128), w2c0)
    u1, _, _, _ = camera.project_points("equirect", d, (256, 128), w2c)
    assert np.allclose(np.mod(u1 - u0 - 256 * psi / (2 * np.pi) + 128, 256) - 128, 0, atol=1e-9)
    s = np.zeros(256)
    s[(-37) % 256] = 1.0                                   # the cloud 37 columns back: the panorama turned by +37
    assert rp.best_yaw(s)[1] == pytest.approx(2 * np.pi * 37 / 256)


def _shipped_pano(roll: int = 0):
    """data_samples/pano.exr box-filtered to 256×128 and turned by ``roll`` columns (np.roll), the cloud and
    scene.json's panorama centre."""
    scene = io.read_json(SAMPLES / "scene.json")
    cloud = io.read_cloud(SAMPLES / "cloud_ldr.ply")
    pano = np.roll(rp.downsample(io.read_image(SAMPLES / scene["panorama"]["file"])[..., :3].astype(np.float64), 4),
                   roll, axis=1)
    return (pano, cloud.points.astype(np.float64), np.clip(cloud.colors, 0, 1).astype(np.float64),
            cloud.normals.astype(np.float64), np.asarray(scene["panorama"]["centre"], float),
            np.asarray(scene["panorama"]["world_to_camera"], float))


PANO_FAST = dict(max_points=40_000, width=64, fine_width=128, sigmas_px=(2.0, 1.0))   # keeps a test near 25 CPU s


@pytest.mark.parametrize("roll", [0, 37])
def test_shipped_panorama_centre_and_yaw(roll):
    """register_panorama on the shipped panorama (256×128 of its 1024×512, on 40 000 of the 200 000 points),
    as shipped and turned by 37 columns (52.03°): the centre within 5 cm of scene.json's, the yaw within 0.2° of
    the turn (scene.json's panorama has yaw 0: its world_to_camera is level_rotation(0)), a confident score.
    Measured 2026-12-06 01:54 UTC: 2.1 cm, 0.016° off, NCC 0.94, cover 0.80 (the full 1024×512 panorama on
    all points: 1.4 cm, 0.00002°, NCC 0.975, 57 CPU s)."""
    pano, pts, col, nrm, centre, w2c = _shipped_pano(roll)
    assert np.allclose(w2c[:3, :3], rp.level_rotation(0.0))
    reg = rp.register_panorama(pts, col, pano, normals=nrm, **PANO_FAST)
    turn = 360.0 * roll / pano.shape[1]
    err_m = float(np.linalg.norm(reg.eye - centre))
    err_deg = abs((reg.yaw_deg - turn + 180) % 360 - 180)
    print(f"panorama roll {roll}: {100 * err_m:.1f} cm, yaw {reg.yaw_deg:.3f}° (turn {turn:.3f}°, {err_deg:.3f}° off), "
          f"NCC {reg.score:.3f}, cover {reg.cover:.2f}, margin {reg.margin:.3f}, {reg.seconds:.0f} s")
    assert err_m < 0.05 and err_deg < 0.2
    assert np.allclose(reg.R, rp.level_rotation(np.radians(reg.yaw_deg)))
    from pipeline.expansion.expose_match import ExposeMatchConfig

    cfg = ExposeMatchConfig()
    assert reg.score >= cfg.min_register_ncc and reg.cover >= cfg.min_register_cover


def test_panorama_of_another_room_scores_low():
    """Confidence: the synthetic room's panorama (a 256×128 equirect render from inside it) registered against
    the shipped cloud is not taken by expose-match's rules (measured 02:00 UTC: NCC 0.08, cover 0.50; the shipped
    panorama 0.94–0.975; the shipped panorama against the synthetic room's cloud: 0.14)."""
    from pipeline.expansion.expose_match import ExposeMatchConfig
    from tests.test_photo_set import _render_equirect

    dense, _, dense_hdr = synthetic_room(300_000, seed=1)
    pano = 2.0 * _render_equirect(dense, dense_hdr, np.array([0.5, 1.7, 0.3]), (256, 128))
    _, pts, col, nrm, _, _ = _shipped_pano()
    reg = rp.register_panorama(pts, col, pano, normals=nrm, **PANO_FAST)
    print(f"another room's panorama: NCC {reg.score:.3f}, cover {reg.cover:.2f}, margin {reg.margin:.3f}")
    cfg = ExposeMatchConfig()
    assert reg.score < cfg.min_register_ncc or reg.cover < cfg.min_register_cover
