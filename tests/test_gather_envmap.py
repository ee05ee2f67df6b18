"""The envmap gatherer (pipeline/gather/envmap.py) against independent truths: a constant environment
(ρ·L; L × the directional albedo of brdf.py's quadrature for glossy BRDFs), a single bright texel (the
analytic clamped-cosine lobe), the spherical cap of test_relight (L sin²θ) through the real capture, the
cube-map geometry, and relight end to end (--method envmap; --surfels refused)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bsh_builders import build_simple_bsh
from pipeline.gather import brdf
from pipeline.gather import GATHERERS, EnvmapGatherer, GatherParams, Receivers
from pipeline.gather import envmap as em


def fib_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    th = np.pi * (1 + 5 ** 0.5) * i
    return np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], 1)


def receivers(nrm, view=None, base=1.0, metallic=0.0, roughness=0.5, pos=None) -> Receivers:
    nrm = np.asarray(nrm, np.float32).reshape(-1, 3)
    k = len(nrm)
    f = lambda v: np.broadcast_to(np.asarray(v, np.float32), (k,)).copy()  # noqa: E731
    return Receivers(np.zeros((k, 3), np.float32) if pos is None else np.asarray(pos, np.float32).reshape(-1, 3), nrm,
                     nrm.copy() if view is None else np.asarray(view, np.float32).reshape(-1, 3),
                     np.broadcast_to(np.asarray(base, np.float32), (k, 3)).copy(), f(metallic), f(roughness))


def no_nodes():
    from pipeline.bsh.format import NODE_DTYPE

    return np.zeros(1, NODE_DTYPE)


def test_in_the_table():
    assert GATHERERS["envmap"] is EnvmapGatherer and not EnvmapGatherer.OBJECT_SURFELS


def test_cube_texel_dirs_match_the_splatter():
    """Texel directions are the splatter's: a point projected by splats.project lands in the texel whose
    direction points at it; the solid angles sum to 4π."""
    from pipeline.camera import cube_cameras
    from pipeline.expansion.splats import project

    S = 16
    d, om = em.cube_texel_dirs(S)
    assert om.sum() == pytest.approx(4 * math.pi, rel=1e-9)
    cams = cube_cameras(np.zeros((1, 3)), S)
    for f in range(6):
        for (r, c) in ((0, 0), (3, 11), (15, 7)):
            u, v, z = project(d[f, r, c][None] * 5.0, cams["K"][f], cams["world_to_camera"][f])
            assert z[0] > 0 and int(u[0]) == c and int(v[0]) == r


# --------------------------------------------------------------------------- constant environment (furnace)
def test_constant_environment_lambert(gl_context):
    """L = 2 everywhere, Lambert ρ = 0.8 → 1.6 for every normal (to 1e-3: the irradiance map's own sum)."""
    rng = np.random.default_rng(0)
    n = rng.normal(size=(200, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    g = EnvmapGatherer(gl_context, no_nodes(), GatherParams(16, brdf="lambert"))
    g.set_environment(np.full((6, 64, 64, 3), 2.0, np.float32))
    rad, st = g.run(receivers(n, base=0.8))
    np.testing.assert_allclose(rad, 1.6, rtol=1e-3)
    assert st["method_stats"]["envmap"]["diffuse"] == "map"
    g.release()


@pytest.mark.parametrize("kind,rough,metal,masking", [
    ("ggx", 0.1, 1.0, "separable"), ("ggx", 0.25, 1.0, "separable"), ("ggx", 0.5, 1.0, "height-correlated"),
    ("ggx", 1.0, 1.0, "separable"), ("ggx", 0.5, 0.0, "height-correlated"),
    ("disney", 0.3, 0.0, "height-correlated"), ("disney", 0.7, 0.5, "height-correlated"),
])
def test_constant_environment_glossy(gl_context, kind, rough, metal, masking):
    """White base colour, L = 2 → L × the directional albedo (brdf.py's h-space quadrature), views 6°…69°,
    within 1 % (the split sum is exact for a constant environment; what is left: the (n·v, roughness)
    table's Monte-Carlo and bilinear error)."""
    th = np.array([0.1, 0.7, 1.2])
    view = np.stack([np.sin(th), 0 * th, np.cos(th)], 1)
    nrm = np.tile([0.0, 0.0, 1.0], (3, 1))
    ref = np.array([brdf.directional_albedo(kind, v, (1, 1, 1), metal, rough, masking, 200, 200)[0] for v in view])
    g = EnvmapGatherer(gl_context, no_nodes(), GatherParams(16, brdf=kind, masking=masking))
    g.set_environment(np.full((6, 32, 32, 3), 2.0, np.float32))
    rad, _ = g.run(receivers(nrm, view, 1.0, metal, rough))
    np.testing.assert_allclose(rad[:, 0] / 2.0, ref, rtol=0.01)
    g.release()


def test_mirror_reads_the_environment_in_the_reflected_direction(gl_context):
    """A smooth environment L(ω) = 2 + ω·(0.5, 1, −0.7) (per channel scaled), white metal of roughness 0: the
    receiver returns L at the mirror direction of its view (the prefiltered cube's orientation is the capture's;
    within 1 %: level 0 is the source, bilinear, and the table's F at α = 1e-4)."""
    S = 64
    d, _ = em.cube_texel_dirs(S)
    a = np.array([0.5, 1.0, -0.7])
    lum = 2.0 + d @ a
    rgb = np.stack([lum, 0.5 * lum, 0.25 * lum], -1).astype(np.float32)
    rng = np.random.default_rng(3)
    n = rng.normal(size=(300, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    v = rng.normal(size=(300, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v = np.where(((v * n).sum(1) < 0.2)[:, None], -v, v)
    keep = (v * n).sum(1) > 0.2
    n, v = n[keep], v[keep]
    R = 2 * (n * v).sum(1, keepdims=True) * n - v
    g = EnvmapGatherer(gl_context, no_nodes(), GatherParams(16, brdf="ggx", masking="separable"))
    g.set_environment(rgb)
    rad, _ = g.run(receivers(n, v, 1.0, 1.0, 0.0))
    ref = 2.0 + R @ a
    np.testing.assert_allclose(rad[:, 0], ref, rtol=0.01)
    np.testing.assert_allclose(rad[:, 2], 0.25 * ref, rtol=0.01)
    g.release()


# --------------------------------------------------------------------------- one bright texel
@pytest.mark.parametrize("face,row,col", [(0, 40, 70), (2, 5, 60), (5, 100, 12)])
def test_single_bright_texel_gives_the_cosine_lobe(gl_context, face, row, col):
    """One texel of radiance L (solid angle Ω), the rest black: a Lambert receiver reflects ρ/π·L·Ω·max(0, n·ω)
    — over 2000 random normals within 3 % of the peak everywhere, 0.6 % RMS (the 64×32 map's bilinear error,
    measured 2.2–2.4 % / 0.35–0.44 %; 3-band SH, measured alongside and asserted ≥ 5× worse in RMS: it rings on
    a point source, 9.4 % / 3.6 %)."""
    S = 128
    rgb = np.zeros((6, S, S, 3), np.float32)
    rgb[face, row, col] = 1000.0
    d, om = em.cube_texel_dirs(S)
    w, Om = d[face, row, col], om[face, row, col]
    rng = np.random.default_rng(1)
    n = rng.normal(size=(2000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    ref = 0.8 / math.pi * 1000.0 * Om * np.maximum(n @ w, 0.0)
    g = EnvmapGatherer(gl_context, no_nodes(), GatherParams(16, brdf="lambert"))
    g.set_environment(rgb)
    rad, _ = g.run(receivers(n, base=0.8))
    peak = ref.max()
    err = np.abs(rad[:, 0] - ref)
    assert err.max() < 0.03 * peak and np.sqrt(np.mean(err ** 2)) < 0.006 * peak
    sh = 0.8 / math.pi * em.irradiance_sh9(rgb, n)[:, 0]
    assert np.sqrt(np.mean((sh - ref) ** 2)) > 5 * np.sqrt(np.mean(err ** 2))
    g.release()


def test_diffuse_error_measure():
    """diffuse_error: both exact for a band-≤ 2 environment (L = 1 + z): SH to 1e-6, the map to its bilinear
    error (< 0.5 %)."""
    d, _ = em.cube_texel_dirs(64)
    rgb = np.repeat((1.0 + d[..., 2:3]), 3, -1).astype(np.float32)
    e = em.diffuse_error(rgb, 500)
    assert e["sh_rel_rms"] < 1e-5 and e["map_rel_rms"] < 5e-3


# --------------------------------------------------------------------------- spherical cap, through the capture
def cap_nodes(theta: float, axis, n_sphere: int = 12000, L: float = 1.0):
    p = fib_sphere(n_sphere)
    keep = p @ np.asarray(axis, float) >= math.cos(theta)
    p = p[keep]
    return build_simple_bsh(p, -p, np.full((len(p), 3), L), 0.5 * math.sqrt(4 * math.pi / n_sphere))


@pytest.mark.parametrize("deg,over", [(30, 0.233), (45, 0.108), (60, 0.076), (75, 0.033), (90, 0.0)])
def test_spherical_cap_irradiance(gl_context, deg, over):
    """test_relight's cap (unit sphere of 12 000 points, radiance 1, half-angle θ about the normal) captured
    from its centre: a white Lambert receiver there reflects sin²θ × (1 + ``over``), within 1 % of the
    irradiance either way (issue 45: asserted two-sided at the measured overshoot, not under a loose ceiling).
    Measured limitation of the capture (re-measured 2026-12-07, the values above): where the discs leave a texel empty —
    beyond the rim too, the cap has nothing behind it — the hole-free radii fill it (splats.knn_splat_radii,
    1.25 × the mean distance to 16 neighbours, about two point spacings), so the rim overhangs and small caps
    come out too bright: +23.3 % at 30°, +10.8 % at 45°, +7.6 % at 60°, +3.3 % at 75°, 0 at 90° (classic PBGI
    at m = 32: +6.4 % at 30°, +2.0 % at 60°). A closed room has no such empty background. A cap behind the
    surface gives < 0.01 (0.0086 at 90°: the map's rows nearest the horizon)."""
    theta = math.radians(deg)
    up = np.array([[0.0, 0.0, 1.0]])
    g = EnvmapGatherer(gl_context, cap_nodes(theta, [0, 0, 1]), GatherParams(16, brdf="lambert", object_center=(0.0, 0.0, 0.0)))
    rad, st = g.run(receivers(up))
    ref = math.sin(theta) ** 2
    assert abs(rad[0, 0] / ref - (1 + over)) <= 0.01, (rad[0, 0] / ref - 1, over)
    assert st["method_stats"]["envmap"]["eye"] == [0.0, 0.0, 0.0]
    g.release()
    g2 = EnvmapGatherer(gl_context, cap_nodes(theta, [0, 0, -1]), GatherParams(16, brdf="lambert", object_center=(0.0, 0.0, 0.0)))
    rad2, _ = g2.run(receivers(up))
    assert 0.0 <= rad2[0, 0] < 0.01
    g2.release()


def test_capture_culls_back_faces_and_leaves_out_the_object(gl_context):
    """The environment is the room's leaves only: nodes from object_first on (the object's surfels) and
    back-facing leaves are not splatted; the furnace room seen from inside covers every texel."""
    p = fib_sphere(3000) * 3
    room = build_simple_bsh(p, -p, np.full((len(p), 3), 2.0), 3 * math.sqrt(4 * math.pi / 3000))
    pts = em.capture_points(room, None, np.zeros(3))
    assert pts["leaves"] == 3000
    g = EnvmapGatherer(gl_context, room, GatherParams(16, brdf="lambert", object_center=(0.2, -0.1, 0.3)))
    faces = g.capture(np.array([0.2, -0.1, 0.3]))
    assert faces[..., 3].all() and np.allclose(faces[..., :3], 2.0)
    outward = build_simple_bsh(p, p, np.full((len(p), 3), 2.0), 3 * math.sqrt(4 * math.pi / 3000))
    g.nodes = outward
    assert not g.capture(np.zeros(3))[..., 3].any()                   # every leaf faces away: culled
    g.release()
    pts = em.capture_points(room, None, np.zeros(3), object_first=1)
    assert pts["leaves"] == 0


# --------------------------------------------------------------------------- relight end to end
def _scene(tmp_path) -> list[str]:
    """test_gather_table's furnace: 300 points on a sphere of radius 3 (radiance 1, normals inward), an
    icosphere object of radius 0.5 — through the real CLI."""
    import trimesh
    from bsh_builders import simple_bsh_arrays

    from pipeline import io

    p = fib_sphere(300)
    io.write_npz(tmp_path / "bsh.npz", "pcrelight.bsh/1", **simple_bsh_arrays(3 * p, -p, np.ones((300, 3)), 0.4))
    tm = trimesh.creation.icosphere(2, radius=0.5)
    io.write_mesh(tmp_path / "o.ply", tm.vertices, tm.faces, tm.vertex_normals)
    return ["relight", "--bsh", str(tmp_path / "bsh.npz"), "--object", str(tmp_path / "o.ply"), "--eye", "0,0,2",
            "--target", "0,0,0", "--size", "24x20", "--brdf", "lambert", "--albedo", "0.5,0.25,1", "--method", "envmap"]


def test_relight_envmap_furnace_end_to_end(tmp_path, cli_run):
    """relight --method envmap in the furnace: every covered pixel = albedo × 1 within 0.2 %; the object's
    surfels (auto) are off for envmap, recorded in stats.json with the capture."""
    from pipeline import io

    code, _, err = cli_run(*_scene(tmp_path), "--out", tmp_path / "out", "-q")
    assert code == 0, err
    img = io.read_image(tmp_path / "out" / "relit.exr")
    st = io.read_json(tmp_path / "out" / "stats.json")
    cov = img[..., 3] > 0
    assert cov.sum() == st["covered_pixels"] > 50
    np.testing.assert_allclose(img[cov][:, :3], np.broadcast_to([0.5, 0.25, 1.0], (int(cov.sum()), 3)), rtol=2e-3)
    assert st["method"] == "envmap" and st["decisions"]["object_in_own_micro_buffers"] is False
    env = st["method_stats"]["envmap"]
    assert env["empty_share"] == 0.0 and env["leaves"] == 300 and np.allclose(env["eye"], 0, atol=1e-6)
    assert "envmap_capture" in st["time_s"] and "envmap_filter" in st["time_s"]


def test_relight_envmap_refuses_explicit_surfels(tmp_path, cli_run):
    code, _, err = cli_run(*_scene(tmp_path), "--surfels", "500", "--out", tmp_path / "out", "-q")
    assert code == 2 and "--surfels 500" in err and "envmap" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_emitters_added_as_eq9_adds_them(gl_context):
    """An emitter (bsh.npz row: centre, disc radius r, normal, flat share 0, radiance L) in a black closed room:
    a white Lambert receiver at the eye facing it reflects L·π r²/4 / (d² + r²) / π (eq9.comp.glsl's closed
    share: a quarter of its disc from any side) within 3 % (the irradiance map on a one-texel source); an
    emitter behind the room's wall is not added."""
    p = fib_sphere(3000) * 3
    room = build_simple_bsh(p, -p, np.zeros((len(p), 3)), 3 * math.sqrt(4 * math.pi / 3000))
    emit = np.zeros((2, 12), np.float32)
    emit[0, :3], emit[0, 3], emit[0, 8:11] = (0.0, 0.0, 2.0), 0.05, 1000.0
    emit[1, :3], emit[1, 3], emit[1, 8:11] = (0.0, 0.0, -3.5), 0.05, 1000.0       # outside the room
    g = EnvmapGatherer(gl_context, room, GatherParams(16, brdf="lambert", object_center=(0.0, 0.0, 0.0)), emitters=emit)
    rad, st = g.run(receivers([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]))
    ref = 1000.0 * math.pi * 0.05 ** 2 / 4 / (4.0 + 0.05 ** 2) / math.pi
    assert st["method_stats"]["envmap"]["emitters"] == 1
    assert rad[0, 0] == pytest.approx(ref, rel=0.03) and rad[1, 0] < 1e-3 * ref
    g.release()
