"""Mitsuba 3 side of make-scene: scene description → Mitsuba dict / XML, and deterministic
radiance estimates through ray batches that we build ourselves.

Every estimate goes through ``integrator.sample(scene, sampler, ray)`` with an ``independent``
sampler seeded from a 32-bit hash of (seed, purpose, batch), never ``mi.render`` (whose film
accumulation order varies between runs). Each input ray is repeated ``spp`` times inside one
batch; the per-sample radiances come back to numpy and are reduced in a fixed order (float64),
giving the mean and the **variance of the mean** (sample variance / spp) per ray. Results do not
depend on the number of threads (every lane is independent).

**Adaptive sampling** (``target`` > 0): every ray gets more samples, in rounds that double its
sample count (spp, 2·spp, 4·spp, … up to ``cap``), until its luminance estimate has had a
relative standard error ≤ ``target`` after two consecutive rounds (the second round's samples
are independent of the first decision: stopping on one estimate selects rays whose variance
happened to be underestimated — measured on the small atrium, 4.3 % of such points had |z| > 3
against an independent re-bake, 0.36 % of the points that ran to the cap); rounds are merged exactly
(Chan's pairwise mean/variance update, float64). A round traces the rays in a **fixed layout**
(chunks of ``lanes // spp_round`` consecutive rays over *all* rays, the sampler seeded from
(seed, purpose, round, chunk start); rays no longer sampled are masked off, chunks without one are
skipped), so a ray's samples depend on its index, the round and the seed only — never on which
other rays are still being sampled. The report gives the share of rays that stopped at the cap.

Camera convention used for the views and the photo (OpenCV): camera x right, y down, z forward;
pixel (i, j) has its centre at (i + 0.5, j + 0.5); ``K = [[f,0,W/2],[0,f,H/2],[0,0,1]]`` with
``f = (H/2)/tan(fov_y/2)`` (``fov_deg`` is the **vertical** field of view); image row 0 is the top.
"""

from __future__ import annotations

import os
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..runtime import get_logger, progress

log = get_logger("make-scene")

VARIANT = "llvm_ad_rgb"
_MI = None


def mitsuba(threads: int = 0):
    """Import Mitsuba and select ``llvm_ad_rgb``; one clear line when LLVM is missing or broken."""
    global _MI
    if _MI is not None:
        return _MI
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError as e:  # pragma: no cover - dependency missing
        raise InputError(None, f"make-scene needs the 'mitsuba' package (pip install mitsuba): {e}") from None
    try:
        mi.set_variant(VARIANT)
        if threads > 0:
            dr.set_thread_count(threads)
        x = mi.Float(np.arange(4, dtype=np.float32)) * 2.0
        np.asarray(x)
    except Exception as e:
        raise InputError(None, f"Mitsuba variant {VARIANT} does not run ({type(e).__name__}: {e}); "
                         "install Debian's libllvm19 (apt-get install libllvm19)") from None
    _MI = mi
    return mi


def llvm_info() -> dict[str, Any]:
    """Mitsuba/Dr.Jit versions and the LLVM the JIT found (for reports and ``pcrelight info``)."""
    mi = mitsuba()
    import drjit as dr

    info = {"mitsuba": mi.__version__, "drjit": dr.__version__, "variant": VARIANT,
            "threads": int(dr.thread_count())}
    try:
        info["llvm"] = ".".join(map(str, dr.detail.llvm_version()))
    except Exception:
        pass
    return info


def seed32(*parts: Any) -> int:
    """A 32-bit seed from any tuple (crc32 of its repr): independent streams per purpose/batch."""
    return zlib.crc32(repr(parts).encode()) & 0xFFFFFFFF


# --------------------------------------------------------------------------- scene description → Mitsuba
def _bsdf_diffuse(albedo) -> dict:
    return {"type": "twosided", "material": {"type": "diffuse",
                                             "reflectance": {"type": "rgb", "value": [float(a) for a in albedo]}}}


def material_bsdf(mat: dict) -> dict:
    """The reference materials of scene.json as Mitsuba BSDFs: Lambert = ``diffuse``; GGX =
    ``roughconductor`` (distribution ggx, α = roughness², material "none": F = 1, separable Smith
    masking G1·G1, visible-normal sampling)."""
    if mat["type"] == "lambert":
        a = mat["albedo"]
        a = [a] * 3 if np.isscalar(a) else list(a)
        return {"type": "diffuse", "reflectance": {"type": "rgb", "value": [float(x) for x in a]}}
    if mat["type"] == "ggx":
        return {"type": "roughconductor", "distribution": "ggx", "alpha": float(mat["alpha"]),
                "material": "none", "sample_visible": True}
    raise ValueError(f"unknown material type {mat['type']!r}")


def emitter_weight(m: dict) -> float:
    """Light-selection weight of an emitting mesh: the cube root of its power π·A·mean(L) (the
    tiny, very bright sun gets about 60 % of the next-event samples without starving the
    skylight). Changes only the variance, never the expectation."""
    return float(np.cbrt(np.pi * m["area"] * float(np.mean(m["emission"]))))


def room_dict(root: Path, scene: dict, integrator: dict) -> dict:
    """Mitsuba dict of the room (all meshes of scene.json, files relative to ``root``)."""
    d: dict[str, Any] = {"type": "scene", "integrator": dict(integrator)}
    for i, m in enumerate(scene["meshes"]):
        shape = {"type": "ply", "filename": str(root / m["file"]), "face_normals": True,
                 "bsdf": _bsdf_diffuse(m["albedo"])}
        if any(e > 0 for e in m["emission"]):
            shape["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": [float(e) for e in m["emission"]]},
                                "sampling_weight": emitter_weight(m)}
        d[f"m{i:03d}_{m['name']}"] = shape
    return d


def object_shape(root: Path, obj: dict, bsdf: dict | None) -> dict:
    """The object (its PLY, smooth vertex normals) placed by ``to_world``."""
    mi = mitsuba()
    shape = {"type": "ply", "filename": str(root / obj["ply"]),
             "to_world": mi.ScalarTransform4f(np.asarray(obj["to_world"], dtype=np.float64).tolist())}
    if bsdf is not None:
        shape["bsdf"] = bsdf
    return shape


def _load_ordered(d: dict):
    """Load a scene dict with its shapes in the dict's order. Mitsuba orders the shapes (hence
    the emitters, hence which emitter a light sample picks) differently from load to load when
    it instantiates them itself; shapes instantiated one by one, in order, keep that order, so
    the same seed gives the same bytes."""
    mi = mitsuba()
    d2 = {k: (mi.load_dict(v, parallel=False) if isinstance(v, dict) and k != "integrator" else v) for k, v in d.items()}
    return mi.load_dict(d2, parallel=False)


def load_room(root: Path, scene: dict, integrator: dict, obj: dict | None = None, bsdf: dict | None = None):
    d = room_dict(root, scene, integrator)
    if obj is not None:
        d["object"] = object_shape(root, obj, bsdf)
    return _load_ordered(d)


def load_object_only(root: Path, obj: dict):
    return _load_ordered({"type": "scene", "object": object_shape(root, obj, None)})


def _fmt(v) -> str:
    return ", ".join(f"{float(x):.9g}" for x in v)


def scene_xml(scene: dict, integrator: dict, view: str, spp: int) -> str:
    """The room + the default object (Lambert 0.8) as a Mitsuba 3 XML file rendering ``view``
    (``mitsuba scene.xml`` renders it as it is; paths relative to the XML's folder)."""
    v = scene["views"][view]
    w, h = v["size"]
    lines = ['<?xml version="1.0" encoding="utf-8"?>',
             "<!-- pcrelight make-scene: the Sponza-style atrium (metres, +Y up, linear Rec.709 RGB). -->",
             '<scene version="3.0.0">',
             '  <integrator type="path">',
             f'    <integer name="max_depth" value="{int(integrator["max_depth"])}"/>',
             f'    <integer name="rr_depth" value="{int(integrator["rr_depth"])}"/>',
             "  </integrator>",
             '  <sensor type="perspective">',
             f'    <float name="fov" value="{float(v["fov_deg"]):.9g}"/>',
             '    <string name="fov_axis" value="y"/>',
             '    <transform name="to_world">',
             f'      <lookat origin="{_fmt(v["eye"])}" target="{_fmt(v["target"])}" up="{_fmt(v["up"])}"/>',
             "    </transform>",
             f'    <sampler type="independent"><integer name="sample_count" value="{int(spp)}"/></sampler>',
             f'    <film type="hdrfilm"><integer name="width" value="{int(w)}"/><integer name="height" value="{int(h)}"/>'
             '<rfilter type="box"/></film>',
             "  </sensor>"]
    for m in scene["meshes"]:
        lines += [f'  <shape type="ply" id="{m["name"]}">',
                  f'    <string name="filename" value="{m["file"]}"/>',
                  '    <boolean name="face_normals" value="true"/>',
                  f'    <bsdf type="twosided"><bsdf type="diffuse"><rgb name="reflectance" value="{_fmt(m["albedo"])}"/></bsdf></bsdf>']
        if any(e > 0 for e in m["emission"]):
            lines.append(f'    <emitter type="area"><rgb name="radiance" value="{_fmt(m["emission"])}"/>'
                         f'<float name="sampling_weight" value="{emitter_weight(m):.9g}"/></emitter>')
        lines.append("  </shape>")
    o = scene["object"]
    mat = np.asarray(o["to_world"], dtype=np.float64)
    lines += ['  <shape type="ply" id="object">',
              f'    <string name="filename" value="{o["ply"]}"/>',
              f'    <transform name="to_world"><matrix value="{" ".join(f"{x:.9g}" for x in mat.reshape(-1))}"/></transform>',
              '    <bsdf type="diffuse"><rgb name="reflectance" value="0.8, 0.8, 0.8"/></bsdf>',
              "  </shape>", "</scene>", ""]
    return "\n".join(lines)


# --------------------------------------------------------------------------- estimators
class Tracer:
    """Deterministic Monte-Carlo radiance through Mitsuba's integrator, on our own ray batches."""

    def __init__(self, seed: int, lanes: int = 1 << 20, threads: int = 0):
        self.mi = mitsuba(threads)
        self.seed = int(seed)
        self.lanes = int(lanes)
        self.sampler = self.mi.load_dict({"type": "independent"})
        self.paths = 0

    def _seed_sampler(self, n: int, *tag) -> None:
        import drjit as dr

        self.sampler.seed(dr.opaque(self.mi.UInt32, seed32(self.seed, *tag)), n)

    def _ray(self, o: np.ndarray, d: np.ndarray):
        mi = self.mi
        return mi.Ray3f(mi.Point3f(np.ascontiguousarray(o.T, dtype=np.float32)),
                        mi.Vector3f(np.ascontiguousarray(d.T, dtype=np.float32)))

    @staticmethod
    def _moments(a: np.ndarray, spp: int):
        """(n·spp, 3) float32 samples → per ray: mean (n,3), sum of squared deviations M2 (n,3),
        luminance mean (n,) and its M2 (n,), float64, reduced in a fixed order."""
        from ..io import luminance

        a = np.nan_to_num(a.astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0).reshape(-1, spp, 3)
        lum = luminance(a.reshape(-1, 3).astype(np.float32)).astype(np.float64).reshape(-1, spp)
        mean, lmean = a.mean(axis=1), lum.mean(axis=1)
        return mean, ((a - mean[:, None]) ** 2).sum(axis=1), lmean, ((lum - lmean[:, None]) ** 2).sum(axis=1)

    def _batches(self, n: int, spp: int):
        chunk = max(1, self.lanes // spp)
        for c0 in progress(range(0, n, chunk), total=-(-n // chunk), desc=f"rays ({spp} spp)"):
            yield c0, min(n, c0 + chunk)

    def _estimate(self, fn, o: np.ndarray, d: np.ndarray, spp: int, tag: str, target: float = 0.0, cap: int = 0):
        """Monte-Carlo estimate per ray (o, d) of ``fn(origins, directions, lane_mask or None)`` →
        per-sample RGB (m, 3): (mean, variance of the mean (n,3), variance of the luminance mean
        (n,), samples per ray (n,) int64). ``target`` > 0: adaptive rounds (module docstring)
        until the relative standard error of the luminance is ≤ target after two consecutive
        rounds, or ``cap`` samples."""
        n = len(o)
        cnt = np.zeros(n, np.int64)
        mean, m2, lmean, lm2 = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n), np.zeros(n)
        rnd, spp_r = 0, int(spp)
        active = np.ones(n, bool)
        hits = np.zeros(n, np.int64)      # consecutive rounds that met the target
        while n and active.any() and spp_r > 0:
            for c0, c1 in self._batches(n, spp_r):
                act = active[c0:c1]
                if not act.any():
                    continue
                oo = np.repeat(o[c0:c1], spp_r, axis=0)
                dd = np.repeat(d[c0:c1], spp_r, axis=0)
                # round 0 keeps the seeds of the plain (non-adaptive) estimate
                self._seed_sampler(len(oo), tag, c0) if rnd == 0 else self._seed_sampler(len(oo), tag, "round", rnd, c0)
                lane = None if act.all() else np.repeat(act, spp_r)
                mb, m2b, lb, l2b = self._moments(fn(oo, dd, lane), spp_r)
                self.paths += int(len(oo) if lane is None else lane.sum())
                i = np.flatnonzero(act) + c0
                mb, m2b, lb, l2b = mb[act], m2b[act], lb[act], l2b[act]
                na, nb = cnt[i].astype(np.float64), float(spp_r)
                tot = na + nb
                dm, dl = mb - mean[i], lb - lmean[i]
                mean[i] += dm * (nb / tot)[:, None]
                lmean[i] += dl * nb / tot
                m2[i] += m2b + dm ** 2 * (na * nb / tot)[:, None]
                lm2[i] += l2b + dl ** 2 * na * nb / tot
                cnt[i] += spp_r
            if target <= 0:
                break
            lse = np.sqrt(np.divide(lm2, cnt * (cnt - 1.0), out=np.zeros(n), where=cnt > 1))
            rel = np.divide(lse, lmean, out=np.full(n, np.inf), where=lmean > 0)
            hits = np.where(rel <= target, hits + 1, 0)
            active = (hits < 2) & (cnt < cap)
            rnd += 1
            spp_r = int(min(cnt[active].max(), cap - cnt[active].max())) if active.any() else 0
        den = np.maximum(cnt * (cnt - 1.0), 1.0)
        return mean, m2 / den[:, None], lm2 / den, cnt

    def radiance(self, scene, o: np.ndarray, d: np.ndarray, spp: int, tag: str, target: float = 0.0, cap: int = 0,
                 counts: bool = False):
        """Radiance arriving at ``o`` from direction −``d`` (rays o + t·d): (mean, var_mean,
        lum_var_mean[, samples per ray]); ``target``/``cap``: adaptive sampling (:meth:`_estimate`)."""
        integ = scene.integrator()

        def fn(oo, dd, lane):
            act = True if lane is None else self.mi.Bool(lane)
            L, _, _ = integ.sample(scene, self.sampler, self._ray(oo, dd), None, act)
            return np.asarray(L).T

        r = self._estimate(fn, o, d, spp, tag, target, cap)
        return r if counts else r[:3]

    def gather(self, room, obj_scene, bsdf_dict: dict, o: np.ndarray, d: np.ndarray, spp: int, tag: str,
               target: float = 0.0, cap: int = 0, counts: bool = False):
        """PBGI's quantity at the object point hit by each ray: ∫ f(ωi, ωo) L_room(x, ωi) cosθi dωi,
        L_room = radiance of the room **without** the object. Per sample: next-event estimation
        of the emitters from x (shadow rays in the room, so the object never occludes itself)
        plus one BSDF-sampled ray whose radiance is path-traced in the room; the emission met
        first by that ray and the light sample are combined by the power heuristic (as
        Mitsuba's ``path`` integrator does). Rays that miss the object give 0. Returns as
        :meth:`radiance`."""
        import drjit as dr

        mi = self.mi
        integ = room.integrator()
        bsdf = mi.load_dict(bsdf_dict)
        ctx = mi.BSDFContext()

        def mis(a, b):
            a2 = a * a
            return dr.select(a > 0, a2 / dr.fma(b, b, a2), 0.0)

        def fn(oo, dd, lane):
            si = obj_scene.ray_intersect(self._ray(oo, dd))
            active = si.is_valid() if lane is None else si.is_valid() & mi.Bool(lane)
            # next-event estimation in the room
            ds, em_w = room.sample_emitter_direction(si, self.sampler.next_2d(), True, active)
            active_em = active & (ds.pdf != 0.0)
            f_em, pdf_em = bsdf.eval_pdf(ctx, si, si.to_local(ds.d), active_em)
            nee = dr.select(active_em, f_em * em_w * dr.select(ds.delta, 1.0, mis(ds.pdf, pdf_em)), 0.0)
            # BSDF sample, then the room's radiance along it
            bs, w = bsdf.sample(ctx, si, self.sampler.next_1d(), self.sampler.next_2d(), active)
            active_b = active & (bs.pdf > 0)
            ray2 = si.spawn_ray(si.to_world(bs.wo))
            si2 = room.ray_intersect(ray2, active_b)
            L, _, _ = integ.sample(room, self.sampler, ray2, None, active_b)
            em = si2.emitter(room, active_b)
            le = dr.select(active_b & (em != None), em.eval(si2, active_b), 0.0)  # noqa: E711
            ds2 = mi.DirectionSample3f(room, si=si2, ref=si)
            pdf_light = room.pdf_emitter_direction(si, ds2, active_b)
            w_b = mis(bs.pdf, pdf_light)
            val = nee + dr.select(active_b, w * (mi.Color3f(L) - le + w_b * le), 0.0)
            return np.asarray(val).T

        r = self._estimate(fn, o, d, spp, tag, target, cap)
        return r if counts else r[:3]

    def first_hits(self, scene, o: np.ndarray, d: np.ndarray):
        """(t (inf on a miss), geometric normal (N,3), valid) of each ray's first hit."""
        outs = []
        for c0 in range(0, len(o), self.lanes):
            c1 = min(len(o), c0 + self.lanes)
            si = scene.ray_intersect(self._ray(o[c0:c1], d[c0:c1]))
            valid = np.asarray(si.is_valid()).astype(bool)
            t = np.where(valid, np.asarray(si.t, dtype=np.float64), np.inf)
            ng = np.asarray(si.n).T.astype(np.float64)
            outs.append((t, ng, valid))
        return tuple(np.concatenate(x) for x in zip(*outs))


def object_mask(tracer: Tracer, obj_scene, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """1 where the pixel-centre ray hits the object (the alpha of every reference)."""
    t, _, valid = tracer.first_hits(obj_scene, o, d)
    return valid


def env_threads() -> int:
    try:
        return int(os.environ.get("PCRELIGHT_MI_THREADS", "0"))
    except ValueError:
        return 0
