"""The importance gatherer (pipeline/gather/importance.py, paper 001): the budget assignment (exactly N_s for any
pdf), Eq. 3's splat size, the clusters, the exhaustive projection against classic's micro-buffer, the white
furnace and the spherical cap, determinism for the seed."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bsh_builders import build_simple_bsh
from pipeline.bsh.format import LEAF
from pipeline.gather import GATHERERS, ClassicGatherer, GatherParams, Receivers
from pipeline.gather import importance as imp
from pipeline.gather.importance import ImportanceGatherer
from pipeline.gather.walk import texel_table
from test_relight import fib_sphere
from test_relight import receivers as relight_receivers


def receivers(pos, nrm, view=None, base=1.0, metallic=0.0, roughness=0.5) -> Receivers:
    """test_relight's receivers, looking along their normals unless ``view`` is given."""
    return relight_receivers(pos, nrm, nrm if view is None else view, base, metallic, roughness)


def sphere_nodes(n: int = 6000, L: float = 2.0, cap_deg: float | None = None, axis=(0, 0, 1)):
    """n points on the unit sphere of radiance L, leaf radius √(a/2) for a = 4π/n the area a point: ΔA = 2r² = a,
    the gatherer's ΔA of a build-bsh leaf (r = d₄/√2, d₄ ≈ the spacing)."""
    p = fib_sphere(n)
    if cap_deg is not None:
        p = p[p @ np.asarray(axis, float) >= math.cos(math.radians(cap_deg))]
    return build_simple_bsh(p, -p, np.full((len(p), 3), L), math.sqrt(0.5 * 4 * math.pi / n))


# --------------------------------------------------------------------------- pure parts
@settings(max_examples=300, deadline=None)
@given(st.lists(st.one_of(st.just(0.0), st.floats(0.0, 1e6), st.floats(1e-30, 1e-20)), min_size=1, max_size=600),
       st.integers(1, 5000), st.integers(0, 2 ** 32 - 1))
def test_budget_is_exactly_n_s_for_any_pdf(pdf, n_s, seed):
    p = np.asarray(pdf)
    u = np.random.default_rng(seed).random(p.size)
    n = imp.assign_budget(p, n_s, u)
    if p.sum() <= 0:
        assert n.sum() == 0
        return
    assert n.sum() == n_s
    assert np.all(n >= 0) and np.all(n[p <= 0] == 0)
    # each prefix stays within one sample of its expectation (the carry is in (−1, 1))
    e = n_s * np.cumsum(p) / p.sum()
    assert np.all(np.abs(np.cumsum(n) - e) < 1 + 1e-6 * n_s)


def test_budget_is_001s_pseudo_code():
    """With a positive pdf, assign_budget draws what 001 §3.2's listing draws for the same uniforms (the
    cumulative form only differs from the carry form by rounding, which never decides a draw here). Note: the
    listing is not unbiased per cluster (a negative carry cannot give negative samples, so a small cluster after
    an overdraw gets more than N_s p_k on average); Eq. 3 divides by N_s p_k as 001 does."""
    rng = np.random.default_rng(3)
    for _ in range(200):
        p = rng.random(rng.integers(1, 600)) ** 3 + 1e-9
        u = rng.random(p.size)
        ns = int(rng.integers(1, 4096))
        pk = p / p.sum()
        ref, carry = [], 0.0
        for k in range(p.size):          # 001's listing, verbatim
            fk = ns * pk[k] + carry
            nk = int(max(fk, 0))
            fk = fk - nk
            if u[k] < fk:
                nk += 1
                carry = fk - 1.0
            else:
                carry = fk
            ref.append(nk)
        n = imp.assign_budget(p, ns, u)
        assert np.sum(n != np.asarray(ref)) <= 1 and n.sum() == ns


def test_splat_side_eq3_on_a_synthetic_cluster():
    """A cluster of 100 points of area 1 cm² at 0.2 m, expecting N_s p_k = 4 samples: Ω_s = 100 · 1e-4 / 4 ·
    cos θ_s / 0.04 [sr]; side = ⌈√(Ω_s/Ω_texel)⌉ (m = 32: Ω_texel = 2π/32²), ≥ 1, ≤ the largest."""
    om_t = 2 * math.pi / 32 ** 2
    for cos_s, side in ((1.0, 4), (-1.0, 4), (0.5, 3), (0.1, 2), (0.05, 1)):
        om = 100 * 1e-4 / 4 * abs(cos_s) / 0.04
        assert (side - 1) ** 2 * om_t < om <= side ** 2 * om_t or side == 1
        got = imp.splat_side(100, np.array([1e-4]), np.array([cos_s]), np.array([0.2]), np.array([4.0]), om_t, 8)
        assert got[0] == side
    assert imp.splat_side(100, np.array([1e-4]), np.array([1.0]), np.array([0.2]), np.array([0.01]), om_t, 8)[0] == 8


@pytest.mark.parametrize("r,d", [(0.02, 1.0), (0.1, 1.0), (0.2, 1.0), (0.5, 1.0)])
def test_shader_splat_is_eq3s_square(gl_context, r, d):
    """One point of radius r straight above the receiver at d, projected exhaustively: Ω_s = ΔA/d² (ΔA = AREA_SCALE·πr²), the
    shader's splat covers side² texels, side = splat_side's (the texel table's Ω of the centre texel)."""
    nodes = build_simple_bsh(np.array([[0.0, 0.0, d], [5.0, 5.0, -5.0]]), np.array([[0, 0, -1.0], [0, 0, 1.0]]),
                             np.ones((2, 3)), r)
    m = 16
    g = ImportanceGatherer(gl_context, nodes, GatherParams(m, brdf="lambert"), clusters=2, exhaustive=True)
    g.keep_microbuffers = True
    g.run(receivers(np.zeros((1, 3)), [[0.0, 0.0, 1.0]]))
    covered = int((g.last_microbuffers[0, ..., 3] < 1e30).sum())
    tt = texel_table(m)[:, 2].reshape(m, m)
    side = imp.splat_side(1, np.array([ImportanceGatherer.AREA_SCALE * math.pi * r * r]), np.array([1.0]), np.array([d]), np.array([1.0]),
                          tt[m // 2, m // 2], ImportanceGatherer.SPLAT_MAX)[0]
    assert covered == side * side
    g.release()


def test_clusters_partition_the_leaves():
    nodes = sphere_nodes(3000)
    roots, offs, pts = imp.bsh_clusters(nodes, 512)
    assert len(roots) == 512 and offs[0] == 0 and offs[-1] == len(pts)
    assert np.array_equal(np.sort(pts), np.flatnonzero(nodes["right"] == LEAF))
    for c in (0, 100, 511):          # cluster c = the leaves of its sub-tree
        sub = np.arange(roots[c], nodes["skip"][roots[c]])
        assert np.array_equal(pts[offs[c]:offs[c + 1]], sub[nodes["right"][sub] == LEAF])
    sizes = np.diff(offs.astype(int))
    assert sizes.max() <= 2 * math.ceil(3000 / 512)   # near-equal counts (most populous split first)


# --------------------------------------------------------------------------- on the GPU
def test_in_the_table():
    assert GATHERERS["importance"] is ImportanceGatherer and ImportanceGatherer.OBJECT_SURFELS


def test_shader_draws_exactly_n_s(gl_context):
    rng = np.random.default_rng(0)
    pos = rng.uniform(-0.5, 0.5, (40, 3))
    nrm = rng.normal(size=(40, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    g = ImportanceGatherer(gl_context, sphere_nodes(), GatherParams(32, brdf="lambert"), clusters=128, samples=4)
    _, stt = g.run(receivers(pos, nrm))
    s = stt["method_stats"]["importance"]
    assert s["budget_drawn_min"] == s["budget_drawn_max"] == 4 * 128
    assert s["receivers_seeing_nothing"] == 0
    g.release()


def test_white_furnace(gl_context):
    """A closed sphere of radiance 2 around the receivers: Lambert ρ = 0.8 reflects 1.6. Measured limitation:
    the samples land at random, so the squares leave holes (Poisson coverage) and the furnace comes out low — (m = 32,
    64 receivers, 2026-12-07) 512 clusters × 8 (the defaults): −0.76 % mean, −2.7 … −0.16 %; 512 × 4 (001's): −4.7 %
    mean, −9.4 % worst; 128 × 8: −22 % (1 280 samples a receiver for ~800 texels: 76 % of them covered). Asserted:
    the defaults within 3 % below, 1.5 % on the mean, never above."""
    rng = np.random.default_rng(1)
    pos = rng.uniform(-0.4, 0.4, (64, 3))
    nrm = rng.normal(size=(64, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    g = ImportanceGatherer(gl_context, sphere_nodes(12000), GatherParams(32, brdf="lambert"))
    rad, _ = g.run(receivers(pos, nrm, base=0.8))
    err = rad / 1.6 - 1
    assert -0.03 < err.min() and err.max() <= 0.0 and err.mean() > -0.015, (err.min(), err.mean(), err.max())
    g.release()


@pytest.mark.parametrize("kind,rough,metal,masking", [
    ("ggx", 0.1, 1.0, "separable"), ("ggx", 0.25, 1.0, "separable"), ("ggx", 0.5, 1.0, "height-correlated"),
    ("ggx", 1.0, 1.0, "separable"), ("ggx", 0.5, 0.0, "height-correlated"), ("disney", 0.3, 0.0, "height-correlated"),
])
def test_white_furnace_glossy(gl_context, kind, rough, metal, masking):
    """White base colour in the furnace (radiance 2) → 2 × the directional albedo (brdf.py's quadrature), views
    6°/40°/69°, m = 16 and 32, the glossy importance (Eq. 4) on. Measured (2026-12-07): m = 16 within ±0.5 %, m = 32
    −2.6 … +0.03 % (the holes, as the Lambert furnace). Asserted: 3.5 % below, 1 % above."""
    from pipeline.gather import brdf

    th = np.array([0.1, 0.7, 1.2])
    view = np.stack([np.sin(th), 0 * th, np.cos(th)], 1)
    nrm = np.tile([0.0, 0.0, 1.0], (3, 1))
    ref = np.array([brdf.directional_albedo(kind, v, (1, 1, 1), metal, rough, masking, 200, 200)[0] for v in view])
    nodes = sphere_nodes(12000)
    for m in (16, 32):
        g = ImportanceGatherer(gl_context, nodes, GatherParams(m, brdf=kind, masking=masking))
        rad, _ = g.run(receivers(np.zeros((3, 3)), nrm, view, 1.0, metal, rough))
        q = rad[:, 0] / 2.0 / ref
        assert np.all(q > 0.965) and np.all(q < 1.01), (m, q)
        g.release()


@pytest.mark.parametrize("deg,lo,hi", [(30, 0.0, 0.08), (60, 0.0, 0.035), (90, -0.02, 0.0)])
def test_spherical_cap(gl_context, deg, lo, hi):
    """test_relight's cap (radiance 1, half-angle θ about the normal, unit sphere of 12 000 points): a white
    Lambert receiver at its centre reflects sin²θ; a cap behind gives exactly 0. Measured (m = 32, defaults,
    seeds 0–4, 2026-12-07): +6.4 % at 30°, +4.5 % at 45°, +3.0 % at 60°, +3.5…+4.2 % at 75°, −0.8…−0.2 % at 90° —
    the squares at the rim spill onto the empty background beyond it (classic's spheres: +6.4 % at 30°, +2.0 % at
    60°), and the full hemisphere shows the furnace's holes. Asserted: [lo, hi] around those."""
    up = np.array([[0.0, 0.0, 1.0]])
    g = ImportanceGatherer(gl_context, sphere_nodes(12000, 1.0, deg), GatherParams(32, brdf="lambert"))
    rad, _ = g.run(receivers(np.zeros((1, 3)), up))
    ref = math.sin(math.radians(deg)) ** 2
    assert (1 + lo) * ref <= rad[0, 0] <= (1 + hi) * ref
    g.release()
    g2 = ImportanceGatherer(gl_context, sphere_nodes(12000, 1.0, deg, (0, 0, -1)), GatherParams(32, brdf="lambert"))
    rad2, _ = g2.run(receivers(np.zeros((1, 3)), up))
    assert rad2[0, 0] == 0.0
    g2.release()


def test_exhaustive_matches_classic_microbuffer(gl_context):
    """Every point projected (each its own area, Ω_s = ΔA_s|cos θ_s|/d²) against classic walked down to its
    leaves (stop_multiple 0), m = 16, a 4000-point sphere of smoothly varying colour around 8 receivers: both
    cover every used texel; texel by texel the colours differ by 1.5 % (median), 12 % (99th percentile), the
    radiance by −0.9 … +3.2 % (measured). Not equal: a square splat reaches up to ⌈side/2⌉ texels from its point
    and the nearest wins the overlap (classic's ray-traced discs do not spill), so nearer points take a few more
    texels. Asserted: ≥ 99 % covered by both, median < 3 %, 99th percentile < 20 %, radiance within 5 %."""
    rng = np.random.default_rng(5)
    p = fib_sphere(4000)
    col = np.c_[1 + 0.5 * p[:, 0], 1 + 0.5 * p[:, 1], 1 + 0.5 * p[:, 2]]
    nodes = build_simple_bsh(p, -p, col, 0.5 * math.sqrt(4 * math.pi / 4000))
    pos = rng.uniform(-0.3, 0.3, (8, 3))
    nrm = rng.normal(size=(8, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    r = receivers(pos, nrm)
    gi = ImportanceGatherer(gl_context, nodes, GatherParams(16, brdf="lambert"), clusters=64, exhaustive=True)
    gc = ClassicGatherer(gl_context, nodes, GatherParams(16, brdf="lambert", stop_multiple=0.0))
    gi.keep_microbuffers = gc.keep_microbuffers = True
    ri, _ = gi.run(r)
    rc, _ = gc.run(r)
    mi, mc = gi.last_microbuffers, gc.last_microbuffers
    used = texel_table(16)[:, 2].reshape(16, 16) > 0
    both = used[None] & (mi[..., 3] < 3e38) & (mc[..., 3] < 3e38)   # written (classic: its fallbacks too)
    assert both.sum() >= 0.99 * used.sum() * len(r)
    rel = np.abs(mi[..., :3] - mc[..., :3])[both] / mc[..., :3][both]
    assert np.median(rel) < 0.03 and np.percentile(rel, 99) < 0.2, (np.median(rel), np.percentile(rel, 99))
    np.testing.assert_allclose(ri, rc, rtol=0.05)
    gi.release()
    gc.release()


def test_deterministic_for_the_seed(gl_context):
    rng = np.random.default_rng(2)
    pos = rng.uniform(-0.4, 0.4, (32, 3))
    nrm = rng.normal(size=(32, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    p = fib_sphere(3000)
    nodes = build_simple_bsh(p, -p, np.c_[1 + p[:, 0], 1 + p[:, 1] ** 2, 1 + p[:, 2] * 0.5], 0.03)
    out = []
    for seed in (7, 7, 8):
        g = ImportanceGatherer(gl_context, nodes, GatherParams(16, brdf="ggx", seed=seed), clusters=64)
        out.append(g.run(receivers(pos, nrm, roughness=0.3))[0])
        g.release()
    assert np.array_equal(out[0], out[1]) and not np.array_equal(out[0], out[2])


# --------------------------------------------------------------------------- relight end to end
def _scene(tmp_path) -> list[str]:
    """A furnace through the real CLI: 3000 points on a sphere of radius 3 (radiance 1, normals inward), an
    icosphere object of radius 0.5."""
    import trimesh
    from bsh_builders import simple_bsh_arrays

    from pipeline import io

    p = fib_sphere(3000)
    io.write_npz(tmp_path / "bsh.npz", "pcrelight.bsh/1",
                 **simple_bsh_arrays(3 * p, -p, np.ones((3000, 3)), 1.5 * math.sqrt(4 * math.pi / 3000)))
    tm = trimesh.creation.icosphere(2, radius=0.5)
    io.write_mesh(tmp_path / "o.ply", tm.vertices, tm.faces, tm.vertex_normals)
    return ["relight", "--bsh", str(tmp_path / "bsh.npz"), "--object", str(tmp_path / "o.ply"), "--eye", "0,0,2",
            "--target", "0,0,0", "--size", "24x20", "--brdf", "lambert", "--albedo", "0.5,0.25,1", "--method",
            "importance", "--adaptive", "0", "-q"]


def test_relight_importance_end_to_end(tmp_path, cli_run):
    """relight --method importance: the furnace within the furnace test's bounds (6 % below, none above), the
    object's surfels in its own micro-buffers (auto: the sphere is convex, so they must not darken it), the method's statistics in stats.json, byte-identical for one --seed."""
    from pipeline import io

    for out, seed in (("a", 3), ("b", 3), ("c", 4)):
        code, _, err = cli_run(*_scene(tmp_path), "--seed", str(seed), "--out", tmp_path / out)
        assert code == 0, err
    img = io.read_image(tmp_path / "a" / "relit.exr")
    st = io.read_json(tmp_path / "a" / "stats.json")
    cov = img[..., 3] > 0
    assert cov.sum() == st["covered_pixels"] > 50
    q = img[cov][:, :3] / np.float32([0.5, 0.25, 1.0])
    assert q.min() > 0.94 and q.max() <= 1.0 + 1e-5, (q.min(), q.max())
    assert st["method"] == "importance" and st["decisions"]["object_in_own_micro_buffers"] is True
    s = st["method_stats"]["importance"]
    assert s["budget_drawn_min"] == s["budget_drawn_max"] == s["budget"] == ImportanceGatherer.SAMPLES * s["clusters"]
    assert np.array_equal(img, io.read_image(tmp_path / "b" / "relit.exr"))
    assert not np.array_equal(img, io.read_image(tmp_path / "c" / "relit.exr"))


def test_relight_importance_shadows_the_object_as_classic(tmp_path, cli_run):
    """The object in its own light (issue 45 §3): two touching spheres under a sky (the upper half of the shell
    at radiance 1, the lower half black), Lambert 0.5, no bounces: where one sphere hides the sky from the other,
    importance darkens it as classic does: its object surfels are splatted as the walk splats them (measured
    2026-12-08: 0.9996 × classic's mean, 4×4 blocks 0.27 % RMS; as ⌈⌉-rounded squares before: within 4 % / 10 %).
    Asserted: within 0.5 % of classic's on the mean and 1 % 4×4-block RMS; both ≥ 3 % darker than with --surfels -1
    (the object absent from its light)."""
    import trimesh
    from bsh_builders import simple_bsh_arrays

    from pipeline import io

    p = fib_sphere(6000)
    col = np.where(p[:, 1:2] > 0, 1.0, 0.0) * np.ones((1, 3))
    io.write_npz(tmp_path / "bsh.npz", "pcrelight.bsh/1",
                 **simple_bsh_arrays(4 * p, -p, col, 2.0 * math.sqrt(4 * math.pi / 6000)))
    a, b = trimesh.creation.icosphere(3, radius=0.4), trimesh.creation.icosphere(3, radius=0.4)
    a.apply_translation([-0.4, 0.0, 0.0])
    b.apply_translation([0.4, 0.2, 0.0])
    tm = trimesh.util.concatenate([a, b])
    io.write_mesh(tmp_path / "o.ply", tm.vertices, tm.faces, tm.vertex_normals)
    base = ["relight", "--bsh", str(tmp_path / "bsh.npz"), "--object", str(tmp_path / "o.ply"), "--eye", "0,0,2.5",
            "--target", "0,0.1,0", "--size", "48x48", "--brdf", "lambert", "--albedo", "0.5,0.5,0.5", "--bounces", "0",
            "--adaptive", "0", "-q"]
    img = {}
    for name, extra in (("imp", ["--method", "importance"]), ("cls", ["--method", "classic"]),
                        ("imp_off", ["--method", "importance", "--surfels", "-1"]),
                        ("cls_off", ["--method", "classic", "--surfels", "-1"])):
        code, _, err = cli_run(*base, *extra, "--out", tmp_path / name)
        assert code == 0, err
        img[name] = io.read_image(tmp_path / name / "relit.exr")
    cov = img["cls"][..., 3] > 0
    mean = {k: float(v[..., 0][cov].mean()) for k, v in img.items()}
    assert abs(mean["imp"] / mean["cls"] - 1) < 0.005, mean
    assert mean["imp"] < 0.97 * mean["imp_off"] and mean["cls"] < 0.97 * mean["cls_off"], mean
    blocks = cov.reshape(12, 4, 12, 4).all((1, 3))
    bi, bc = (v[..., 0].reshape(12, 4, 12, 4).mean((1, 3))[blocks] for v in (img["imp"], img["cls"]))
    assert np.sqrt(np.mean((bi - bc) ** 2) / np.mean(bc ** 2)) < 0.01
