"""Reference BRDFs in numpy (the GLSL twins live in ``brdf.glsl``; tests compare the two).

Conventions: ``wi`` (towards the light) and ``wo`` (towards the viewer) are unit vectors, ``n``
the unit shading normal; arrays broadcast over leading axes, the last axis is xyz. Every BRDF
returns ``f(wi, wo)`` in 1/sr as (..., 3) linear RGB, zero when ``wi`` or ``wo`` is below the
surface. The reflected radiance is ``∫ f(wi, wo) L(wi) (n·wi) dwi``.

- ``lambert``: ``base_color / π``.
- ``ggx``: Cook–Torrance microfacet with the GGX/Trowbridge–Reitz distribution,
  α = roughness², Schlick Fresnel with F0 = mix(0.04, base_color, metallic) (F0 = 1 for the
  ground truth's white metal: base colour 1, metallic 1) and Smith masking — ``height-correlated``
  (default; Heitz 2014 Eq. 99) or ``separable`` G1(wi)·G1(wo) (Mitsuba's roughconductor).
  A metallic < 1 GGX adds the Lambert lobe (1 − metallic)·base_color/π.
- ``disney``: Burley 2012 principled BRDF with the glTF metallic-roughness mapping (specular 0.5
  → dielectric F0 0.04, subsurface = sheen = clearcoat = 0): diffuse with the Fd90 retro-reflection
  term times (1 − metallic), GTR2 specular with α = roughness², Schlick Fresnel, separable Smith GGX
  masking with Burley's α_g = (0.5 + roughness/2)².
"""

from __future__ import annotations

import numpy as np

KINDS = ("lambert", "ggx", "disney")
MASKINGS = ("height-correlated", "separable")
ALPHA_MIN = 1e-4  # smallest GGX α: avoids 0/0 for a perfect mirror


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.sum(a * b, axis=-1)


def f0_from(base_color: np.ndarray, metallic: np.ndarray) -> np.ndarray:
    """Schlick F0 (..., 3): 0.04 for a dielectric, the base colour for a metal, linear in between."""
    m = np.asarray(metallic, np.float64)[..., None]
    return 0.04 * (1.0 - m) + np.asarray(base_color, np.float64) * m


def fresnel_schlick(f0: np.ndarray, cos_t: np.ndarray) -> np.ndarray:
    """F0 + (1 − F0)(1 − cos)^5 (..., 3)."""
    c = np.clip(np.asarray(cos_t, np.float64), 0.0, 1.0)[..., None]
    return f0 + (1.0 - f0) * (1.0 - c) ** 5


def ggx_d(nh: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """GGX normal distribution D(h) [1/sr], normalised so ∫ D (n·h) dh = 1."""
    a2 = np.asarray(alpha, np.float64) ** 2
    nh = np.asarray(nh, np.float64)
    t = nh * nh * (a2 - 1.0) + 1.0
    return np.where(nh > 0, a2 / (np.pi * t * t), 0.0)


def smith_g1(nx: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Smith G1 for GGX: 2 cos / (cos + sqrt(α² + (1 − α²) cos²))."""
    a2 = np.asarray(alpha, np.float64) ** 2
    c = np.clip(np.asarray(nx, np.float64), 0.0, 1.0)
    return 2.0 * c / np.maximum(c + np.sqrt(a2 + (1.0 - a2) * c * c), 1e-30)


def smith_g2_height_correlated(nl: np.ndarray, nv: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Height-correlated Smith G2 = 1 / (1 + Λ(l) + Λ(v)) for GGX."""
    a2 = np.asarray(alpha, np.float64) ** 2

    def lam(c):
        c = np.clip(c, 1e-12, 1.0)
        return 0.5 * (np.sqrt(1.0 + a2 * (1.0 - c * c) / (c * c)) - 1.0)

    return 1.0 / (1.0 + lam(np.asarray(nl, np.float64)) + lam(np.asarray(nv, np.float64)))


def ggx_alpha(roughness: np.ndarray) -> np.ndarray:
    """GGX α = roughness², at least :data:`ALPHA_MIN` (float64)."""
    return np.maximum(np.asarray(roughness, np.float64) ** 2, ALPHA_MIN)


_alpha = ggx_alpha


def lambert(wi, wo, n, base_color) -> np.ndarray:
    nl, nv = _dot(wi, n), _dot(wo, n)
    ok = ((nl > 0) & (nv > 0))[..., None]
    return np.where(ok, np.asarray(base_color, np.float64) / np.pi, 0.0) * np.ones_like(np.asarray(wi, np.float64))


def ggx(wi, wo, n, base_color, metallic, roughness, masking: str = "height-correlated") -> np.ndarray:
    wi, wo, n = (np.asarray(x, np.float64) for x in (wi, wo, n))
    nl, nv = _dot(wi, n), _dot(wo, n)
    h = wi + wo
    h = h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-30)
    nh, lh = _dot(n, h), _dot(wi, h)
    a = _alpha(roughness)
    d = ggx_d(nh, a)
    if masking == "separable":
        g = smith_g1(nl, a) * smith_g1(nv, a)
    elif masking == "height-correlated":
        g = smith_g2_height_correlated(nl, nv, a)
    else:
        raise ValueError(f"unknown masking {masking!r}")
    metallic = np.asarray(metallic, np.float64)
    base = np.asarray(base_color, np.float64)
    f = fresnel_schlick(f0_from(base, metallic), lh)
    ok = (nl > 0) & (nv > 0)
    spec = f * (d * g / np.maximum(4.0 * nl * nv, 1e-30))[..., None]
    diff = (1.0 - metallic)[..., None] * base / np.pi
    return np.where(ok[..., None], spec + diff, 0.0)


def disney(wi, wo, n, base_color, metallic, roughness) -> np.ndarray:
    wi, wo, n = (np.asarray(x, np.float64) for x in (wi, wo, n))
    nl, nv = _dot(wi, n), _dot(wo, n)
    h = wi + wo
    h = h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-30)
    nh, lh = _dot(n, h), _dot(wi, h)
    rough = np.asarray(roughness, np.float64)
    metallic = np.asarray(metallic, np.float64)
    base = np.asarray(base_color, np.float64)
    fl = (1.0 - np.clip(nl, 0, 1)) ** 5
    fv = (1.0 - np.clip(nv, 0, 1)) ** 5
    fd90 = 0.5 + 2.0 * rough * lh * lh
    fd = (1.0 + (fd90 - 1.0) * fl) * (1.0 + (fd90 - 1.0) * fv)
    diff = (1.0 - metallic)[..., None] * base / np.pi * fd[..., None]
    a = _alpha(rough)
    d = ggx_d(nh, a)
    ag = (0.5 + 0.5 * rough) ** 2
    g = smith_g1(nl, ag) * smith_g1(nv, ag)
    f = fresnel_schlick(f0_from(base, metallic), lh)
    spec = f * (d * g / np.maximum(4.0 * nl * nv, 1e-30))[..., None]
    ok = (nl > 0) & (nv > 0)
    return np.where(ok[..., None], diff + spec, 0.0)


def evaluate(kind: str, wi, wo, n, base_color, metallic=0.0, roughness=0.5,
             masking: str = "height-correlated") -> np.ndarray:
    """Dispatch on ``kind`` in :data:`KINDS`."""
    if kind == "lambert":
        return lambert(wi, wo, n, base_color)
    if kind == "ggx":
        return ggx(wi, wo, n, base_color, metallic, roughness, masking)
    if kind == "disney":
        return disney(wi, wo, n, base_color, metallic, roughness)
    raise ValueError(f"unknown BRDF {kind!r}")


def _spec_fg(kind, nl, nv, lh, base_color, metallic, roughness, masking):
    """F·G of the specular lobe (..., 3): f_spec = F G D / (4 nl nv)."""
    a = _alpha(roughness)
    f = fresnel_schlick(f0_from(base_color, metallic), lh)
    if kind == "disney":
        ag = (0.5 + 0.5 * np.asarray(roughness, np.float64)) ** 2
        g = smith_g1(nl, ag) * smith_g1(nv, ag)
    elif masking == "separable":
        g = smith_g1(nl, a) * smith_g1(nv, a)
    else:
        g = smith_g2_height_correlated(nl, nv, a)
    return f * g[..., None]


def diffuse_part(kind, wi, wo, n, base_color, metallic=0.0, roughness=0.5) -> np.ndarray:
    """The non-microfacet part of :func:`evaluate` (Lambert; (1−metallic)·base/π for GGX; Burley's
    diffuse for Disney)."""
    if kind == "lambert":
        return lambert(wi, wo, n, base_color)
    if kind == "ggx":
        wi = np.asarray(wi, np.float64)
        ok = ((_dot(wi, n) > 0) & (_dot(wo, n) > 0))[..., None]
        d = (1.0 - np.asarray(metallic, np.float64))[..., None] * np.asarray(base_color, np.float64) / np.pi
        return np.where(ok, d, 0.0) * np.ones_like(wi)
    return disney(wi, wo, n, base_color, metallic, roughness) - _disney_spec(wi, wo, n, base_color, metallic, roughness)


def _disney_spec(wi, wo, n, base_color, metallic, roughness):
    wi, wo, n = (np.asarray(x, np.float64) for x in (wi, wo, n))
    nl, nv = _dot(wi, n), _dot(wo, n)
    h = wi + wo
    h = h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-30)
    d = ggx_d(_dot(n, h), _alpha(roughness))
    fg = _spec_fg("disney", nl, nv, _dot(wi, h), np.asarray(base_color, np.float64), np.asarray(metallic, np.float64),
                  roughness, "")
    ok = (nl > 0) & (nv > 0)
    return np.where(ok[..., None], fg * (d / np.maximum(4.0 * nl * nv, 1e-30))[..., None], 0.0)


def directional_albedo(kind: str, wo, base_color=(1.0, 1.0, 1.0), metallic=0.0, roughness=0.5,
                       masking: str = "height-correlated", n_theta: int = 512, n_phi: int = 512) -> np.ndarray:
    """∫ f(wi, wo) (n·wi) dwi over the hemisphere (n = +Z), the reference for the white-furnace tests.
    Diffuse part: Gauss–Legendre in cos θ × midpoint in φ. Specular part in half-vector space with
    GGX's own CDF variable u = tan²θh / (α² + tan²θh), where D(h) cos θh dω_h = du dφ / 2π, so the
    integrand F·G·(wo·h) / (wo.z cos θh) is smooth however narrow the lobe (Gauss–Legendre in u ×
    midpoint in φ). Returns (3,)."""
    wo = np.asarray(wo, np.float64)
    nrm = np.array([0.0, 0.0, 1.0])
    base = np.asarray(base_color, np.float64)
    x, w = np.polynomial.legendre.leggauss(n_theta)
    mu = 0.5 * (x + 1.0)
    wmu = 0.5 * w
    phi = (np.arange(n_phi) + 0.5) * (2 * np.pi / n_phi)
    total = np.zeros(3)
    # diffuse
    st = np.sqrt(1.0 - mu * mu)
    wi = np.stack([st[:, None] * np.cos(phi)[None], st[:, None] * np.sin(phi)[None],
                   np.broadcast_to(mu[:, None], (n_theta, n_phi))], axis=-1)
    fd = diffuse_part(kind, wi, wo, nrm, base, np.float64(metallic), np.float64(roughness))
    total += np.einsum("ijc,i->c", fd * mu[:, None, None], wmu) * (2 * np.pi / n_phi)
    if kind == "lambert":
        return total
    # specular, in h-space
    a = float(_alpha(roughness))
    u = mu                                    # u in (0, 1)
    tan2 = a * a * u / (1.0 - u)
    ch = 1.0 / np.sqrt(1.0 + tan2)
    sh = np.sqrt(np.maximum(1.0 - ch * ch, 0.0))
    h = np.stack([sh[:, None] * np.cos(phi)[None], sh[:, None] * np.sin(phi)[None],
                  np.broadcast_to(ch[:, None], (n_theta, n_phi))], axis=-1)
    oh = _dot(h, wo)
    wi = 2.0 * oh[..., None] * h - wo
    nl = wi[..., 2]
    ok = (nl > 0) & (oh > 0)
    fg = _spec_fg(kind, np.where(ok, nl, 1.0), wo[2], np.where(ok, oh, 1.0), base, np.float64(metallic),
                  np.float64(roughness), masking)
    integ = np.where(ok[..., None], fg * (oh / (wo[2] * ch[:, None]))[..., None], 0.0)
    total += np.einsum("ijc,i->c", integ, wmu) / n_phi
    return total


def sample_vndf(wo: np.ndarray, alpha: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Heitz 2018 visible-normal sampling of GGX, the twin of ``brdf.glsl`` brdf_sample_vndf: local frame (n = +z,
    wo.z > 0), ``u`` (..., 2) in [0,1)², α (...) ; returns wi (..., 3) (may be below the horizon). The estimator of
    ∫ f_spec (n·wi) L dwi is L(wi) · :func:`spec_weight`, pdf G1(wo) D(h) / (4 wo.z)."""
    wo = np.asarray(wo, np.float64)
    a = np.asarray(alpha, np.float64)
    u = np.asarray(u, np.float64)
    vh = np.stack([a * wo[..., 0], a * wo[..., 1], wo[..., 2]], -1)
    vh = vh / np.linalg.norm(vh, axis=-1, keepdims=True)
    lensq = vh[..., 0] ** 2 + vh[..., 1] ** 2
    inv = np.where(lensq > 0, 1.0 / np.sqrt(np.where(lensq > 0, lensq, 1.0)), 0.0)
    t1 = np.where((lensq > 0)[..., None], np.stack([-vh[..., 1] * inv, vh[..., 0] * inv, np.zeros_like(inv)], -1),
                  np.array([1.0, 0.0, 0.0]))
    t2 = np.cross(vh, t1)
    r = np.sqrt(u[..., 0])
    phi = 2.0 * np.pi * u[..., 1]
    p1, p2 = r * np.cos(phi), r * np.sin(phi)
    s = 0.5 * (1.0 + vh[..., 2])
    p2 = (1.0 - s) * np.sqrt(np.maximum(1.0 - p1 * p1, 0.0)) + s * p2
    nh = p1[..., None] * t1 + p2[..., None] * t2 + np.sqrt(np.maximum(0.0, 1.0 - p1 * p1 - p2 * p2))[..., None] * vh
    h = np.stack([a * nh[..., 0], a * nh[..., 1], np.maximum(0.0, nh[..., 2])], -1)
    h = h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-30)
    return 2.0 * _dot(wo, h)[..., None] * h - wo


def spec_weight(kind: str, wi: np.ndarray, wo: np.ndarray, base_color, metallic, roughness,
                masking: str = "height-correlated") -> np.ndarray:
    """(..., 3) the VNDF-sampling weight f_spec·cos/pdf = F·G / G1(wo) of a direction ``wi`` drawn by
    :func:`sample_vndf` (local frame, n = +z; 0 where wi or wo is below the horizon) — eq9.comp.glsl's estimator."""
    wi, wo = np.asarray(wi, np.float64), np.asarray(wo, np.float64)
    nl, nv = wi[..., 2], wo[..., 2]
    h = wi + wo
    h = h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-30)
    ok = (nl > 0) & (nv > 0)
    fg = _spec_fg(kind, np.where(ok, nl, 1.0), np.where(ok, nv, 1.0), _dot(wi, h), np.asarray(base_color, np.float64),
                  np.asarray(metallic, np.float64), roughness, masking)
    g1 = smith_g1(np.where(ok, nv, 1.0), _alpha(roughness))
    return np.where(ok[..., None], fg / np.maximum(g1, 1e-30)[..., None], 0.0)
