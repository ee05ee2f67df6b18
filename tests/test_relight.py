"""relight (classic PBGI + Eq. 9 gather) against independent truths: white furnace, spherical cap,
a brute-force CPU gather of disc splats, extremes; plus the G-buffer and the CLI.

BSHs are built here with ``relight.build_simple_bsh`` (median splits, exact spheres and cones) so the
tests do not depend on build-bsh.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline import brdf
from pipeline.relight import (Gatherer, Receivers, build_simple_bsh, tangent_frame, texel_table)


def fib_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    th = np.pi * (1 + 5 ** 0.5) * i
    return np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], 1)


def receivers(pos, nrm, view, base=1.0, metallic=0.0, roughness=0.5) -> Receivers:
    pos = np.asarray(pos, np.float32).reshape(-1, 3)
    k = len(pos)
    f = lambda v: np.broadcast_to(np.asarray(v, np.float32), (k,)).copy()  # noqa: E731
    return Receivers(pos, np.asarray(nrm, np.float32).reshape(-1, 3), np.asarray(view, np.float32).reshape(-1, 3),
                     np.broadcast_to(np.asarray(base, np.float32), (k, 3)).copy(), f(metallic), f(roughness))


@pytest.fixture(scope="module")
def furnace_nodes():
    """Closed unit sphere of 3000 points, radiance L = 2, normals inward, leaf radius = spacing."""
    p = fib_sphere(3000)
    return build_simple_bsh(p, -p, np.full((len(p), 3), 2.0), math.sqrt(4 * math.pi / len(p)))


def random_receivers(k: int, seed: int = 0, spread: float = 0.3):
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-spread, spread, (k, 3))
    nrm = rng.normal(size=(k, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return pos, nrm


# --------------------------------------------------------------------------- texel table
@pytest.mark.parametrize("m", [8, 16, 24, 32])
def test_texel_table_exact_integrals(m):
    t = texel_table(m, "exact")
    assert t[:, 2].sum() == pytest.approx(2 * math.pi, rel=1e-6)       # ∫ dω over the hemisphere
    assert t[:, 3].sum() == pytest.approx(math.pi, rel=1e-6)            # ∫ cos dω
    # an interior and a rim texel against scipy's adaptive 2-D quadrature (independent of the table's)
    from scipy import integrate

    e = np.linspace(-1, 1, m + 1)
    for u, v in ((m // 2, m // 2 + 1), (m - 1, m // 2)):
        x0, x1, y0, y1 = e[u], e[u + 1], e[v], e[v + 1]
        ylo = lambda x: max(y0, -math.sqrt(max(1 - x * x, 0)))  # noqa: E731
        yhi = lambda x: min(y1, math.sqrt(max(1 - x * x, 0)))  # noqa: E731
        f = lambda y, x: 1 / math.sqrt(max(1 - x * x - y * y, 1e-300))  # noqa: E731
        om, _ = integrate.dblquad(f, x0, min(x1, 1.0), ylo, yhi, epsabs=1e-10, epsrel=1e-8)
        ar, _ = integrate.dblquad(lambda y, x: 1.0, x0, min(x1, 1.0), ylo, yhi)
        assert t[v * m + u, 2] == pytest.approx(om, rel=1e-4)
        assert t[v * m + u, 3] == pytest.approx(ar, rel=1e-5)
    d = np.c_[t[:, :2], np.sqrt(np.maximum(1 - (t[:, :2] ** 2).sum(1), 0))]
    assert np.all(np.abs(np.linalg.norm(d, axis=1) - 1) < 1e-5)


def test_tangent_frame_orthonormal():
    rng = np.random.default_rng(1)
    n = rng.normal(size=(1000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[:4] = [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, -1, 0]]
    t, b = tangent_frame(n)
    assert np.allclose(np.cross(t, b), n, atol=1e-6)
    assert np.allclose((t * n).sum(1), 0, atol=1e-6) and np.allclose((b * n).sum(1), 0, atol=1e-6)


# --------------------------------------------------------------------------- white furnace
@pytest.mark.parametrize("m", [8, 16, 24, 32])
def test_furnace_lambert_exact(gl_context, furnace_nodes, m):
    pos, nrm = random_receivers(64)
    g = Gatherer(gl_context, furnace_nodes, m, brdf="lambert")
    rad, st = g.run(receivers(pos, nrm, nrm, base=0.8))
    assert st["nodes_visited"] > 0 and st["tiles"] == 1
    np.testing.assert_allclose(rad, 0.8 * 2.0, rtol=0.02)


@pytest.mark.parametrize("m", [8, 16, 32])
def test_furnace_paper_solid_angle_bias(gl_context, furnace_nodes, m):
    """Eq. 5's constant Ω = 2π/m² substituted for the node's: the furnace comes out biased by exactly
    Σ_centre-inside (2π/m²)·z_centre / π − 1 (computed here from the texel centres)."""
    pos, nrm = random_receivers(32, seed=2)
    g = Gatherer(gl_context, furnace_nodes, m, brdf="lambert", solid_angle="paper")
    rad, _ = g.run(receivers(pos, nrm, nrm, base=1.0))
    c = (np.arange(m) + 0.5) / m * 2 - 1
    x, y = np.meshgrid(c, c)
    r2 = x * x + y * y
    bias = (2 * math.pi / m ** 2) * np.sqrt(1 - r2[r2 < 1]).sum() / math.pi - 1
    assert bias > 0.04  # the paper's rule over-estimates by 4.7–7.4 % at m = 8…32
    np.testing.assert_allclose(rad / 2.0 - 1, bias, atol=2e-4)


@pytest.mark.parametrize("kind,rough,metal,masking", [
    ("ggx", 0.5, 1.0, "height-correlated"), ("ggx", 0.5, 1.0, "separable"),
    ("ggx", 1.0, 1.0, "height-correlated"), ("ggx", 1.0, 1.0, "separable"),
    ("ggx", 0.5, 0.0, "height-correlated"),
    ("disney", 0.3, 0.0, "height-correlated"), ("disney", 0.7, 0.5, "height-correlated"),
    ("disney", 0.5, 1.0, "height-correlated"),
])
def test_furnace_glossy_directional_albedo(gl_context, furnace_nodes, kind, rough, metal, masking):
    """White base colour in the furnace → L × directional albedo, the albedo by Gauss–Legendre ×
    midpoint quadrature of brdf.py (independent of the micro-buffer)."""
    th = np.array([0.1, 0.7, 1.2])
    view = np.stack([np.sin(th), 0 * th, np.cos(th)], 1)
    nrm = np.tile([0.0, 0.0, 1.0], (3, 1))
    g = Gatherer(gl_context, furnace_nodes, 32, brdf=kind, masking=masking)
    rad, _ = g.run(receivers(np.zeros((3, 3)), nrm, view, 1.0, metal, rough))
    ref = np.array([brdf.directional_albedo(kind, v, (1, 1, 1), metal, rough, masking, 200, 200)[0] for v in view])
    np.testing.assert_allclose(rad[:, 0] / 2.0, ref, rtol=0.02)


def test_brdf_glsl_matches_numpy(gl_context):
    """brdf.glsl against brdf.py at random directions (all kinds, both maskings)."""
    from pipeline import gl

    src = """#version 430
#include "brdf.glsl"
layout(local_size_x = 1) in;
layout(std430, binding = 0) readonly buffer In { vec4 inp[]; };
layout(std430, binding = 1) writeonly buffer Out { vec4 outp[]; };
uniform int kind; uniform int masking;
void main() {
    uint k = gl_GlobalInvocationID.x;
    vec4 a = inp[3u * k], b = inp[3u * k + 1u], c = inp[3u * k + 2u];
    outp[k] = vec4(brdf_eval(kind, masking, a.xyz, b.xyz, vec3(0, 0, 1), c.xyz, a.w, b.w), 0.0);
}"""
    prog = gl_context.compute_shader(src.replace('#include "brdf.glsl"', gl.load_glsl("brdf.glsl", brdf.__file__)))
    rng = np.random.default_rng(3)
    k = 256

    def hemi(n):
        v = rng.normal(size=(n, 3))
        v[:, 2] = np.abs(v[:, 2]) + 0.05
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    wi, wo = hemi(k), hemi(k)
    base = rng.uniform(0, 1, (k, 3))
    met, rough = rng.uniform(0, 1, k), rng.uniform(0.05, 1, k)
    data = np.zeros((k, 3, 4), np.float32)
    data[:, 0, :3], data[:, 0, 3] = wi, met
    data[:, 1, :3], data[:, 1, 3] = wo, rough
    data[:, 2, :3] = base
    bi = gl_context.buffer(data.tobytes())
    bo = gl_context.buffer(reserve=k * 16)
    bi.bind_to_storage_buffer(0)
    bo.bind_to_storage_buffer(1)
    for kind, kid in (("lambert", 0), ("ggx", 1), ("disney", 2)):
        for mname, mid in (("height-correlated", 0), ("separable", 1)):
            prog["kind"].value = kid
            try:
                prog["masking"].value = mid
            except KeyError:
                pass
            prog.run(group_x=k)
            got = np.frombuffer(bo.read(), np.float32).reshape(k, 4)[:, :3]
            ref = brdf.evaluate(kind, wi, wo, np.array([0, 0, 1.0]), base, met, rough, mname)
            np.testing.assert_allclose(got, ref, rtol=2e-3, atol=1e-5 * (1 + np.abs(ref).max()))


# --------------------------------------------------------------------------- spherical cap
def cap_nodes(theta: float, axis, n_sphere: int = 40000, L: float = 1.0):
    p = fib_sphere(n_sphere)
    keep = p @ np.asarray(axis, float) >= math.cos(theta)
    p = p[keep]
    return build_simple_bsh(p, -p, np.full((len(p), 3), L), 0.5 * math.sqrt(4 * math.pi / n_sphere))


@pytest.mark.parametrize("theta", [math.radians(75), math.radians(90)])
def test_spherical_cap_irradiance(gl_context, theta):
    """Cap of half-angle θ centred on the normal, radiance L: irradiance E = π L sin²θ, so a white
    Lambert receiver at the centre reflects L sin²θ; a cap behind the surface gives exactly 0.
    Measured limitation (not asserted): with the 4Ω stop rule the bounding spheres of the nodes along
    the cap's rim overhang it, so smaller caps come out too bright (m = 32: +2.9 % at 60°, +5.4 % at
    45°, +9.4 % at 30°; m = 16: +25 % at 30°)."""
    nodes = cap_nodes(theta, [0, 0, 1])
    g = Gatherer(gl_context, nodes, 32, brdf="lambert")
    up = np.array([[0.0, 0.0, 1.0]])
    rad, _ = g.run(receivers(np.zeros((1, 3)), up, up))
    assert rad[0, 0] == pytest.approx(math.sin(theta) ** 2, rel=0.03)
    behind = cap_nodes(theta, [0, 0, -1])
    g2 = Gatherer(gl_context, behind, 32, brdf="lambert")
    rad2, st2 = g2.run(receivers(np.zeros((1, 3)), up, up))
    assert rad2[0, 0] == 0.0 and st2["nodes_visited"] >= 1
