"""make-scene: checks of how we use Mitsuba 3 against independent truths (analytic radiometry,
conventions), the closed atrium, determinism, and the CLI's errors. Small spp, pooled statistics."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from pipeline import camera, io
from pipeline.scene import geometry as geo
from pipeline.scene import mitsuba_render as smi
from pipeline.scene.make_scene import MATERIALS, MakeSceneConfig, bake_cloud, ldr_from_hdr, render_view, run_make_scene

INTEGRATOR = {"type": "path", "max_depth": -1, "rr_depth": 5, "hide_emitters": False}


def _scene(root: Path, meshes: list[geo.Mesh]) -> dict:
    """Write the meshes and return a scene.json-like description of them."""
    entries = []
    for m in meshes:
        f = f"meshes/{m.name}.ply"
        io.write_mesh(root / f, m.vertices)
        entries.append({"name": m.name, "file": f, "albedo": list(m.albedo), "emission": list(m.emission),
                        "area": float(geo.triangle_areas(m.triangles).sum())})
    return {"meshes": entries}


def _inward_sphere(radius: float, subdiv: int = 2) -> np.ndarray:
    V, F = geo.icosphere(subdiv)
    return (V[F[:, [0, 2, 1]]] * radius).reshape(-1, 3)


def _pooled(mean: np.ndarray, var: np.ndarray) -> tuple[float, float]:
    """Pooled mean of per-point means and its standard error (independent points)."""
    n = len(mean)
    return float(mean.mean()), float(np.sqrt(var.sum()) / n)


# --------------------------------------------------------------------------- radiometry
def test_white_furnace_pooled_and_1_over_sqrt_spp(tmp_path):
    rho, le = 0.5, 1.0
    mesh = geo.Mesh("furnace", _inward_sphere(2.0), (rho,) * 3, (le,) * 3)
    sc = _scene(tmp_path, [mesh])
    room = smi.load_room(tmp_path, sc, INTEGRATOR)
    tr = smi.Tracer(seed=3)
    truth = le / (1 - rho)
    rms = {}
    for spp in (4, 16):
        b = bake_cloud(tr, room, [mesh], 1500, spp, np.random.default_rng(spp), tag=f"furnace{spp}")
        assert b["rejected"] == 0
        lum = b["mean"].mean(axis=1)
        m, se = _pooled(lum, b["var"].mean(axis=1))
        assert abs(m - truth) < 3 * se, (spp, m, se)
        err = lum - truth
        rms[spp] = float(np.sqrt(np.mean(err ** 2)))
        # the variance estimate agrees with the observed scatter (mean squared error ≈ mean variance)
        ratio = np.mean(err ** 2) / np.mean(b["var"].mean(axis=1))
        assert 0.6 < ratio < 1.6, (spp, ratio)
    shrink = rms[4] / rms[16]
    assert 1.6 < shrink < 2.5, shrink  # 1/sqrt(spp): 4× the paths, half the error


def _disc_fan(center, radius, n, normal_sign):
    c = np.asarray(center, float)
    t = np.linspace(0, 2 * np.pi, n + 1)
    b = geo.Builder()
    for a0, a1 in zip(t[:-1], t[1:]):
        b.tri(c, c + radius * np.array([np.cos(a0), 0, np.sin(a0)]), c + radius * np.array([np.cos(a1), 0, np.sin(a1)]),
              np.array([0, normal_sign, 0.0]))
    return b.array()


def _dome(radius, n_az, n_el):
    """Upper hemisphere (normals inwards) whose rim matches _disc_fan(radius, n_az)."""
    b = geo.Builder()
    az = np.linspace(0, 2 * np.pi, n_az + 1)
    el = np.linspace(0, np.pi / 2, n_el + 1)
    p = lambda a, e: radius * np.array([np.cos(e) * np.cos(a), np.sin(e), np.cos(e) * np.sin(a)])  # noqa: E731
    for i in range(n_az):
        for j in range(n_el):
            q = [p(az[i], el[j]), p(az[i + 1], el[j]), p(az[i + 1], el[j + 1]), p(az[i], el[j + 1])]
            mid = sum(q) / 4
            b.quad(*q, -mid)
    return b.array()


def test_plane_under_uniform_hemisphere(tmp_path):
    rho, L = 0.6, 1.0
    floor = geo.Mesh("floor", _disc_fan((0, 0, 0), 3.0, 48, 1), (rho,) * 3)
    dome = geo.Mesh("dome", _dome(3.0, 48, 12), (0.0,) * 3, (L,) * 3)
    room = smi.load_room(tmp_path, _scene(tmp_path, [floor, dome]), INTEGRATOR)
    b = bake_cloud(smi.Tracer(seed=1), room, [floor], 400, 8, np.random.default_rng(0))
    m, se = _pooled(b["mean"][:, 1], b["var"][:, 1])
    assert abs(m - rho * L) < 3 * se + 1e-6, (m, se)


def _polygon_irradiance_factor(x, n, verts):
    """Lambert's polygon formula: E / L for a uniform Lambertian emitter polygon seen from x."""
    v = verts - x
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    tot = 0.0
    for i in range(len(v)):
        a, b = v[i], v[(i + 1) % len(v)]
        c = np.cross(a, b)
        tot += np.arccos(np.clip(a @ b, -1, 1)) * (c / np.linalg.norm(c)) @ n
    return 0.5 * abs(tot)


def test_plane_under_small_emissive_disc(tmp_path):
    rho, L, a, h, nseg = 0.5, 10.0, 0.3, 1.5, 32
    box = geo.Mesh("box", np.concatenate([_cube_faces(2.0, skip_bottom=True)]), (0.0,) * 3)
    floor = geo.Mesh("floor", _cube_bottom(2.0), (rho,) * 3)
    disc = geo.Mesh("disc", _disc_fan((0, h - 2.0, 0), a, nseg, -1), (0.0,) * 3, (L,) * 3)
    room = smi.load_room(tmp_path, _scene(tmp_path, [box, floor, disc]), INTEGRATOR)
    p = np.array([0.0, -2.0, 0.0])
    n = np.array([0.0, 1.0, 0.0])
    pts = np.repeat(p[None], 256, axis=0)
    nrm = np.repeat(n[None], 256, axis=0)
    m, v, _ = smi.Tracer(seed=2).radiance(room, pts + 2e-3 * nrm, -nrm, 32, "disc")
    t = np.linspace(0, 2 * np.pi, nseg + 1)[:-1]
    verts = np.stack([a * np.cos(t), np.full_like(t, h - 2.0), a * np.sin(t)], axis=1)
    expected = rho / np.pi * L * _polygon_irradiance_factor(p, n, verts)
    # the polygon formula agrees with the disc formula ρ L a²/(h²+a²) up to the polygon's area
    assert abs(expected / (rho * L * a * a / (h * h + a * a)) - 1) < 0.01
    pm, pse = _pooled(m[:, 0], v[:, 0])
    assert abs(pm - expected) < 3 * pse, (pm, pse, expected)


def _cube_faces(s: float, skip_bottom=False) -> np.ndarray:
    """Inward faces of the cube [-s, s]³ (optionally without its bottom)."""
    b = geo.Builder()
    for axis in range(3):
        for sign in (1, -1):
            if skip_bottom and axis == 1 and sign == -1:
                continue
            b.quad(*_face(s, axis, sign), -sign * np.eye(3)[axis])
    return b.array()


def _cube_bottom(s: float) -> np.ndarray:
    b = geo.Builder()
    b.quad(*_face(s, 1, -1), np.eye(3)[1])
    return b.array()


def _face(s, axis, sign):
    u, v = [i for i in range(3) if i != axis]
    pts = []
    for cu, cv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
        p = np.zeros(3)
        p[axis], p[u], p[v] = sign * s, cu * s, cv * s
        pts.append(p)
    return pts


# --------------------------------------------------------------------------- adaptive sampling
def test_adaptive_sampling_reaches_target_and_ignores_other_rays(tmp_path):
    """A box with one emissive black face (rays at it: radiance Le exactly, zero variance, done
    after the first round) and grey faces (noisy): the noisy rays keep sampling until their
    relative standard error is ≤ target or the cap; a ray's result depends on its index, the
    round and the seed only — identical when the other rays change (here: all made noise-free)."""
    b = geo.Builder()
    meshes = []
    for axis in range(3):
        for sign in (1, -1):
            b = geo.Builder()
            b.quad(*_face(1.0, axis, sign), -sign * np.eye(3)[axis])
            em = (5.0,) * 3 if (axis, sign) == (1, 1) else (0.0,) * 3
            meshes.append(geo.Mesh(f"f{axis}{sign:+d}", b.array(), (0.0,) * 3 if em[0] else (0.5,) * 3, em))
    room = smi.load_room(tmp_path, _scene(tmp_path, meshes), INTEGRATOR)
    rng = np.random.default_rng(0)
    n = 400
    o = rng.uniform(-0.5, 0.5, (n, 3))
    up = np.tile([0, 1.0, 0], (n, 1))                 # at the emitter: exact
    side = np.tile([1.0, 0, 0], (n, 1))               # at a grey wall: noisy
    noisy = np.arange(n) % 2 == 0
    d = np.where(noisy[:, None], side, up)
    target, cap = 0.05, 512
    m, v, lv, cnt = smi.Tracer(seed=4, lanes=4096).radiance(room, o, d, 8, "ad", target, cap, counts=True)
    # exact rays: the target is met after rounds 0 and 1 (two consecutive rounds) → 8 + 8 samples
    assert np.all(cnt[~noisy] == 16) and np.all(v[~noisy] == 0) and np.allclose(m[~noisy], 5.0)
    rel = np.sqrt(lv) / m.mean(axis=1)
    assert np.all((rel[noisy] <= target) | (cnt[noisy] == cap)) and np.mean(rel[noisy] <= target) > 0.9
    assert set(np.unique(cnt[noisy])) <= {8, 16, 32, 64, 128, 256, 512} and cnt[noisy].max() > 8
    # pooled truth of the noisy rays from a high-spp plain estimate agrees within the errors
    ref, rv, _ = smi.Tracer(seed=9, lanes=4096).radiance(room, o[noisy], d[noisy], 512, "ref")
    diff = m[noisy].mean(axis=1) - ref.mean(axis=1)
    assert abs(diff.mean()) < 4 * np.sqrt((v[noisy].mean(axis=1) + rv.mean(axis=1)).sum()) / noisy.sum()
    # the other rays made noisy too (at the −x wall: sampled in later rounds as well): the first
    # rays' results are byte-identical (fixed layout per round)
    d2 = np.where(noisy[:, None], side, -side)
    m2, v2, _, cnt2 = smi.Tracer(seed=4, lanes=4096).radiance(room, o, d2, 8, "ad", target, cap, counts=True)
    assert cnt2[~noisy].max() > 16
    assert np.array_equal(m2[noisy], m[noisy]) and np.array_equal(v2[noisy], v[noisy]) and np.array_equal(cnt2[noisy], cnt[noisy])
    # and a plain estimate is the adaptive one's first round (a ray's mean with cap = spp)
    m8, _, _ = smi.Tracer(seed=4, lanes=4096).radiance(room, o, d, 8, "ad")
    m8a, _, _, c8 = smi.Tracer(seed=4, lanes=4096).radiance(room, o, d, 8, "ad", target, 8, counts=True)
    assert np.array_equal(m8, m8a) and np.all(c8 == 8)


# --------------------------------------------------------------------------- conventions
def test_orientation_cloud_and_photo(tmp_path):
    colours = {(0, 1): (1.0, 0, 0), (1, 1): (0, 1.0, 0), (2, 1): (0, 0, 1.0)}  # +X red, +Y green, +Z blue
    meshes = []
    for axis in range(3):
        for sign in (1, -1):
            b = geo.Builder()
            b.quad(*_face(1.0, axis, sign), -sign * np.eye(3)[axis])
            em = colours.get((axis, sign), (0.1, 0.1, 0.1))
            meshes.append(geo.Mesh(f"f{axis}{sign:+d}", b.array(), (0.0,) * 3, em))
    room = smi.load_room(tmp_path, _scene(tmp_path, meshes), INTEGRATOR)
    tr = smi.Tracer(seed=0)
    b = bake_cloud(tr, room, meshes, 600, 2, np.random.default_rng(0))
    p, c = b["points"], b["mean"]
    axis = np.argmax(np.abs(p), axis=1)
    sign = np.sign(p[np.arange(len(p)), axis]).astype(int)
    want = np.array([colours.get((a, s), (0.1, 0.1, 0.1)) for a, s in zip(axis, sign)])
    np.testing.assert_allclose(c, want, atol=1e-5)
    np.testing.assert_allclose(b["normals"], -sign[:, None] * np.eye(3)[axis], atol=1e-6)  # inward normals
    # the photo camera: at the centre, looking along +Z, +Y up, 120° vertical fov (sees 5 faces)
    W = H = 33
    M = camera.look_at((0, 0, 0), (0, 0, 1), (0, 1, 0))
    K = camera.intrinsics(120.0, (W, H))
    o, d = camera.camera_rays(M, K, (W, H))
    img = tr.radiance(room, o, d, 2, "photo")[0].reshape(H, W, 3)
    np.testing.assert_allclose(img[16, 16], (0, 0, 1), atol=1e-5)        # straight ahead: +Z
    np.testing.assert_allclose(img[0, 16], (0, 1, 0), atol=1e-5)         # top row: +Y
    np.testing.assert_allclose(img[16, 0], (1, 0, 0), atol=1e-5)         # left: +X (right-handed, +Y up)
    np.testing.assert_allclose(img[16, 32], (0.1, 0.1, 0.1), atol=1e-5)  # right: −X
    np.testing.assert_allclose(img[32, 16], (0.1, 0.1, 0.1), atol=1e-5)  # bottom: −Y
    # K and world_to_camera project a world point back to the pixel whose ray passes through it
    x = o[5 * W + 7] + 0.8 * d[5 * W + 7]
    q = K @ (M[:3, :3] @ x + M[:3, 3])
    np.testing.assert_allclose(q[:2] / q[2], (7.5, 5.5), atol=1e-9)


# --------------------------------------------------------------------------- references
def test_gather_and_full_of_white_sphere_in_uniform_enclosure(tmp_path):
    L = 1.0
    encl = geo.Mesh("enclosure", _inward_sphere(4.0), (0.0,) * 3, (L,) * 3)
    sc = _scene(tmp_path, [encl])
    V, F, N = geo.object_sphere(4)
    io.write_mesh(tmp_path / "sphere.ply", V, F, N)
    obj = {"ply": "sphere.ply", "to_world": np.eye(4).tolist()}
    mats = {m: MATERIALS[m] for m in ("lambert", "ggx0.5")}
    view = {"eye": [0, 0, 3.0], "target": [0, 0, 0], "up": [0, 1, 0], "fov_deg": 50.0, "size": [12, 12]}
    runs = []
    for _ in range(2):  # the second time from freshly loaded scenes: byte-identical results
        room = smi.load_room(tmp_path, sc, INTEGRATOR)
        obj_scene = smi.load_object_only(tmp_path, obj)
        full = {name: smi.load_room(tmp_path, sc, INTEGRATOR, obj, smi.material_bsdf(m)) for name, m in mats.items()}
        runs.append(render_view(smi.Tracer(seed=5), room, obj_scene, full, view, 32, 2, "t", mats))
    r = runs[0]
    for k, (img, var) in r["images"].items():
        assert np.array_equal(img, runs[1]["images"][k][0]) and np.array_equal(var, runs[1]["images"][k][1]), k
    mask = r["mask"]
    # mask: the sphere (angular radius asin(1/3)) covers the expected share of pixel centres
    M, K = camera.look_at(view["eye"], view["target"], view["up"]), camera.intrinsics(50.0, (12, 12))
    o, d = camera.camera_rays(M, K, (12, 12))
    inside = (d @ np.array([0, 0, -1.0])) > np.cos(np.arcsin(1 / 3))
    assert np.array_equal(mask.reshape(-1), inside)
    for name in mats:
        g, gv = r["images"][f"gather_{name}"]
        f, fv = r["images"][f"full_{name}"]
        assert np.array_equal(g[..., 3] > 0, mask) and np.array_equal(f[..., 3] > 0, mask)
        gm, gse = _pooled(g[..., 0][mask], gv[..., 0][mask])
        fm, fse = _pooled(f[..., 0][mask], fv[..., 0][mask])
        assert abs(gm - fm) < 3 * np.hypot(gse, fse), (name, gm, fm)   # convex object: full = gather
        if name == "lambert":
            assert abs(gm - 0.8 * L) < 3 * gse, (gm, gse)
            assert abs(fm - 0.8 * L) < 3 * fse, (fm, fse)
            # every pixel, not only the pool: within 4 of its own standard errors
            z = np.abs(g[..., 0][mask] - 0.8) / np.sqrt(gv[..., 0][mask] + 1e-12)
            assert np.mean(z < 4) > 0.97


# --------------------------------------------------------------------------- the atrium
def test_atrium_is_closed(tmp_path):
    meshes = geo.atrium(geo.AtriumParams())
    room = smi.load_room(tmp_path, _scene(tmp_path, meshes), INTEGRATOR)
    rng = np.random.default_rng(0)
    n = 60000
    # random points in the courtyard and in both galleries (both storeys), random directions
    boxes = [((-14.5, 0.2, -3.5), (14.5, 11.8, 3.5)), ((-14.5, 0.2, 4.5), (14.5, 4.8, 6.8)),
             ((-14.5, 5.6, -6.8), (14.5, 9.8, -4.5))]
    o = np.concatenate([lo + (np.array(hi) - lo) * rng.random((n // 3, 3)) for lo, hi in boxes])
    d = rng.normal(size=o.shape)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, ng, valid = smi.Tracer(0).first_hits(room, o, d)
    assert valid.all(), f"{np.count_nonzero(~valid)} of {len(o)} rays escaped"
    # every surface met from inside is met from its visible side (no inverted or hidden faces)
    assert np.mean(np.sum(ng * d, axis=1) < 0) > 0.999


def test_ldr_exposure_and_quantisation(tmp_path):
    rng = np.random.default_rng(0)
    hdr = np.exp(rng.normal(0, 2, (5000, 3))).astype(np.float32)
    e, lin, codes = ldr_from_hdr(hdr, 0.05, 0.0, rng)
    sat = (codes == 255).any(axis=1).mean()
    assert abs(sat - 0.05) < 0.002
    io.write_cloud(tmp_path / "c.ply", io.Cloud(hdr, np.tile([0, 1, 0.0], (5000, 1)).astype(np.float32), lin), uchar_colors=True)
    from plyfile import PlyData

    v = PlyData.read(str(tmp_path / "c.ply"))["vertex"]
    got = np.stack([v["red"], v["green"], v["blue"]], axis=1)
    assert np.array_equal(got, codes)  # the uchar file holds exactly the quantised codes
    expect = np.round(io.srgb_encode(np.clip(e * hdr, 0, 1)) * 255)
    assert np.abs(codes.astype(float) - expect).max() <= 1


# --------------------------------------------------------------------------- determinism + CLI
MINI = dict(points=3000, cloud_spp=4, cloud_max_spp=8, photo_size=(24, 16), photo_spp=2, ref_size=(12, 12), ref_spp=4,
            ref_max_spp=8, ref_bg_spp=2, materials=("lambert",), pano_size=(32, 16), pano_spp=2)


def _digests(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and p.name != "report.json"}


def test_determinism_same_seed_identical_other_seed_different(tmp_path):
    runs, reps = {}, {}
    for name, seed in (("a", 0), ("b", 0), ("c", 1)):
        reps[name] = run_make_scene(tmp_path / name, MakeSceneConfig(seed=seed, **MINI), preview=(name == "c"))
        runs[name] = _digests(tmp_path / name)
    assert runs["a"] == runs["b"]
    assert set(runs["a"]) == {f for f in runs["c"] if not f.startswith("previews/")}
    for f in ("cloud_gt.ply", "cloud_ldr.ply", "photo.exr", "truth/truth.npz", "truth/gather_view1_lambert.exr", "pano.exr",
              "truth/truth_pano.npz"):
        assert runs["a"][f] != runs["c"][f], f
    # the outputs promised by the contract exist
    must = ["scene.json", "scene.xml", "cloud_gt.ply", "cloud_ldr.ply", "photo.exr", "object.glb", "object.obj",
            "object.ply", "object2.glb", "truth/truth.npz", "photo_lights.exr", "photo_sun.exr", "truth/truth_lights.npz",
            "truth/truth_sun.npz", "pano.exr", "truth/truth_pano.npz"] + \
        [f"truth/{k}_{v}_{m}{s}.exr" for k in ("gather", "full") for v in ("view1", "view2") for m in MINI["materials"] for s in ("", "_var")]
    assert not [f for f in must if f not in runs["a"]]
    # truth: alpha_true = e/k, and the overexposed mask follows its rule on the LDR cloud
    t = io.read_npz(tmp_path / "a" / "truth" / "truth.npz", "pcrelight.truth/1")
    assert np.isclose(t["alpha_true"], t["e"] / t["k"])
    ldr = io.read_cloud(tmp_path / "a" / "cloud_ldr.ply")
    rule = (io.luminance(ldr.colors) > 0.9) | (ldr.colors >= 1.0 - 1e-6).any(axis=1)
    assert np.array_equal(t["overexposed"].astype(bool), rule)
    gt = io.read_cloud(tmp_path / "a" / "cloud_gt.ply")
    assert gt.quality is not None and len(gt) == MINI["points"]
    np.testing.assert_allclose(np.linalg.norm(gt.normals, axis=1), 1, atol=1e-5)
    assert reps["a"]["photo_scale_k"] == t["k"] and reps["a"]["exposure_e"] == t["e"]
    # adaptive sampling (MINI: 4 spp first, cap 8): the reached precision is reported, the cap holds
    cp = reps["a"]["cloud_precision"]
    assert cp["n"] == MINI["points"] and cp["spp_max"] <= 8 and 4 <= cp["spp_mean"] <= 8 and 0 < cp["share_at_cap"] <= 1
    lum = io.luminance(gt.colors)
    rel = np.divide(gt.quality, lum, out=np.full(len(lum), np.inf), where=lum > 0)   # ∞: no light seen yet
    assert np.isclose(cp["rel_se_median"], np.median(rel), rtol=1e-3)
    pr = reps["a"]["references"]["view1/lambert"]["precision"]["gather"]
    assert pr["n"] == reps["a"]["references"]["view1/lambert"]["object_pixels"] and pr["spp_max"] <= 8
    assert (tmp_path / "c" / "previews" / "cloud_gt_panorama.png").exists()
    # scene.xml is a Mitsuba scene of its own: every mesh, the object, one emitter per emitting mesh
    import mitsuba as mi

    sj = io.read_json(tmp_path / "a" / "scene.json")
    xs = mi.load_file(str(tmp_path / "a" / "scene.xml"))
    assert len(xs.shapes()) == len(sj["meshes"]) + 1
    assert len(xs.emitters()) == sum(any(e > 0 for e in m["emission"]) for m in sj["meshes"])


def test_cli_errors(cli_run, tmp_path):
    code, _, err = cli_run("make-scene", "--out", tmp_path / "o", "--object", tmp_path / "missing.obj")
    assert code == 1 and "missing.obj: no such file" in err
    (tmp_path / "bad.obj").write_text("this is not a mesh\n")
    code, _, err = cli_run("make-scene", "--out", tmp_path / "o2", "--object", tmp_path / "bad.obj", "--points", "1000")
    assert code == 1 and "bad.obj" in err
    code, _, err = cli_run("make-scene", "--preset", "tiny", "--out", tmp_path / "o3", "--points", "5")
    assert code == 2 and "--points" in err


def test_object_placement_maps_bounding_sphere():
    from pipeline.scene.make_scene import _bounding_sphere, _to_world

    rng = np.random.default_rng(0)
    V = rng.normal(size=(500, 3)) * (3.0, 1.0, 0.5) + (10.0, -4.0, 2.0)   # any object, any units
    c, r = _bounding_sphere(V)
    M = _to_world((1.5, 1.3, -0.5), 1.0, c, r)
    W = V @ M[:3, :3].T + M[:3, 3]
    wc, wr = _bounding_sphere(W)
    np.testing.assert_allclose(wc, (1.5, 1.3, -0.5), atol=1e-9)
    assert abs(wr - 1.0) < 1e-9
    # the default objects are already unit-sized and centred: identity scale about the origin
    for kind in ("knot", "sphere"):
        V2 = (geo.object_knot if kind == "knot" else geo.object_sphere)()[0]
        assert abs(np.linalg.norm(V2, axis=1).max() - 1) < 1e-9


# --------------------------------------------------------------------------- photos, the lamp room
def test_tiny_photos_see_the_lights(tiny_scene):
    """The tiny atrium's photos: photo.exr (the brightest region), photo_lights.exr and
    photo_sun.exr, each with its own k and truth file; the sun photo sees the sun (its peak is
    the sun's radiance) and its visibility mask holds the cloud's brightest points."""
    sj = io.read_json(tiny_scene / "scene.json")
    names = [p["name"] for p in sj["photos"]]
    assert names == ["bright", "lights", "sun"] and sj["photos"][0]["file"] == "photo.exr"
    gt = io.read_cloud(tiny_scene / "cloud_gt.ply")
    lum = io.luminance(gt.colors)
    sun_lum = float(io.luminance(np.asarray([sj["sun"]["radiance"]], np.float32))[0])
    for p in sj["photos"]:
        t = io.read_npz(tiny_scene / p["truth"], "pcrelight.truth/1")
        assert str(t["photo_name"]) == p["name"] and np.isclose(t["alpha_true"], t["e"] / t["k"])
        img = io.read_image(tiny_scene / p["file"])
        peak = float(io.luminance(img[..., :3]).max()) / float(t["k"])
        assert np.isclose(peak, p["peak_radiance_lum"], rtol=1e-5)
        vis = t["photo_visible"].astype(bool)
        assert vis.sum() == p["visible_points"] > 100
        # a visible point projects into the frame
        pc = gt.points[vis] @ t["photo_world_to_camera"][:3, :3].T + t["photo_world_to_camera"][:3, 3]
        uv = pc[:, :2] / pc[:, 2:] * np.diag(t["photo_K"])[:2] + t["photo_K"][:2, 2]
        assert np.all(pc[:, 2] > 0) and np.all((uv >= -1e-3) & (uv <= t["photo_size"] + 1e-3))
        if p["name"] == "sun":
            assert peak > 0.9 * sun_lum and np.sum(vis & (lum > 0.5 * sun_lum)) >= 3   # sun points in view
        else:
            assert peak < 1e-2 * sun_lum and not np.any(vis & (lum > 0.5 * sun_lum))
    assert len({p["scale_k"] for p in sj["photos"]}) == 3


# --------------------------------------------------------------------------- the HDR panorama
def _pano_region_mean(pano: np.ndarray, M: np.ndarray, K: np.ndarray, size, world_to_pano: np.ndarray) -> tuple[np.ndarray, int]:
    """Mean of the panorama's pixels whose centres fall in a pinhole frame (M, K, size), each weighted by
    its solid angle (∝ cos latitude) over the pinhole's solid angle per pixel (∝ cos³ of the angle off its
    axis): the panorama's estimate of the pinhole image's mean. Returns (RGB mean, pixels used)."""
    h, w = pano.shape[:2]
    eye, dirs = camera.world_rays("equirect", (w, h), world_to_pano)
    d = dirs.reshape(-1, 3)
    u, v, _, ok = camera.project_points("pinhole", eye + d, size, M, K=K)
    lat = np.pi / 2 - np.pi * (np.arange(h) + 0.5) / h
    cos_axis = d @ M[2, :3]
    wgt = (np.repeat(np.cos(lat), w) / np.maximum(cos_axis, 1e-9) ** 3) * ok
    return (pano.reshape(-1, 3) * wgt[:, None]).sum(0) / wgt.sum(), int(ok.sum())


def test_panorama_agrees_with_pinhole_photos_from_its_centre(tiny_scene):
    """pano.exr (camera.MODELS['equirect'], traced by Mitsuba) against pinhole photos rendered here from its
    centre along ±X, ±Y, ±Z and towards a skylight panel (a known emitter): the panorama's mean over each frame
    (÷ its k) equals the photo's within 4 standard errors; the same panorama mirrored left–right or upside down
    does not (the test sees a wrong orientation); the pixel towards the panel's centre holds at least the panel's emission."""
    sj = io.read_json(tiny_scene / "scene.json")
    p = sj["panorama"]
    assert p["file"] == "pano.exr" and p["model"] == "equirect" and p["size"] == [128, 64]
    pano = io.read_image(tiny_scene / p["file"])[..., :3].astype(np.float64) / p["scale_k"]
    W2P = np.asarray(p["world_to_camera"])
    c = np.asarray(p["centre"])
    obj = sj["object"]
    assert np.linalg.norm(c - obj["center"]) > obj["radius"]                  # near the object, not inside it
    np.testing.assert_allclose(camera.world_rays("equirect", (4, 2), W2P)[0], c, atol=1e-12)
    t = io.read_npz(tiny_scene / p["truth"], "pcrelight.truth/1")
    assert str(t["photo_model"]) == "equirect" and np.isclose(t["alpha_true"], t["e"] / t["k"]) and t["k"] == p["scale_k"]
    room = smi.load_room(tiny_scene, sj, sj["integrator"])
    tr = smi.Tracer(seed=21)
    # the skylight panel whose centre the panorama's centre sees best (nearest unoccluded)
    sky = [m for m in sj["meshes"] if m["name"].startswith("skylight")]
    cents = np.array([io.read_mesh(tiny_scene / m["file"])[0].mean(axis=0) for m in sky])
    dist = np.linalg.norm(cents - c, axis=1)
    tt, _, valid = tr.first_hits(room, np.repeat(c[None], len(cents), 0), (cents - c) / dist[:, None])
    seen = np.flatnonzero(valid & (tt > dist - 0.05))
    assert len(seen), "no skylight seen from the panorama's centre"
    i_sky = seen[np.argmin(dist[seen])]
    size, spp, fov = (24, 24), 16, 40.0
    K = camera.intrinsics(fov, size)
    dirs = {"+X": (1, 0, 0), "-X": (-1, 0, 0), "+Y": (0, 1, 0), "-Y": (0, -1, 0), "+Z": (0, 0, 1), "-Z": (0, 0, -1),
            "skylight": tuple((cents[i_sky] - c) / dist[i_sky])}
    z, z_mirror, z_flip = {}, {}, {}
    for name, f in dirs.items():
        M = np.eye(4)
        M[:3, :3] = camera.look_rotation(np.asarray(f, float))
        M[:3, 3] = -M[:3, :3] @ c
        o, d = camera.camera_rays(M, K, size)
        m, v, _ = tr.radiance(room, o, d, spp, f"pinhole/{name}")
        photo, se_photo = m.mean(0), np.sqrt(v.sum(0)) / len(m)
        got, n = _pano_region_mean(pano, M, K, size, W2P)
        # the panorama's own noise: the photo's per-path variance, p["spp"] paths on each of its n pixels
        se_pano = np.sqrt(v.mean(0) * spp / p["spp"] / n)
        se = np.sqrt(se_photo ** 2 + se_pano ** 2)
        z[name] = float(np.max(np.abs(got - photo) / se))
        for zz, img in ((z_mirror, pano[:, ::-1]), (z_flip, pano[::-1])):
            zz[name] = float(np.max(np.abs(_pano_region_mean(img, M, K, size, W2P)[0] - photo) / se))
    assert max(z.values()) < 4.0, z
    assert max(z_mirror.values()) > 10 and max(z_flip.values()) > 10, (z_mirror, z_flip)
    # the pixel towards the panel's centre: its emission plus what it reflects (≥ 0), half-float rounding aside
    u, v, _, _ = camera.project_points("equirect", cents[i_sky][None], (128, 64), W2P)
    px = pano[int(v[0]), int(u[0])]
    assert np.all(px >= (1 - 1e-3) * np.asarray(sky[i_sky]["emission"])), (px, sky[i_sky]["emission"])


def test_panorama_alone_into_an_existing_folder_is_the_full_runs(tiny_scene, tmp_path, cli_run):
    """`make-scene --only panorama` on a make-scene folder without its panorama writes the bytes of the full
    run's pano.exr, truth/truth_pano.npz and scene.json (the panorama's k and paths depend on the seed only)."""
    import shutil

    d = tmp_path / "t"
    shutil.copytree(tiny_scene, d)
    for f in ("pano.exr", "truth/truth_pano.npz"):
        (d / f).unlink()
    sj = io.read_json(d / "scene.json")
    del sj["panorama"]
    io.write_json(d / "scene.json", sj)
    code, _, err = cli_run("make-scene", "--preset", "tiny", "--out", d, "--seed", "0", "--only", "panorama", "-q")
    assert code == 0, err
    for f in ("pano.exr", "truth/truth_pano.npz", "scene.json"):
        assert (d / f).read_bytes() == (tiny_scene / f).read_bytes(), f
    assert (d / "previews" / "pano.png").exists()
    # another seed: another k and other paths; a folder without a make-scene truth: one line, exit 1
    code, _, err = cli_run("make-scene", "--preset", "tiny", "--out", d, "--seed", "1", "--only", "panorama", "-q")
    assert code == 0 and (d / "pano.exr").read_bytes() != (tiny_scene / "pano.exr").read_bytes()
    code, _, err = cli_run("make-scene", "--preset", "tiny", "--out", tmp_path / "empty", "--only", "panorama")
    assert code == 1 and "scene.json: no such file" in err and len(err.strip().splitlines()) == 1
    code, _, err = cli_run("make-scene", "--preset", "tiny", "--out", d, "--only", "panorama", "--pano-at", "0,-5,0")
    assert code == 2 and "--pano-at" in err


def test_lamp_room(tmp_path):
    """The lamp room: emitters ≤ 1 % of the object's directions and 10³–10⁴ × the walls; the
    'lights' photo sees a lamp; Lambert and GGX references are rendered."""
    from pipeline.scene.make_scene import apply_preset

    cfg = apply_preset("lamps", {"points": 4000, "ref_size": (24, 24), "ref_spp": 16, "ref_max_spp": 32,
                                 "materials": ("lambert", "ggx0.25")})
    rep = run_make_scene(tmp_path, cfg, preview=False)
    lamps = rep["lights"]["lamps"]
    assert lamps["solid_angle_share"] <= 0.01 and 1e3 <= lamps["over_wall_median"] <= 1e4, lamps
    assert "sun" not in rep["lights"]
    ph = {p["name"]: p for p in rep["photos"]}
    assert ph["lights"]["peak_radiance_lum"] > 0.9 * lamps["radiance_lum"] and "lamp" in ph["lights"]
    for kind in ("gather", "full"):
        for m in ("lambert", "ggx0.25"):
            img = io.read_image(tmp_path / "truth" / f"{kind}_view1_{m}.exr")
            assert (img[..., 3] > 0).any() and np.isfinite(img).all()


def test_precise_subset_and_independent_rebakes_agree(tmp_path):
    """truth/cloud_precise.npz re-bakes a subset of cloud_gt.ply's points with independent paths,
    adaptively; two such re-bakes with different seeds agree point by point within their combined
    standard errors (|z| > 3 for a few points at most; Gaussian: 0.27 %)."""
    from pipeline.metrics import zscores

    rep = run_make_scene(tmp_path, MakeSceneConfig(seed=0, **{**MINI, "references": False, "photos": ("bright",)},
                                                   precise_points=300, precise_target=0.1, precise_max_spp=512),
                         preview=False)
    pr = io.read_npz(tmp_path / "truth" / "cloud_precise.npz", "pcrelight.cloud_precise/1")
    gt = io.read_cloud(tmp_path / "cloud_gt.ply")
    assert len(pr["index"]) == 300 and len(np.unique(pr["index"])) == 300 and pr["index"].max() < len(gt)
    lum = io.luminance(pr["colors"].astype(np.float32)).astype(np.float64)
    rel = np.sqrt(pr["lum_var"]) / lum
    assert np.all((rel <= 0.1) | (pr["spp"] == 512)) and pr["spp"].max() > MINI["cloud_spp"]
    assert np.isclose(rep["cloud_precise"]["rel_se_median"], np.median(rel))
    # a second re-bake of the same points with other seeds
    sj = io.read_json(tmp_path / "scene.json")
    room = smi.load_room(tmp_path, sj, sj["integrator"])
    pts, nrm = gt.points[pr["index"]].astype(np.float64), gt.normals[pr["index"]].astype(np.float64)
    m, _, lv = smi.Tracer(seed=77).radiance(room, pts + 2e-3 * nrm, -nrm, MINI["cloud_spp"], "precise", 0.1, 512)
    z = zscores(io.luminance(m.astype(np.float32)), lv, lum, pr["lum_var"])
    assert np.mean(np.abs(z) > 3) <= 0.03, np.sort(np.abs(z))[-10:]


def test_shipped_truth_precision():
    """Issue 13 on the shipped ``small`` truth (data_samples/, cloud 1024…24576 paths a point to 5 %,
    references 1024…65536 paths a pixel to 3 %), its "done when" as written: cloud_gt's median relative
    standard error ≤ 5 % (4.27 %) and p90 ≤ 15 % (8.6 %); the independent re-bake of 4000 points
    (truth/cloud_precise.npz) agrees point by point (|z| > 3 for 0.37 % ≤ 1 %) and in the pooled mean;
    every reference's median per-pixel noise ≤ 3 % (1.8–2.6 %). A reference pixel's luminance noise is
    bounded by Σ_c w_c σ_c (exact for fully correlated channels; equal to make-scene's luminance
    estimate to 3 digits here)."""
    import pytest

    from pipeline.color import luminance, y_weights
    from pipeline.metrics import zscores
    from tests.conftest import SAMPLES

    c = io.read_cloud(SAMPLES / "cloud_gt.ply")
    lum = luminance(c.colors).astype(np.float64)
    rel = c.quality.astype(np.float64) / np.maximum(lum, 1e-30)
    assert np.percentile(rel, 90) <= 0.15 and np.median(rel) <= 0.05, (np.median(rel), np.percentile(rel, 90))
    p = np.load(SAMPLES / "truth" / "cloud_precise.npz")
    i = p["index"]
    plum = luminance(p["colors"].astype(np.float32)).astype(np.float64)
    z = zscores(lum[i], c.quality[i].astype(np.float64) ** 2, plum, p["lum_var"])
    assert np.mean(np.abs(z) > 3) <= 0.01, np.mean(np.abs(z) > 3)
    assert lum[i].sum() / plum.sum() == pytest.approx(1.0, abs=0.01)
    refs = sorted(p for p in (SAMPLES / "truth").glob("*_var.exr") if not p.name.startswith("photo_"))
    assert len(refs) == 20
    med = {}
    for f in refs:
        v, m = io.read_image(f), io.read_image(str(f).replace("_var", ""))
        obj = m[..., 3] > 0.5
        sd = (y_weights() * np.sqrt(np.maximum(v[..., :3], 0))).sum(-1)
        med[f.name] = float(np.median(sd[obj] / np.maximum(luminance(m[..., :3])[obj], 1e-30)))
    assert max(med.values()) <= 0.03, med


def test_shipped_lights_photo_sees_a_lamp_and_the_brightest_patch():
    """Issue 13: photo_lights.exr of the shipped sample is placed by its own rule (no fallback to the
    'bright' camera) and shows a lamp at the lamp's radiance, with the brightest lit patch in frame."""
    from tests.conftest import SAMPLES

    sj = io.read_json(SAMPLES / "scene.json")
    ph = {p["name"]: p for p in sj["photos"]}
    lights = ph["lights"]
    assert "fell back" not in lights["rule"] and "lamp" in lights and "patch" in lights
    assert np.linalg.norm(np.subtract(lights["eye"], ph["bright"]["eye"])) > 1.0
    t = io.read_npz(SAMPLES / lights["truth"], "pcrelight.truth/1")
    img = io.read_image(SAMPLES / lights["file"])[..., :3]
    W, K = t["photo_world_to_camera"], t["photo_K"]
    h, w = img.shape[:2]
    for key in ("lamp", "patch"):
        pc = W[:3, :3] @ np.asarray(lights[key]) + W[:3, 3]
        u, v = (K @ (pc / pc[2]))[:2]
        assert pc[2] > 0 and 3 <= u < w - 3 and 3 <= v < h - 3, (key, u, v)
        if key == "lamp":
            win = img[int(v) - 3:int(v) + 4, int(u) - 3:int(u) + 4]
            lamp_lum = float(io.luminance(np.asarray([sj["lamps"]["radiance"]], np.float32))[0])
            assert float(io.luminance(win.reshape(-1, 3)).max()) / float(t["k"]) > 0.5 * lamp_lum


def test_shipped_panorama_is_the_clouds_room():
    """data_samples/pano.exr (small preset: 1024×512 at 256 paths a pixel, half floats, ≤ 6 MB) shows the
    room of cloud_gt.ply: the Lambertian walls' radiance is the same from every side, so the panorama's pixels
    at the cloud points it sees (truth/truth_pano.npz), ÷ its k, pool to the points' radiance — per channel
    within 2 % (measured +0.4…+0.6 %), on the overexposed points within 3 % (−0.9 %)."""
    import OpenImageIO as oiio

    from tests.conftest import SAMPLES

    sj = io.read_json(SAMPLES / "scene.json")
    p = sj["panorama"]
    f = SAMPLES / p["file"]
    assert f.stat().st_size <= 6 * 2 ** 20
    inp = oiio.ImageInput.open(str(f))
    spec = inp.spec()
    inp.close()
    assert (spec.width, spec.height) == tuple(p["size"]) == (1024, 512) and str(spec.format) == p["pixel_type"] == "half"
    pano = io.read_image(f)[..., :3].astype(np.float64) / p["scale_k"]
    t = io.read_npz(SAMPLES / p["truth"], "pcrelight.truth/1")
    gt = io.read_cloud(SAMPLES / "cloud_gt.ply")
    vis = t["photo_visible"].astype(bool)
    assert vis.sum() == p["visible_points"] > 50000
    u, v, _, ok = camera.project_points("equirect", gt.points[vis], (1024, 512), np.asarray(p["world_to_camera"]))
    assert ok.all()
    px = pano[v.astype(int), u.astype(int)]
    over = t["overexposed"].astype(bool)[vis]
    ratio = px.sum(0) / gt.colors[vis].astype(np.float64).sum(0)
    ratio_over = px[over].sum(0) / gt.colors[vis][over].astype(np.float64).sum(0)
    assert np.all(np.abs(ratio - 1) < 0.02) and np.all(np.abs(ratio_over - 1) < 0.03), (ratio, ratio_over)


def test_bowl_object_is_closed_outward_and_unit():
    """make-scene's bowl (preset bowl): closed once coincident vertices merge, faces outward (positive volume),
    bounding sphere about the origin of radius 1, opening towards +Y."""
    import trimesh

    from pipeline.relight.surfels import closed
    from pipeline.scene.geometry import object_bowl

    V, F, N = object_bowl(tilt_deg=0.0)
    m = trimesh.Trimesh(V, F, process=False)
    assert closed(m)
    assert m.volume > 0
    assert np.linalg.norm(V, axis=1).max() == pytest.approx(1.0, abs=1e-9)
    assert V[:, 1].max() == pytest.approx(0.0, abs=1e-9) and V[:, 1].min() == pytest.approx(-1.0, abs=1e-9)
    np.testing.assert_allclose(np.linalg.norm(N, axis=1), 1.0, atol=1e-9)
    Vt, Ft, Nt = object_bowl()                                   # tilted 50° towards −X: a rotation
    np.testing.assert_allclose(np.linalg.norm(Vt, axis=1), np.linalg.norm(V, axis=1), atol=1e-12)
    d = np.array([-np.sin(np.radians(50)), np.cos(np.radians(50)), 0.0])   # the opening's direction
    np.testing.assert_allclose(Vt[np.argmin(Vt @ d)], -d, atol=1e-9)         # the bottom pole opposite it
