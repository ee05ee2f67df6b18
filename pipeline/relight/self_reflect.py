"""A glossy object's reflections of itself at pixel resolution (issue 22): a per-pixel secondary gather where a
glossy pixel's lobe sees the object.

The gather with the object in its own micro-buffers (:mod:`.surfels`) reads the object's light from its surfels'
directional bounce maps (~6 cm apart, 16² directions): a near-mirror bowl's inside, a hall of mirrors whose rings
are 2–4 px wide, is blurred and misplaced. Here a glossy receiver's Eq. 9 radiance is split in two:

* A — the gather with the object's surfels black (the room's light, the object an occluder only);
* B — ∫ over the lobe directions ω that meet the object of f·cos·L(q(ω), −ω) dω, estimated by sampling the BRDF
  lobe: K VNDF directions a pixel (:func:`pipeline.gather.brdf.sample_vndf`, weight F·G/G1; plus K cosine-weighted ones
  for a diffuse part, weight π·f_d), each cast against the object's triangles (Open3D's Embree ray caster,
  :class:`MeshCaster`); at every hit q a secondary receiver (position q, normals and material from the mesh:
  :func:`.surfels.surface_at`, view −ω) is gathered by the same gatherer over the object's LIT surfels (their
  directional maps): the reflection of a reflection comes from the surfels. B = Σ_hits w_k L_k / K; a miss adds 0
  (A holds the room there).

The surfels' discs do not cover exactly what the triangles cover (a cluster's disc overhangs a silhouette, and the
room leaks between discs: the test's patch covers 0.80–1.0 of a lobe in a 16² micro-buffer, the rays 0.98–1.0), so A
loses room light where the discs hide what the rays find open (a thin tube's reflection grazing past another part of
the knot) and keeps some where they leak. With :data:`COVER` (default) A is corrected by what the two disagree on:
A + (c − h)·E, floored at 0, with c the BRDF-weighted share of the lobe the object's surfels cover in the micro-buffer
(:func:`coverage`: one more gather, room (0,1,0), object (1,1,0)), h the BRDF-weighted share of the K rays that meet
the triangles (:func:`ray_share`), and E the gather over the room alone (:func:`.surfels.subtree`: the lobe's room light as if
the object were absent; its mean over the lobe stands for the part in dispute). Measured (bench/README.md
'per-pixel self-reflection'): the knot's view2 GGX 0.1 from 0.975 to 0.982 / 0.982 / 0.980 of ``full_*`` (7.9 % block
RMS, was 8.7 %), its view2 GGX 0.25 6.6 → 3.5 %, the bowl's view1 GGX 0.1 / 0.25 13.1 / 7.4 → 11.9 / 6.9 %. (A first
form, A·(1 − h)/(1 − c) with h from 64 rays of their own, left the knot at 0.974: it cannot correct a pixel whose lobe
the discs hide wholly, c → 1.)

A pixel none of whose K rays meets the object keeps the ordinary gather (B = 0 exactly; the surfels' share of its
lobe is what the K rays did not find). Pixels rougher than :data:`MAX_ROUGHNESS` keep it too (their lobes are
wide: the surfels resolve them). Samples: a Fibonacci lattice of K points, Cranley–Patterson rotated per pixel by
``default_rng(sub_seed(seed, SEED_TAG))`` (the same --seed gives the same image).

Units: metres, linear RGB radiance.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Optional

import numpy as np

from ..gather.base import Receivers
from ..gather.walk import tangent_frame

SEED_TAG = 22          # sub_seed(seed, SEED_TAG): the per-pixel rotations of the lobe samples
MAX_ROUGHNESS = 0.5    # pixels with roughness below this (relight's GLOSSY_BOUNCE_ROUGHNESS: directional bounces)
SECONDARY_M = 16       # the secondary receivers' micro-buffer side
SECONDARY_LOBE = 8     # their n×n VNDF samples (surfels.DIR_LOBE_SAMPLES)
SECONDARY_LOBE_M = 16  # their lobe micro-buffer side (0 = none: the lobe samples read the hemisphere buffer)
OFFSET = 1e-4          # ray origins lifted this × the object's bounding radius along the geometric normal
COVER = True           # correct A where the surfels' coverage of the lobe and the rays' disagree (module doc)
COVER_RAYS = 64        # hit_share's rays a receiver (a measure for tests and benches: no gather at their hits)
AUTO_K = ((0.15, 8), (0.5, 16))   # auto K: median pixel roughness < r -> K (a wider lobe needs more rays: the bowl's view1
                                  # GGX 0.1 block RMS 13.0 / 13.0 / 12.7 % at K 4 / 8 / 16, GGX 0.25 8.7 / 7.9 / 7.3 /
                                  # 7.1 % at K 4 / 8 / 16 / 32; K 4 left bright outliers on the knot's view2 GGX 0.1)


def auto_k(roughness: np.ndarray) -> int:
    """K (rays a pixel) for ``--self-reflect auto`` from the glossy pixels' median roughness (:data:`AUTO_K`)."""
    r = float(np.median(roughness)) if len(roughness) else 1.0
    for lim, k in AUTO_K:
        if r < lim:
            return k
    return AUTO_K[-1][1]


def parse_option(value: str) -> Optional[int]:
    """``--self-reflect``: None for auto, 0 for off, K ≥ 1 rays a pixel; ValueError otherwise."""
    v = str(value).strip().lower()
    if v == "auto":
        return None
    if v == "off":
        return 0
    k = int(v)          # ValueError for anything else
    if not 1 <= k <= 256:
        raise ValueError(f"{value!r}: K must be in [1, 256]")
    return k


def lattice(k: int, count: int, seed: int) -> np.ndarray:
    """(count, k, 2) points in [0,1)²: a k-point Fibonacci lattice, rotated (mod 1) by one random offset a row."""
    from ..config import sub_seed

    i = np.arange(k, dtype=np.float64)
    base = np.stack([(i + 0.5) / k, (i * 0.6180339887498949) % 1.0], 1)
    off = np.random.default_rng(sub_seed(seed, SEED_TAG)).random((count, 1, 2))
    return (base[None] + off) % 1.0


def lobe_samples(recv: Receivers, k: int, kind: str, masking: str, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Directions (P, S, 3) world and weights (P, S, 3) sampling each receiver's BRDF towards its eye with the
    points ``u`` (P, k, 2): S = k VNDF samples of the specular lobe (weight F·G/G1), then, when any receiver has a
    diffuse part, k cosine-weighted samples (weight π·f_d). A direction below the shading or the geometric plane
    weighs 0 (Eq. 9 takes nothing from there)."""
    from ..gather import brdf

    n = np.asarray(recv.normal, np.float64)
    ng = np.asarray(recv.geometric, np.float64)
    t, b = tangent_frame(n)
    v = np.asarray(recv.view, np.float64)
    wl = np.stack([np.einsum("pj,pj->p", v, t), np.einsum("pj,pj->p", v, b), np.maximum(np.einsum("pj,pj->p", v, n), 1e-4)], -1)
    wl /= np.linalg.norm(wl, axis=1, keepdims=True)
    base = np.asarray(recv.base_color, np.float64)[:, None]
    met = np.asarray(recv.metallic, np.float64)[:, None]
    rgh = np.asarray(recv.roughness, np.float64)[:, None]
    wo = np.broadcast_to(wl[:, None], u.shape[:2] + (3,))
    wi = brdf.sample_vndf(wo, brdf.ggx_alpha(rgh), u)
    dirs, wts = [wi], [brdf.spec_weight(kind, wi, wo, base, met, rgh, masking)]
    diff_w = brdf.diffuse_part(kind, np.array([0.0, 0.0, 1.0]), wl, np.array([0.0, 0.0, 1.0]), base[:, 0], met[:, 0],
                               rgh[:, 0])
    if np.any(diff_w > 0):
        r, phi = np.sqrt(u[..., 0]), 2 * np.pi * u[..., 1]
        wd = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1.0 - u[..., 0], 0.0))], -1)
        dirs.append(wd)
        wts.append(np.pi * brdf.diffuse_part(kind, wd, wo, np.array([0.0, 0.0, 1.0]), base, met, rgh))
    wi, w = np.concatenate(dirs, 1), np.concatenate(wts, 1)
    world = wi[..., :1] * t[:, None] + wi[..., 1:2] * b[:, None] + wi[..., 2:] * n[:, None]
    world /= np.maximum(np.linalg.norm(world, axis=-1, keepdims=True), 1e-30)
    below = (wi[..., 2] <= 0) | (np.einsum("psj,pj->ps", world, ng) <= 0)
    return world, np.where(below[..., None], 0.0, w)


class MeshCaster:
    """The object's triangles (world-space ``parts``, :func:`pipeline.relight.gbuffer.place_parts`) in Open3D's ray caster."""

    def __init__(self, parts: list[dict[str, Any]]) -> None:
        import open3d as o3d

        self.parts = parts
        verts, faces, self.part_of, self.face_of = [], [], [], []
        off = 0
        for i, p in enumerate(parts):
            v = np.asarray(p["positions"], np.float64).reshape(-1, 3)
            f = np.asarray(p["faces"], np.int64).reshape(-1, 3)
            verts.append(v)
            faces.append(f + off)
            self.part_of.append(np.full(len(f), i, np.int64))
            self.face_of.append(np.arange(len(f), dtype=np.int64))
            off += len(v)
        self.vertices = np.concatenate(verts) if verts else np.zeros((0, 3))
        self.faces = np.concatenate(faces) if faces else np.zeros((0, 3), np.int64)
        self.part_of = np.concatenate(self.part_of) if faces else np.zeros(0, np.int64)
        self.face_of = np.concatenate(self.face_of) if faces else np.zeros(0, np.int64)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(self.vertices.astype(np.float32)),
                                 o3d.core.Tensor(self.faces.astype(np.uint32)))
        lo, hi = self.vertices.min(0), self.vertices.max(0)
        self.radius = float(np.linalg.norm(hi - lo) / 2) if len(self.vertices) else 0.0

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
        """The first hit of each ray (R,): ``hit`` bool, ``t`` [m], ``tri`` (global triangle), ``uv`` (R, 2) the
        barycentrics of vertices 1 and 2."""
        import open3d as o3d

        rays = np.concatenate([origins, dirs], 1).astype(np.float32)
        ans = self.scene.cast_rays(o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy().astype(np.float64)
        tri = ans["primitive_ids"].numpy().astype(np.int64)
        hit = np.isfinite(t) & (tri >= 0) & (tri < len(self.faces))
        return {"hit": hit, "t": t, "tri": np.where(hit, tri, 0), "uv": ans["primitive_uvs"].numpy().astype(np.float64)}

    def receivers(self, points: np.ndarray, tri: np.ndarray, uv: np.ndarray, dirs: np.ndarray,
                  overrides: Optional[dict[str, Any]] = None) -> tuple[Receivers, np.ndarray]:
        """Secondary receivers at hit points (H, 3) on triangles ``tri`` (barycentrics ``uv``) met by rays of unit
        directions ``dirs`` (H, 3): normals and material of the mesh there (:func:`.surfels.surface_at`; ``overrides``
        base_color / metallic / roughness as relight's --albedo / --metallic / --roughness), both normals turned
        towards the ray (a sheet's other side), view −dir; and the surface's emission there (H, 3) float32."""
        from .surfels import surface_at

        H = len(points)
        out = {k: np.zeros((H, 3)) for k in ("normal", "geom_normal", "base_color", "emission")}
        out.update(metallic=np.zeros(H), roughness=np.zeros(H))
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], 1)
        for i, p in enumerate(self.parts):
            s = np.flatnonzero(self.part_of[tri] == i)
            if not len(s):
                continue
            f = np.asarray(p["faces"], np.int64).reshape(-1, 3)[self.face_of[tri[s]]]
            v = np.asarray(p["positions"], np.float64).reshape(-1, 3)
            fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
            ln = np.linalg.norm(fn, axis=1, keepdims=True)
            fn = np.where(ln > 0, fn / np.where(ln > 0, ln, 1.0), 0.0)
            at = surface_at(p, f, fn, bary[s])
            for key, val in at.items():
                out[key][s] = val
        for key in ("base_color", "metallic", "roughness"):
            if overrides and overrides.get(key) is not None:
                out[key][:] = overrides[key]
        flip = np.where(np.einsum("hj,hj->h", out["geom_normal"], dirs) > 0, -1.0, 1.0)[:, None]
        f32 = lambda a: np.ascontiguousarray(a, np.float32)  # noqa: E731
        return (Receivers(f32(points), f32(out["normal"] * flip), f32(-dirs), f32(out["base_color"]),
                          f32(np.clip(out["metallic"], 0, 1)), f32(np.clip(out["roughness"], 0, 1)),
                          f32(out["geom_normal"] * flip)), f32(out["emission"]))


@dataclasses.dataclass
class Plan:
    """The lobe rays of every glossy receiver, cast once: ``sees`` (P,) bool (some ray meets the object),
    ``dirs``/``weight`` (P, S, 3), ``hit``/``tri``/``t`` (P, S), ``uv`` (P, S, 2), ``k`` the rays a pixel, ``origins``
    (P, 3) [m]."""

    k: int
    sees: np.ndarray
    dirs: np.ndarray
    weight: np.ndarray
    hit: np.ndarray
    tri: np.ndarray
    t: np.ndarray
    uv: np.ndarray
    origins: np.ndarray


def plan(caster: MeshCaster, recv: Receivers, k: int, kind: str, masking: str, seed: int) -> Plan:
    """Cast ``k`` lobe rays (and k diffuse ones where a receiver has a diffuse part: :func:`lobe_samples`) from each
    receiver with roughness < :data:`MAX_ROUGHNESS` against the object; rays of weight 0 are not cast."""
    P = len(recv)
    u = lattice(k, P, seed)
    dirs, w = lobe_samples(recv, k, kind, masking, u)
    S = dirs.shape[1]
    ng = np.asarray(recv.geometric, np.float64)
    org = np.asarray(recv.position, np.float64) + OFFSET * max(caster.radius, 1e-30) * ng
    live = (np.asarray(recv.roughness) < MAX_ROUGHNESS)[:, None] & (w.max(2) > 0)
    hit = np.zeros((P, S), bool)
    tri = np.zeros((P, S), np.int64)
    t = np.full((P, S), np.inf)
    uv = np.zeros((P, S, 2))
    pi, si = np.nonzero(live)
    if len(pi):
        c = caster.cast(org[pi], dirs[pi, si])
        hit[pi, si], tri[pi, si], t[pi, si], uv[pi, si] = c["hit"], c["tri"], np.where(c["hit"], c["t"], np.inf), c["uv"]
    return Plan(k, hit.any(1), dirs, w, hit, tri, t, uv, org)


def ray_share(pl: Plan, idx: np.ndarray) -> np.ndarray:
    """(len(idx),) the BRDF-weighted share (the samples' weights, channel mean) of receivers ``idx``'s K lobe rays that
    meet the object."""
    w = pl.weight[idx].mean(2)
    return (w * pl.hit[idx]).sum(1) / np.maximum(w.sum(1), 1e-30)


def hit_share(caster: MeshCaster, recv: Receivers, kind: str, masking: str, seed: int, origins: np.ndarray,
              rays: Optional[int] = None) -> np.ndarray:
    """(P,) the share of each receiver's BRDF-weighted lobe (the samples' weights, channel mean) whose rays meet the
    object: ``rays`` (default :data:`COVER_RAYS`) lobe samples of their own (a lattice seeded apart from the K rays')."""
    n = int(rays or COVER_RAYS)
    P = len(recv)
    dirs, w = lobe_samples(recv, n, kind, masking, lattice(n, P, seed + 1))
    w = w.mean(2)
    live = (np.asarray(recv.roughness) < MAX_ROUGHNESS)[:, None] & (w > 0)
    hit = np.zeros(w.shape, bool)
    pi, si = np.nonzero(live)
    if len(pi):
        hit[pi, si] = caster.cast(origins[pi], dirs[pi, si])["hit"]
    return (w * hit).sum(1) / np.maximum(w.sum(1), 1e-30)


def secondary(pl: Plan, idx: np.ndarray, caster: MeshCaster, gatherer: Any, overrides: Optional[dict[str, Any]] = None,
              timings: Any = None) -> tuple[np.ndarray, dict[str, Any]]:
    """B (len(idx), 3) for receivers ``idx`` of the plan: Σ_hits w·L(q, −ω) / K with L gathered by ``gatherer``
    at secondary receivers on the hits (:meth:`MeshCaster.receivers`) plus the surface's emission there."""
    pi, si = np.nonzero(pl.hit[idx])
    out = np.zeros((len(idx), 3))
    if not len(pi):
        return out.astype(np.float32), {"secondary_receivers": 0}
    g = idx[pi]
    d = pl.dirs[g, si]
    q = pl.origins[g] + pl.t[g, si, None] * d
    rec, emit = caster.receivers(q, pl.tri[g, si], pl.uv[g, si], d, overrides)
    from ..runtime import Timings

    with (timings if timings is not None else Timings()).step("self_reflect_secondary"):
        L, st = gatherer.run(rec, None, None)
    L = np.where(np.isfinite(L), np.maximum(L, 0), 0).astype(np.float64) + emit
    np.add.at(out, pi, pl.weight[g, si] * L)
    st = dict(st)
    st["secondary_receivers"] = int(len(pi))
    return (out / pl.k).astype(np.float32), st


def secondary_params(params: Any) -> Any:
    """The secondary gather's parameters: micro-buffer :data:`SECONDARY_M`, at most :data:`SECONDARY_LOBE`² VNDF samples."""
    return dataclasses.replace(params, m=SECONDARY_M, lobe_samples=min(int(params.lobe_samples), SECONDARY_LOBE),
                               lobe_m=min(int(params.lobe_m), SECONDARY_LOBE_M))


def black_object(nodes: np.ndarray, first: int) -> np.ndarray:
    """A copy of the merged ``nodes`` with the object's (from ``first`` on) black: A's node array."""
    out = np.array(nodes, copy=True)
    out["color"][first:] = 0.0
    return out


def cover_nodes(nodes: np.ndarray, first: int) -> np.ndarray:
    """A copy of the merged ``nodes`` coloured for :func:`coverage`: the room (0, 1, 0), the object (1, 1, 0)."""
    out = np.array(nodes, copy=True)
    out["color"][:first] = (0.0, 1.0, 0.0)
    out["color"][first:] = (1.0, 1.0, 0.0)
    return out


def coverage(recv: Receivers, g_cover: Any, pixels: Optional[np.ndarray], shape: Optional[tuple[int, int]]) -> np.ndarray:
    """(P,) the share of each receiver's BRDF-weighted hemisphere (white base colour) that the object's surfels cover
    in its micro-buffer: the gather over :func:`cover_nodes` (no emitters), red ÷ green."""
    white = dataclasses.replace(recv, base_color=np.ones_like(recv.base_color))
    r, _ = g_cover.run(white, pixels, shape)
    r = np.asarray(r, np.float64)
    return np.clip(r[:, 0] / np.maximum(r[:, 1], 1e-30), 0.0, 1.0)




def shade(recv: Receivers, idx: np.ndarray, pixels: Optional[np.ndarray], shape: Optional[tuple[int, int]], pl: Plan,
          caster: MeshCaster, g: Any, g_black: Any, g_second: Any, overrides: Optional[dict[str, Any]] = None,
          timings: Any = None, g_cover: Any = None, g_room: Any = None) -> tuple[np.ndarray, list[dict[str, Any]], int]:
    """Radiance (len(idx), 3) of receivers ``idx`` (their viewport ``pixels`` in ``shape``, or None): the ordinary
    gather ``g`` where the plan's rays miss the object, A (``g_black``) + B (:func:`secondary`, ``g_second``) where
    some meets it, A corrected by (c − h)·E when ``g_cover`` (:func:`cover_nodes`) and ``g_room`` (the room alone)
    are given (module doc). Returns the radiance, the primary gathers' stats and the number of secondary receivers."""
    from ..runtime import Timings

    idx = np.asarray(idx, np.int64)
    sel = pl.sees[idx]
    rad = np.zeros((len(idx), 3), np.float32)
    runs = []
    seeing = recv.take(idx[sel]) if sel.any() else None
    for gat, s in ((g, ~sel), (g_black, sel)):
        if s.any():
            r, st = gat.run(seeing if s is sel else recv.take(idx[s]), None if pixels is None else pixels[s], shape,
                            timings=timings)
            rad[s] = r
            runs.append(st)
    n2 = 0
    if sel.any() and g_cover is not None and g_room is not None:
        ps = None if pixels is None else pixels[sel]
        with (timings if timings is not None else Timings()).step("self_reflect_cover"):
            e, _ = g_room.run(seeing, ps, shape)
            c = coverage(seeing, g_cover, ps, shape)
        d = (c - ray_share(pl, idx[sel]))[:, None] * np.asarray(e, np.float64)
        rad[sel] = np.maximum(rad[sel] + d, 0.0).astype(np.float32)
    if sel.any():
        b, st2 = secondary(pl, idx[sel], caster, g_second, overrides, timings)
        rad[sel] += b
        n2 = st2["secondary_receivers"]
    return rad, runs, n2


def decide(option: str, brdf: str, directional: bool, self_vis: Optional[float], roughness: np.ndarray,
           threshold: float) -> tuple[int, str]:
    """(K, the rule in words) for ``--self-reflect`` (auto|off|K): auto is on for a glossy object with directional
    bounces whose measured self-visibility is ≥ ``threshold`` (surfels.GLOSSY_SELF_VIS), K = :func:`auto_k`."""
    k = parse_option(option)
    glossy = np.asarray(roughness)[np.asarray(roughness) < MAX_ROUGHNESS]
    if k == 0:
        return 0, "off (--self-reflect off)"
    if brdf == "lambert":
        return 0, "off (Lambert: no lobe to sample)"
    if k is not None:
        return k, f"on (--self-reflect {k}): {k} lobe rays a pixel with roughness < {MAX_ROUGHNESS}"
    if not directional:
        return 0, "off (auto: no directional bounces — the object's lobes are wide)"
    if self_vis is None:
        return 0, "off (auto: self-visibility not measured; --bounce-surfels was given)"
    if self_vis < threshold:
        return 0, f"off (auto: self-visibility {self_vis:.3f} < {threshold})"
    if not len(glossy):
        return 0, f"off (auto: no pixel with roughness < {MAX_ROUGHNESS})"
    k = auto_k(glossy)
    return k, (f"on (auto: glossy, self-visibility {self_vis:.3f} >= {threshold}; K = {k} lobe rays a pixel, median "
               f"roughness {float(np.median(glossy)):.3g})")
