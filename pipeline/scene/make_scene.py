"""make-scene: the Sponza-style ground truth, rendered by Mitsuba 3 (DESIGN "Ground truth").

Writes into one folder: ``scene.json`` + ``meshes/*.ply`` + ``scene.xml`` (the atrium), the HDR
cloud ``cloud_gt.ply`` (outgoing radiance at points uniform by area, true normals, ``quality`` =
standard error of the luminance estimate), the LDR cloud ``cloud_ldr.ply`` (Eq. 1 with exposure
e, 8-bit sRGB), the HDR photos ``photo.exr`` and ``photo_<rule>.exr`` (one per camera rule of
``photos``, each at its own scale k; cameras, k and the cloud points each sees only in
``truth/truth.npz`` (the first photo) and ``truth/truth_<rule>.npz``), the default
objects ``object.*`` / ``object2.*``, the HDR panorama ``pano.exr`` (equirectangular, from a point beside the
object, at its own scale k; ``truth/truth_pano.npz``, scene.json "panorama"; ``--only panorama`` renders it
alone into an existing folder), ``truth/truth.npz`` and the references
``truth/{gather,full}_<view>_<material>[_var].exr``, PNG previews and ``report.json``.

The room is **closed**: every ray from inside hits a surface, so the cloud holds all the light an
object inside receives (as a scanner's cloud does; PBGI has no other light).

Units: metres, +Y up; radiance in linear Rec.709 RGB (arbitrary absolute scale). Cameras: see
:mod:`pipeline.camera` (OpenCV convention, vertical ``fov_deg``, pixel centres).
"""

from __future__ import annotations

import itertools
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import io
from ..errors import ConfigError, InputError
from ..config import StageConfig, load_toml, resolve
from ..runtime import Timings, get_logger
from . import geometry as geo
from .. import camera
from ..color import T_L
from . import mitsuba_render as smi

log = get_logger("make-scene")

PRESETS = ("tiny", "small", "full", "lamps", "bowl")
ROOMS = ("atrium", "lamps")
LAMP_COS = 0.25          # a lamp point counts as shown when it faces the eye by at least this cosine (not grazing)
LAMP_EYE_HEIGHTS = (1.7, 2.5)   # [m] handheld first, a raised camera (tripod, monopod) only where none at 1.7 m adds a lamp point
LAMPS_RULE = (f"shows the most lamp points the photos before it do not (facing it by cos ≥ {LAMP_COS:g}, unoccluded, in "
              f"its frame): eyes on a 1 m grid at {LAMP_EYE_HEIGHTS[0]:g} m (at {LAMP_EYE_HEIGHTS[1]:g} m where none there "
              "adds one), aimed at the mean direction of the new points or at one of them")
PHOTO_RULES = {
    "bright": "looks at the brightest 2 m region (a voxel holding ≥ 0.2 % of the points), from 7 m along x",
    "lights": "sees the brightest lit patch (the sun patch) and the lamp nearest to it, from across the room at 1.5 m (swung up to 80° aside where a wall is in the way)",
    "sun": "stands in the sun's beam at 1.5 m and looks up the light shaft at the sun (atrium; elsewhere as 'lights')",
    "lamps": LAMPS_RULE, "lamps2": LAMPS_RULE + " (the next one)", "lamps3": LAMPS_RULE + " (the one after)",
}
PRESET_DIR = Path(__file__).resolve().parents[2] / "configs" / "scene"
MATERIALS: dict[str, dict] = {
    "lambert": {"type": "lambert", "albedo": 0.8},
    **{f"ggx{r}": {"type": "ggx", "roughness": r, "alpha": round(r * r, 6), "fresnel": "none (F = 1)",
                     "masking": "smith-separable",
                     "mitsuba": "roughconductor(distribution=ggx, alpha=roughness^2, material=none, sample_visible=true)"}
       for r in (0.1, 0.25, 0.5, 1.0)},
}
PANO_CLEARANCE = 0.25   # [m] the default panorama centre's distance outside the object's bounding sphere
PANO_FREE = 0.3         # [m] free space the default panorama centre needs around it
PANO_RULE = (f"at the object's centre height, {PANO_CLEARANCE:g} m outside its bounding sphere, on the first of 8 "
             f"horizontal directions (view1's side first, then turning by 45°) with {PANO_FREE:g} m free around it")
PANO_LAMPS_HEIGHT = 1.7  # [m] the lamps rule's tripod height
PANO_LAMPS_RULE = (f"on a 1 m grid at {PANO_LAMPS_HEIGHT:g} m ({PANO_FREE:g} m free around it, {PANO_CLEARANCE:g} m outside "
                   "the object's bounding sphere): the centre that shows the most lamps, then the most lamp points (facing it "
                   f"by cos ≥ {LAMP_COS:g}, line of sight traced against the room's meshes), then the nearest the object")
PANO_RULES = {"object": PANO_RULE, "lamps": PANO_LAMPS_RULE}
PANO_SEED_TAG = 17      # the panorama's scale k: default_rng(sub_seed(seed, 17)), independent of the rest
OVEREXPOSED_RULE = f"LDR cloud point with luminance(decoded linear colour) > {T_L:g} or any 8-bit channel = 255"


@dataclass
class MakeSceneConfig(StageConfig):
    """Options of make-scene (presets in ``configs/scene/<preset>.toml``)."""

    name: str = field(default="custom", metadata={"help": "preset name recorded in scene.json"})
    room: str = field(default="atrium", metadata={"help": "the room: the Sponza-style atrium, or a box room lit by small very bright lamps", "choices": ROOMS})
    points: int = field(default=200_000, metadata={"help": "points in the HDR/LDR clouds"})
    cloud_spp: int = field(default=32, metadata={"help": "paths per cloud point in the first round"})
    cloud_target: float = field(default=0.05, metadata={"help": "adaptive sampling: relative standard error of a cloud point's luminance at which it stops (0: cloud_spp paths, no more)"})
    cloud_max_spp: int = field(default=4096, metadata={"help": "adaptive sampling: most paths per cloud point"})
    precise_points: int = field(default=0, metadata={"help": "also re-bake this many of the cloud's points (chosen at random) with independent paths to precise_target: truth/cloud_precise.npz (0: none)"})
    precise_target: float = field(default=0.05, metadata={"help": "relative standard error the precise subset is sampled to"})
    precise_max_spp: int = field(default=16384, metadata={"help": "most paths per point of the precise subset"})
    photo_size: tuple[int, ...] = field(default=(384, 256), metadata={"help": "HDR photo width,height [pixels]"})
    photo_spp: int = field(default=32, metadata={"help": "paths per photo pixel"})
    photo_fov: float = field(default=70.0, metadata={"help": "photo vertical field of view [degrees]"})
    photo_noise: float = field(default=0.0, metadata={"help": "photo sensor noise: relative Gaussian sigma per pixel"})
    photos: tuple[str, ...] = field(default=("bright", "lights", "sun"), metadata={"help": "photo cameras by placement rule (" + "; ".join(f"{k}: {v}" for k, v in PHOTO_RULES.items()) + "); the first is photo.exr, the others photo_<rule>.exr"})
    panorama: bool = field(default=True, metadata={"help": "also render the HDR panorama pano.exr (equirectangular, linear Rec.709; truth/truth_pano.npz)"})
    pano_size: tuple[int, ...] = field(default=(1024, 512), metadata={"help": "panorama width,height [pixels] (width = 2 × height: 360° × 180°)"})
    pano_spp: int = field(default=64, metadata={"help": "paths per panorama pixel (pixel-centre rays)"})
    pano_at: tuple[float, ...] = field(default=(), metadata={"help": "panorama centre x,y,z [m] (empty: by --pano-rule)"})
    pano_rule: str = field(default="object", metadata={"help": "where the panorama stands without --pano-at: object = "
                           + PANO_RULE + "; lamps = " + PANO_LAMPS_RULE, "choices": tuple(PANO_RULES)})
    ref_size: tuple[int, ...] = field(default=(128, 128), metadata={"help": "reference (and relight default) width,height [pixels]"})
    ref_spp: int = field(default=1024, metadata={"help": "paths per object pixel of the references (first round)"})
    ref_target: float = field(default=0.03, metadata={"help": "adaptive sampling: relative standard error of an object pixel's luminance at which it stops (0: ref_spp paths)"})
    ref_max_spp: int = field(default=16384, metadata={"help": "adaptive sampling: most paths per object pixel of the references"})
    ref_bg_spp: int = field(default=32, metadata={"help": "paths per background pixel of the references"})
    references: bool = field(default=True, metadata={"help": "render the gather_/full_ references"})
    photo_ref_spp: int = field(default=0, metadata={"help": "paths a pixel of the composite's truth: the first photo's view "
                                                            "with the Lambert object and without (truth/photo_{with,without}.exr; 0 = none)"})
    materials: tuple[str, ...] = field(default=tuple(MATERIALS), metadata={"help": "reference materials to render (of: " + ", ".join(MATERIALS) + ")"})
    saturate_share: float = field(default=0.05, metadata={"help": "share of LDR points saturated by the exposure e"})
    ldr_noise: float = field(default=0.0, metadata={"help": "LDR noise before 8-bit quantisation [sigma in code values]"})
    default_object: str = field(default="knot", metadata={"help": "built-in object written as object.* (the other one is object2.*)", "choices": ("knot", "sphere", "bowl")})
    object_center: tuple[float, ...] = field(default=(1.5, 1.3, -0.5), metadata={"help": "object bounding-sphere centre [m]"})
    object_radius: float = field(default=1.0, metadata={"help": "object bounding-sphere radius [m]"})
    sky_radiance: float = field(default=2.0, metadata={"help": "skylight panel radiance (mean)"})
    sun_radiance: float = field(default=1.5e5, metadata={"help": "sun sphere radiance"})
    lamp_radiance: float = field(default=40.0, metadata={"help": "gallery lamp radiance"})
    max_depth: int = field(default=-1, metadata={"help": "Mitsuba path max_depth (-1: unbounded, Russian roulette)"})
    rr_depth: int = field(default=5, metadata={"help": "Mitsuba path rr_depth"})
    lanes: int = field(default=1 << 20, metadata={"help": "rays per Mitsuba batch (memory vs. speed)"})
    threads: int = field(default=0, metadata={"help": "Dr.Jit threads (0: all cores); results do not depend on it"})

    @classmethod
    def presets(cls) -> dict[str, dict[str, Any]]:
        """``configs/scene/<preset>.toml`` [make-scene] for each of :data:`PRESETS`."""
        return {name: load_toml(PRESET_DIR / f"{name}.toml").get("make-scene", {}) for name in PRESETS}

    def check(self) -> None:
        self._require(self.points >= 100, "points", "must be ≥ 100")
        for n in ("cloud_spp", "photo_spp", "ref_spp", "ref_bg_spp"):
            self._require(getattr(self, n) >= 2, n, "must be ≥ 2 (the variance needs two samples)")
        for n in ("cloud_target", "ref_target"):
            self._require(0 <= getattr(self, n) < 1, n, "must be in [0, 1)")
        self._require(self.cloud_max_spp >= self.cloud_spp, "cloud_max_spp", "must be ≥ cloud_spp")
        self._require(0 <= self.precise_points <= self.points, "precise_points", "must be in [0, points]")
        self._require(0 < self.precise_target < 1, "precise_target", "must be in (0, 1)")
        self._require(self.precise_max_spp >= self.cloud_spp, "precise_max_spp", "must be ≥ cloud_spp")
        self._require(self.ref_max_spp >= self.ref_spp, "ref_max_spp", "must be ≥ ref_spp")
        for n in ("photo_size", "ref_size"):
            v = getattr(self, n)
            self._require(len(v) == 2 and min(v) >= 4, n, "must be width,height ≥ 4")
        self._require(0 < self.photo_fov < 170, "photo_fov", "must be in (0, 170)")
        self._require(self.photo_noise >= 0, "photo_noise", "must be ≥ 0")
        self._require(0 < self.saturate_share < 1, "saturate_share", "must be in (0, 1)")
        self._require(self.ldr_noise >= 0, "ldr_noise", "must be ≥ 0")
        self._require(len(self.object_center) == 3, "object_center", "must be x,y,z")
        self._require(0.1 <= self.object_radius <= 2.5, "object_radius", "must be in [0.1, 2.5] m")
        for n in ("sky_radiance", "sun_radiance", "lamp_radiance"):
            self._require(getattr(self, n) >= 0, n, "must be ≥ 0")
        self._require(self.max_depth == -1 or self.max_depth >= 2, "max_depth", "must be -1 or ≥ 2")
        self._require(self.rr_depth >= 1, "rr_depth", "must be ≥ 1")
        self._require(self.lanes >= 1024, "lanes", "must be ≥ 1024")
        self._require(self.threads >= 0, "threads", "must be ≥ 0")
        self._require(self.default_object in ("knot", "sphere", "bowl"), "default_object", "must be knot, sphere or bowl")
        self._require(len(self.materials) > 0 and all(m in MATERIALS for m in self.materials), "materials",
                      "must name materials of: " + ", ".join(MATERIALS))
        self._require(self.room in ROOMS, "room", "must be one of " + ", ".join(ROOMS))
        self._require(len(self.pano_size) == 2 and self.pano_size[1] >= 4 and self.pano_size[0] == 2 * self.pano_size[1],
                      "pano_size", "must be width,height with width = 2 × height ≥ 8")
        self._require(self.pano_spp >= 2, "pano_spp", "must be ≥ 2 (the variance needs two samples)")
        self._require(len(self.pano_at) in (0, 3), "pano_at", "must be x,y,z or empty")
        self._require(self.pano_rule in PANO_RULES, "pano_rule", "must be one of " + ", ".join(PANO_RULES))
        self._require(len(self.photos) > 0 and all(p in PHOTO_RULES for p in self.photos) and len(set(self.photos)) == len(self.photos),
                      "photos", "must name distinct rules of: " + ", ".join(PHOTO_RULES))
        c = np.asarray(self.object_center)
        r = self.object_radius
        if self.room == "atrium":
            inside = (geo.X0 + 0.5 < c[0] - r and c[0] + r < geo.X1 - 0.5 and abs(c[2]) + r < geo.Z_FRONT - 0.3
                      and 0.05 < c[1] - r and c[1] + r < 5.0)
            self._require(bool(inside), "object_center", "must keep the object's sphere inside the courtyard (|z|+r < 3.4, y−r > 0.05, y+r < 5)")
        else:
            lo, hi = geo.room_box(self.room)
            inside = bool(np.all(c - r > lo + 0.05) and np.all(c + r < hi - 0.5))
            self._require(inside, "object_center", f"must keep the object's sphere inside the room {lo.tolist()}–{hi.tolist()} (0.5 m below the ceiling)")


def apply_preset(preset: str, params: dict[str, Any]) -> MakeSceneConfig:
    """Config of a preset (:func:`pipeline.config.resolve`): defaults < ``configs/scene/<preset>.toml``
    [make-scene] < the TOML given with --config < options given on the command line (``params``: click's
    parameters, ``None`` for options not given)."""
    names = set(MakeSceneConfig.field_names())
    return resolve(MakeSceneConfig, params.get("config_file"), "make-scene",  # type: ignore[return-value]
                   {k: v for k, v in params.items() if k in names}, preset=preset)


# --------------------------------------------------------------------------- helpers
def _to_world(center, radius, local_center, local_radius) -> np.ndarray:
    """4×4 row-major: local → world, mapping the local bounding sphere onto (center, radius)."""
    s = radius / local_radius
    M = np.eye(4)
    M[:3, :3] *= s
    M[:3, 3] = np.asarray(center, float) - s * np.asarray(local_center, float)
    return M


def _bounding_sphere(V: np.ndarray) -> tuple[np.ndarray, float]:
    c = 0.5 * (V.min(axis=0) + V.max(axis=0))
    return c, float(np.linalg.norm(V - c, axis=1).max())


def _default_object(kind: str):
    return {"knot": geo.object_knot, "sphere": geo.object_sphere, "bowl": geo.object_bowl}[kind]()


def _write_object(out: Path, stem: str, V, F, N, cfg: MakeSceneConfig, label: str) -> dict:
    for ext in ("glb", "obj", "ply"):
        io.write_mesh(out / f"{stem}.{ext}", V, F, N, base_color=(0.8, 0.8, 0.8), metallic=0.0, roughness=1.0)
    c, r = _bounding_sphere(np.asarray(V, np.float64))
    M = _to_world(cfg.object_center, cfg.object_radius, c, r)
    return {"name": label, "file": f"{stem}.glb", "obj": f"{stem}.obj", "ply": f"{stem}.ply",
            "to_world": M.tolist(), "center": [float(x) for x in cfg.object_center],
            "radius": float(cfg.object_radius), "triangles": int(len(F)),
            "material": "glTF metallic-roughness: baseColor 0.8, metallic 0, roughness 1 (Lambert 0.8)"}


def make_views(center, radius, size) -> dict:
    """view1: the object's bounding sphere fills the viewport; view2: the whole object visible
    (2.2× farther), from another side. Vertical fov 40°."""
    c = np.asarray(center, float)
    fov = 40.0
    d1 = radius / np.sin(np.radians(fov / 2))
    views = {}
    for name, direction, dist in (("view1", (-0.80, 0.30, 0.45), d1), ("view2", (0.85, 0.35, -0.25), 2.2 * d1)):
        dv = np.asarray(direction) / np.linalg.norm(direction)
        views[name] = {"eye": (c + dist * dv).tolist(), "target": c.tolist(), "up": [0.0, 1.0, 0.0],
                       "fov_deg": fov, "size": [int(size[0]), int(size[1])]}
    return views


def view_camera(v: dict):
    M = camera.look_at(v["eye"], v["target"], v["up"])
    K = camera.intrinsics(v["fov_deg"], v["size"])
    return M, K


# --------------------------------------------------------------------------- the cloud bake
def sample_cloud_points(meshes: list[geo.Mesh], n: int, rng: np.random.Generator):
    """Candidate points uniform by area over all meshes: (points, normals, mesh index)."""
    tris = np.concatenate([m.triangles for m in meshes])
    owner = np.concatenate([np.full(len(m.triangles), i) for i, m in enumerate(meshes)])
    p, nrm, f = geo.sample_surface(tris, n, rng)
    return p, nrm, owner[f]


def check_first_hits(tracer: smi.Tracer, room, p: np.ndarray, n: np.ndarray, eps: float) -> np.ndarray:
    """True for points whose bake ray (from p + eps·n along −n) first hits the point itself
    (distance eps, normal n), and whose outward ray (from p + eps·n along n) first meets a front
    face (the point is not inside a solid or under a coincident face)."""
    o = p + eps * n
    t, ng, valid = tracer.first_hits(room, np.concatenate([o, o]), np.concatenate([-n, n]))
    m = len(p)
    t_in, n_in, v_in = t[:m], ng[:m], valid[:m]
    t_out, n_out, v_out = t[m:], ng[m:], valid[m:]
    ok_in = v_in & (np.abs(t_in - eps) < 0.25 * eps) & (np.sum(n_in * n, axis=1) > 0.99)
    ok_out = v_out & (np.sum(n_out * n, axis=1) < 0) & (t_out > 2 * eps)
    return ok_in & ok_out


def bake_cloud(tracer: smi.Tracer, room, meshes, n_points: int, spp: int, rng: np.random.Generator,
               eps: float = 2e-3, tag: str = "cloud", target: float = 0.0, cap: int = 0) -> dict:
    """Sample ``n_points`` valid points and bake their outgoing radiance (rays arriving along the
    normal from eps above: the radiance returned is the point's outgoing radiance, Lambertian);
    ``target``/``cap``: adaptive sampling (:mod:`pipeline.scene.mitsuba_render`); ``spp`` in the result
    is the number of paths each point got."""
    pts, nrm, own, rejected = [], [], [], 0
    need = n_points
    rounds = 0
    while need > 0:
        rounds += 1
        if rounds > 20:
            raise RuntimeError(f"could not find {n_points} valid surface points (rejected {rejected})")
        m = int(need * 1.1) + 64
        p, nn, ow = sample_cloud_points(meshes, m, rng)
        ok = check_first_hits(tracer, room, p, nn, eps)
        rejected += int(np.count_nonzero(~ok))
        idx = np.flatnonzero(ok)[:need]
        pts.append(p[idx]); nrm.append(nn[idx]); own.append(ow[idx])
        need -= len(idx)
    p, nn, ow = np.concatenate(pts), np.concatenate(nrm), np.concatenate(own)
    mean, var, lvar, cnt = tracer.radiance(room, p + eps * nn, -nn, spp, tag, target, cap, counts=True)
    return {"points": p, "normals": nn, "mesh": ow, "mean": mean, "var": var, "lum_var": lvar, "spp": cnt,
            "rejected": rejected}


def precision_summary(lum: np.ndarray, lum_var: np.ndarray, spp: np.ndarray, cap: int) -> dict[str, float]:
    """The reached precision of Monte-Carlo estimates: relative standard error of the luminance
    (√var / mean; ∞ where the mean is 0) — median, p90, max — and paths per estimate (mean,
    max) with the share that stopped at ``cap`` (0: no cap)."""
    lum, se = np.asarray(lum, np.float64), np.sqrt(np.asarray(lum_var, np.float64))
    rel = np.divide(se, lum, out=np.full(len(lum), np.inf), where=lum > 0)
    if len(rel) == 0:
        return {"n": 0}
    return {"n": int(len(rel)), "rel_se_median": float(np.median(rel)), "rel_se_p90": float(np.percentile(rel, 90)),
            "rel_se_max": float(rel.max()), "spp_mean": float(np.mean(spp)), "spp_max": int(np.max(spp)),
            "share_at_cap": float(np.mean(spp >= cap)) if cap > 0 else 0.0}


def ldr_from_hdr(colors: np.ndarray, share: float, noise: float, rng: np.random.Generator):
    """Eq. 1 with e chosen so ``share`` of the points have a channel ≥ 1: returns (e, linear LDR
    colours (decoded from 8-bit sRGB codes), codes uint8)."""
    mx = colors.max(axis=1)
    e = float(1.0 / np.quantile(mx.astype(np.float64), 1.0 - share))
    lin = np.clip(e * colors.astype(np.float64), 0.0, 1.0)
    enc = io.srgb_encode(lin).astype(np.float64) * 255.0
    if noise > 0:
        enc = enc + rng.normal(0.0, noise, enc.shape)
    codes = np.clip(np.round(enc), 0, 255).astype(np.uint8)
    return e, io.srgb_decode(codes.astype(np.float32) / 255.0), codes


def photo_camera_place(meshes, b: dict, lum: np.ndarray, cfg: MakeSceneConfig) -> tuple[np.ndarray, np.ndarray]:
    """The photo looks at the brightest region: among non-emitting points below the roof, the
    2 m voxel (with at least 0.2 % of the points) of highest mean luminance; the camera stands
    in the courtyard at 1.7 m, on the other side of the centre line, 7 m away along x."""
    skip = np.array([any(x > 0 for x in m.emission) or m.name in ("light_shaft", "roof_beams") for m in meshes])
    cand = np.flatnonzero(~skip[b["mesh"]] & (b["points"][:, 1] < geo.Y_ROOF - 0.1))
    pts = b["points"][cand]
    key = np.floor(pts / 2.0).astype(np.int64)
    uniq, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    mean_l = np.bincount(inv, weights=lum[cand].astype(np.float64)) / cnt
    ok = cnt >= max(5, int(0.002 * len(b["points"])))
    best = int(np.argmax(np.where(ok, mean_l, -1.0)))
    target = pts[inv == best].mean(axis=0)
    sx = 1.0 if target[0] < 0 else -1.0
    lo, hi = geo.room_box(cfg.room)
    eye = np.array([np.clip(target[0] + 7.0 * sx, lo[0] + 3.0, hi[0] - 3.0), 1.7, (-1.0 if target[2] > 0 else 1.0) * 2.0])
    c = np.asarray(cfg.object_center)
    if np.linalg.norm(eye - c) < cfg.object_radius + 0.5:   # never inside the object's sphere
        eye[0] += sx * (2 * cfg.object_radius + 1.0)
    return target, eye


def _emitting(meshes) -> np.ndarray:
    return np.array([any(x > 0 for x in m.emission) for m in meshes])


def _sees(tracer: smi.Tracer, room, eye: np.ndarray, pts: np.ndarray, slack: np.ndarray | float) -> np.ndarray:
    """True where the ray from ``eye`` towards each point first hits within ``slack`` [m] of it."""
    d = pts - eye
    dist = np.linalg.norm(d, axis=1)
    t, _, valid = tracer.first_hits(room, np.repeat(eye[None], len(pts), axis=0), d / np.maximum(dist, 1e-12)[:, None])
    return valid & (t >= dist - slack)


def lights_camera_place(tracer: smi.Tracer, room, meshes, b: dict, lum: np.ndarray, lamp_centers, lamp_radius: float,
                        cfg: MakeSceneConfig) -> tuple[np.ndarray, np.ndarray, dict] | None:
    """The "lights" photo: the brightest lit patch P (non-emitting points within 1.5 m of the
    brightest one, among the 0.1 % brightest) and a lamp L, both in view and unoccluded from an
    eye at 1.5 m height across the room: P + D·h, h the horizontal direction of P − L turned by
    0, ±20, ±40, ±60, ±80° (in that order: straight across first, then swung aside where a wall
    is in the way), D = 6, 5, 4, 7, 8, 3 m; lamps by distance to P. Returns (target = (P + L)/2,
    eye, info) or None when no candidate works."""
    skip = _emitting(meshes) | np.array([m.name in ("light_shaft", "roof_beams") for m in meshes])
    cand = np.flatnonzero(~skip[b["mesh"]])
    top = cand[np.argsort(-lum[cand], kind="stable")[:max(5, int(0.001 * len(lum)))]]
    pts = b["points"][top]
    patch = pts[np.linalg.norm(pts - pts[0], axis=1) < 1.5].mean(axis=0)
    c, r = np.asarray(cfg.object_center), cfg.object_radius
    lo, hi = geo.room_box(cfg.room)
    half_fov = np.radians(cfg.photo_fov) / 2 * min(1.0, cfg.photo_size[0] / cfg.photo_size[1])
    lamps = np.asarray(lamp_centers, float)
    for li in np.argsort(np.linalg.norm(lamps - patch, axis=1), kind="stable"):
        L = lamps[li]
        h0 = patch - L
        h0[1] = 0.0
        h0 = h0 / np.linalg.norm(h0) if np.linalg.norm(h0) > 1e-6 else np.array([1.0, 0, 0])
        for turn, dist in itertools.product((0, 20, -20, 40, -40, 60, -60, 80, -80), (6.0, 5.0, 4.0, 7.0, 8.0, 3.0)):
            a = np.radians(turn)
            h = np.array([h0[0] * np.cos(a) - h0[2] * np.sin(a), 0.0, h0[0] * np.sin(a) + h0[2] * np.cos(a)])
            eye = patch + dist * h
            eye[1] = 1.5
            if np.any(eye < lo + 0.3) or np.any(eye > hi - 0.3) or np.linalg.norm(eye - c) < r + 0.5:
                continue
            target = 0.5 * (patch + L)
            f = (target - eye) / np.linalg.norm(target - eye)
            ang = [np.arccos(np.clip(f @ (x - eye) / np.linalg.norm(x - eye), -1, 1)) for x in (patch, L)]
            if max(ang) > 0.8 * half_fov:
                continue
            if _sees(tracer, room, eye, np.stack([patch, L]), np.array([0.05, lamp_radius + 0.05])).all():
                return target, eye, {"patch": patch.tolist(), "lamp": L.tolist(), "turn_deg": turn}
    return None


def sun_camera_place(tracer: smi.Tracer, room, sun: dict, cfg: MakeSceneConfig) -> tuple[np.ndarray, np.ndarray, dict] | None:
    """The "sun" photo: the eye on the beam's axis (sun centre − t·shaft direction) at 1.5 m, a
    little off-axis (0.5 m along −x) so the sun sits off-centre above the lit floor; None if the sun's
    centre is not seen from there or the eye is in the object's sphere."""
    lean = np.asarray(geo.SHAFT_LEAN, float)
    lean /= np.linalg.norm(lean)
    sc = np.asarray(sun["center"], float)
    eye = sc - (sc[1] - 1.5) / lean[1] * lean + np.array([-0.5, 0.0, 0.0])
    if np.linalg.norm(eye - np.asarray(cfg.object_center)) < cfg.object_radius + 0.5:
        return None
    if not _sees(tracer, room, eye, sc[None], sun["radius"] + 0.05)[0]:
        return None
    return sc, eye, {"sun": sc.tolist()}


def lamp_points(points: np.ndarray, lamps: dict | None) -> np.ndarray:
    """(N,) bool: the cloud points on a lamp — within its radius + 1 cm of one of scene.json's ``lamps`` centres
    (``{"centers": …, "radius": …}``; None: no lamp). The same test in a full run and in ``--only panorama``."""
    pts = np.asarray(points, np.float64)
    if not lamps:
        return np.zeros(len(pts), bool)
    c = np.asarray(lamps["centers"], np.float64)
    d = np.linalg.norm(pts[:, None, :] - c[None], axis=2)
    return d.min(axis=1) <= float(lamps["radius"]) + 0.01


def shown_points(tracer: smi.Tracer, room, points: np.ndarray, normals: np.ndarray, eye, among: np.ndarray) -> np.ndarray:
    """(N,) bool: the points of ``among`` a camera at ``eye`` shows well — facing it by cos ≥ :data:`LAMP_COS`
    (not at grazing incidence, where the pipeline's surfel test drops them) and first hit by the ray from it
    (:func:`seen_points`: line of sight traced against the room's meshes)."""
    eye = np.asarray(eye, np.float64)
    d = eye - points
    cos = np.sum(d * normals, axis=1) / np.maximum(np.linalg.norm(d, axis=1), 1e-12)
    return seen_points(tracer, room, points, normals, eye, among & (cos >= LAMP_COS))


def _grid_eyes(cfg: MakeSceneConfig, y: float, clearance: float) -> np.ndarray:
    """Eyes on a 1 m grid of the room's floor plan (cell centres, ≥ 0.5 m from its walls) at height ``y`` [m],
    ``clearance`` [m] or more outside the object's bounding sphere; x fastest, then z."""
    lo, hi = geo.room_box(cfg.room)
    xs = np.arange(np.floor(lo[0]) + 0.5, hi[0] - 0.49, 1.0)
    zs = np.arange(np.floor(lo[2]) + 0.5, hi[2] - 0.49, 1.0)
    E = np.array([(x, y, z) for z in zs for x in xs], np.float64)
    c = np.asarray(cfg.object_center, np.float64)
    return E[np.linalg.norm(E - c, axis=1) >= cfg.object_radius + clearance]


def lamps_camera_place(tracer: smi.Tracer, room, points: np.ndarray, normals: np.ndarray, lamp: np.ndarray,
                       shown_before: np.ndarray, cfg: MakeSceneConfig) -> tuple[np.ndarray, np.ndarray, dict] | None:
    """The "lamps" photos (:data:`LAMPS_RULE`): of the eyes of :func:`_grid_eyes` at 1.7 m (2.5 m where none at
    1.7 m shows a lamp point not ``shown_before``), the one whose photo — ``cfg.photo_fov``, ``cfg.photo_size``,
    aimed at the mean direction of its new lamp points or at one of them — frames the most new lamp points (3 px
    inside), then the most lamp points; ties: grid order. Returns (target, eye, info) or None when no eye shows a
    new lamp point."""
    K = camera.intrinsics(cfg.photo_fov, cfg.photo_size)
    w, h = cfg.photo_size
    lp = np.flatnonzero(lamp)
    P, N = np.asarray(points, np.float64)[lp], np.asarray(normals, np.float64)[lp]
    before = np.asarray(shown_before, bool)[lp]
    everywhere = np.ones(len(lp), bool)
    for y in LAMP_EYE_HEIGHTS:
        best, best_key = None, (0, 0)
        for eye in _grid_eyes(cfg, y, 0.5):
            shown = shown_points(tracer, room, P, N, eye, everywhere)
            new = shown & ~before
            if not new.any():
                continue
            d = P - eye
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            aims = [d[new].mean(axis=0)] + list(d[new])
            for f in aims:
                if np.linalg.norm(f) < 1e-6 or abs(f[1]) / np.linalg.norm(f) > 0.95:
                    continue
                M = camera.look_at(eye, eye + f, (0.0, 1.0, 0.0))
                u, v, _, ok = camera.project_points("pinhole", P, (w, h), M, K=K)
                ok &= (u >= 3) & (u <= w - 3) & (v >= 3) & (v <= h - 3)
                key = (int(np.sum(ok & new)), int(np.sum(ok & shown)))
                if key > best_key:
                    best_key, best = key, (eye, f / np.linalg.norm(f), ok & shown)
        if best is not None:
            eye, f, framed = best
            dist = float(np.mean(np.linalg.norm(P[framed] - eye, axis=1)))
            return eye + dist * f, eye, {"lamp_points_new": best_key[0], "lamp_points_framed": best_key[1],
                                         "eye_height": float(y)}
    return None


def pano_lamps_place(tracer: smi.Tracer, room, points: np.ndarray, normals: np.ndarray, lamps: dict | None,
                     cfg: MakeSceneConfig) -> tuple[np.ndarray, dict]:
    """The panorama centre by :data:`PANO_LAMPS_RULE`: of the grid eyes at :data:`PANO_LAMPS_HEIGHT` with
    :data:`PANO_FREE` m free around them, the one that shows the most lamps (≥ 1 of their points), then the most
    lamp points, then the nearest the object's centre; (centre, info)."""
    lamp = lamp_points(points, lamps)
    P, N = np.asarray(points, np.float64)[lamp], np.asarray(normals, np.float64)[lamp]
    if not len(P):
        raise InputError(None, "--pano-rule lamps: the room has no lamp points")
    C = np.asarray(lamps["centers"], np.float64)
    which = np.argmin(np.linalg.norm(P[:, None] - C[None], axis=2), axis=1)
    c = np.asarray(cfg.object_center, np.float64)
    best, best_key = None, None
    for eye in _grid_eyes(cfg, PANO_LAMPS_HEIGHT, PANO_CLEARANCE):
        shown = shown_points(tracer, room, P, N, eye, np.ones(len(P), bool))
        key = (len(np.unique(which[shown])), int(shown.sum()), -float(np.linalg.norm(eye - c)))
        if best_key is not None and key <= best_key:
            continue
        free = free_space(tracer, room, eye)
        if free >= PANO_FREE:
            best, best_key = (eye, free), key
    if best is None:
        raise InputError(None, f"no panorama centre by the rule ({PANO_LAMPS_RULE}): give --pano-at x,y,z")
    eye, free = best
    return eye, {"rule": PANO_LAMPS_RULE, "free_m": free, "lamps_shown": best_key[0], "lamp_points_shown": best_key[1],
                 "lamp_points": int(len(P))}


def lamp_pixels(centre, lamps: dict | None, width: int) -> float:
    """The smallest angular diameter of the lamps seen from ``centre``, in pixels of a ``width``-wide equirect
    (2π / width radians a pixel); inf without lamps."""
    if not lamps:
        return float("inf")
    d = np.linalg.norm(np.asarray(lamps["centers"], np.float64) - np.asarray(centre, np.float64), axis=1)
    ang = 2.0 * np.arcsin(np.minimum(1.0, float(lamps["radius"]) / d))
    return float(ang.min() / (2.0 * np.pi / width))


def light_stats(scene: dict, b: dict, lum: np.ndarray, meshes, center) -> dict[str, dict[str, float]]:
    """The small emitters (lamps, sun) seen from the object's centre: share of the sphere of
    directions they cover, Σ 2π(1 − √(1 − r²/d²)) / 4π, and their radiance (luminance) over the
    median luminance of the non-emitting cloud points (the walls)."""
    from ..io import luminance

    walls = float(np.median(lum[~_emitting(meshes)[b["mesh"]]]))
    out = {}
    for key in ("lamps", "sun"):
        if key not in scene:
            continue
        e = scene[key]
        cs = np.asarray(e["centers"] if "centers" in e else [e["center"]], float)
        dd = np.linalg.norm(cs - np.asarray(center, float), axis=1)
        r = float(e["radius"])
        share = float(np.sum(1.0 - np.sqrt(1.0 - np.minimum(1.0, (r / dd) ** 2))) / 2.0)
        L = float(luminance(np.asarray([e["radiance"]], np.float32))[0])
        out[key] = {"count": int(len(cs)), "solid_angle_share": share, "radiance_lum": L,
                    "over_wall_median": L / max(walls, 1e-30)}
    return out


def visible_points(tracer: smi.Tracer, room, points: np.ndarray, normals: np.ndarray, M: np.ndarray, K: np.ndarray,
                   size, eye: np.ndarray) -> np.ndarray:
    """Cloud points a photo sees: inside its frame, facing it, and first hit by the ray from its eye."""
    pc = points @ M[:3, :3].T + M[:3, 3]
    z = pc[:, 2]
    uv = (pc[:, :2] / np.maximum(z, 1e-9)[:, None]) * np.diag(K)[:2] + K[:2, 2]
    inframe = (z > 1e-3) & (uv[:, 0] >= 0) & (uv[:, 0] < size[0]) & (uv[:, 1] >= 0) & (uv[:, 1] < size[1])
    return seen_points(tracer, room, points, normals, eye, inframe)


def seen_points(tracer: smi.Tracer, room, points: np.ndarray, normals: np.ndarray, eye: np.ndarray,
                among: np.ndarray | None = None) -> np.ndarray:
    """Cloud points (of ``among``, default all) facing ``eye`` and first hit by the ray from it (within 1 cm + 0.1 %
    of the distance)."""
    facing = np.sum((eye - points) * normals, axis=1) > 0
    vis = np.zeros(len(points), bool)
    idx = np.flatnonzero(facing if among is None else among & facing)
    if len(idx):
        dist = np.linalg.norm(points[idx] - eye, axis=1)
        vis[idx] = _sees(tracer, room, eye, points[idx], 0.01 + 1e-3 * dist)
    return vis


def photo_file(i: int, name: str) -> str:
    """The first photo is ``photo.exr`` (the pipeline's input), the others ``photo_<name>.exr``."""
    return "photo.exr" if i == 0 else f"photo_{name}.exr"


# --------------------------------------------------------------------------- the HDR panorama
PANO_FILE = "pano.exr"
PANO_TRUTH = "truth/truth_pano.npz"
PANO_CONVENTION = ("camera.MODELS['equirect'] on OpenCV camera axes (camera.equirect_directions: column 0 at longitude −π, "
                   "the centre column along the camera's +z, row 0 at the zenith −y; pixel-centre rays); "
                   "world_to_camera = camera.look_at(centre, centre + (0, 0, 1), (0, 1, 0)): the centre column looks "
                   "along world +Z, columns to its right towards −X, row 0 at world +Y")


def pano_world_to_camera(centre) -> np.ndarray:
    """The panorama's world→camera 4×4 (OpenCV axes): camera +z = world +Z, camera −y (the zenith) = world +Y."""
    c = np.asarray(centre, np.float64)
    return camera.look_at(c, c + np.array([0.0, 0.0, 1.0]), (0.0, 1.0, 0.0))


def free_space(tracer: smi.Tracer, room, p: np.ndarray) -> float:
    """Distance [m] from ``p`` to the nearest surface met along 42 directions (icosphere vertices); 0 when a
    ray escapes (``p`` outside the closed room) or most rays meet back faces (``p`` inside a solid)."""
    V, _ = geo.icosphere(1)
    t, ng, valid = tracer.first_hits(room, np.repeat(np.asarray(p, np.float64)[None], len(V), axis=0), V)
    if not valid.all() or np.mean(np.sum(ng * V, axis=1) > 0) > 0.5:
        return 0.0
    return float(t.min())


def pano_centre_place(tracer: smi.Tracer, room, center, radius: float, towards) -> tuple[np.ndarray, dict]:
    """The default panorama centre (:data:`PANO_RULE`): at the object's centre height, ``radius`` +
    :data:`PANO_CLEARANCE` from its centre, along the horizontal direction to ``towards`` (view1's eye) turned
    by 0, 45, …, 315° until the point has :data:`PANO_FREE` m free around it; (centre, info)."""
    c = np.asarray(center, np.float64)
    h0 = np.asarray(towards, np.float64) - c
    h0[1] = 0.0
    h0 = h0 / np.linalg.norm(h0) if np.linalg.norm(h0) > 1e-9 else np.array([1.0, 0.0, 0.0])
    d = radius + PANO_CLEARANCE
    for turn in range(0, 360, 45):
        a = np.radians(turn)
        h = np.array([h0[0] * np.cos(a) - h0[2] * np.sin(a), 0.0, h0[0] * np.sin(a) + h0[2] * np.cos(a)])
        p = c + d * h
        free = free_space(tracer, room, p)
        if free >= PANO_FREE:
            return p, {"rule": PANO_RULE, "turn_deg": turn, "free_m": free}
    raise InputError(None, f"no panorama centre by the rule ({PANO_RULE}) around the object at {c.tolist()}: give --pano-at x,y,z")


def render_panorama(tracer: smi.Tracer, room, centre, size, spp: int, seed: int, e: float, overexposed: np.ndarray,
                    points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, dict, np.ndarray]:
    """The HDR panorama at ``centre`` [m]: every pixel-centre ray of camera.MODELS['equirect'] traced by Mitsuba
    (:meth:`scene_mitsuba.Tracer.radiance`, tag "pano", ``spp`` paths a pixel), times its own unknown scale k =
    10^U(−1, 1) (the stream ``default_rng(sub_seed(seed, 17))``, independent of make-scene's other draws, so a
    panorama rendered alone into an existing folder is the one a full run writes). Returns (image (H, W, 3)
    float32 linear Rec.709, the scene.json entry, the cloud points it sees (facing the centre, unoccluded))."""
    from ..config import sub_seed

    w, h = (int(x) for x in size)
    c = np.asarray(centre, np.float64)
    M = pano_world_to_camera(c)
    eye, dirs = camera.world_rays("equirect", (w, h), M)
    d = dirs.reshape(-1, 3)
    pm, _, _ = tracer.radiance(room, np.repeat(eye[None], len(d), axis=0), d, spp, "pano")
    k = float(10.0 ** np.random.default_rng(sub_seed(seed, PANO_SEED_TAG)).uniform(-1.0, 1.0))
    img = (k * pm).reshape(h, w, 3).astype(np.float32)
    peak = float(np.max(img))
    vis = seen_points(tracer, room, points, normals, c)
    over = np.asarray(overexposed).astype(bool)
    info = {"file": PANO_FILE, "model": "equirect", "centre": c.tolist(), "world_to_camera": M.tolist(),
            "size": [w, h], "spp": int(spp), "scale_k": k, "alpha_true": e / k, "truth": PANO_TRUTH,
            "convention": PANO_CONVENTION, "pixel_type": "half" if peak < 65504.0 else "float",
            "peak_radiance_lum": float(io.luminance(img.reshape(-1, 3)).max()) / k,
            "visible_points": int(vis.sum()), "visible_overexposed": int((vis & over).sum())}
    return img, info, vis


def write_panorama(out: Path, img: np.ndarray, info: dict, vis: np.ndarray, e: float, overexposed: np.ndarray,
                   preview: bool) -> None:
    """pano.exr (half floats when its peak fits, else float32), truth/truth_pano.npz (schema
    pcrelight.truth/1: k, e, α, the camera with ``photo_model`` equirect and no K) and previews/pano.png."""
    io.write_image(out / PANO_FILE, img, half=info["pixel_type"] == "half")
    w, h = info["size"]
    io.write_npz(out / PANO_TRUTH, "pcrelight.truth/1", k=np.float64(info["scale_k"]), e=np.float64(e),
                 alpha_true=np.float64(info["alpha_true"]), photo_model=np.asarray("equirect"),
                 photo_world_to_camera=np.asarray(info["world_to_camera"], np.float64),
                 photo_size=np.asarray([w, h], np.int32), photo_eye=np.asarray(info["centre"], np.float64),
                 overexposed=np.asarray(overexposed, np.uint8), photo_name=np.asarray("pano"),
                 photo_visible=vis.astype(np.uint8))
    if preview:
        io.write_preview(out / "previews" / "pano.png", img)


def log_panorama(info: dict, secs: float) -> None:
    log.info("%s: %dx%d equirect at %s (%s), %d spp, scale k = %.5g (alpha_true %.5g), %s pixels, peak luminance %.4g; "
             "sees %d cloud points (%d overexposed); %.1f s", info["file"], *info["size"],
             np.round(info["centre"], 3).tolist(), info.get("rule", "given"), info["spp"], info["scale_k"],
             info["alpha_true"], info["pixel_type"], info["peak_radiance_lum"], info["visible_points"],
             info["visible_overexposed"], secs)


def run_panorama(out_dir, cfg: MakeSceneConfig, preview: bool | str | Path = True) -> dict:
    """``make-scene --only panorama``: render only the panorama into an existing make-scene folder, from its
    scene.json (the room's meshes, the object's centre and radius, view1), truth/truth.npz (e, the overexposed
    mask) and cloud_gt.ply (the points it sees); writes pano.exr, truth/truth_pano.npz, previews/pano.png and
    scene.json's "panorama" entry — the bytes a full run with the same options writes."""
    cfg.check()
    if not cfg.panorama:
        raise ConfigError("--only panorama with --no-panorama: nothing to do")
    out = Path(out_dir)
    t0 = time.perf_counter()
    scene = io.read_json(io.must_exist(out / "scene.json"))
    tr = io.read_npz(out / "truth" / "truth.npz", "pcrelight.truth/1")
    gt = io.read_cloud(out / "cloud_gt.ply")
    if len(gt) != len(tr["overexposed"]):
        raise InputError(out / "cloud_gt.ply", f"{len(gt)} points, truth/truth.npz's overexposed mask has {len(tr['overexposed'])}")
    if int(scene.get("seed", cfg.seed)) != cfg.seed:
        log.warning("--seed %d, but %s was made with seed %s: the panorama's k and paths follow --seed", cfg.seed,
                    out / "scene.json", scene.get("seed"))
    smi.mitsuba(cfg.threads)
    tracer = smi.Tracer(cfg.seed, lanes=cfg.lanes, threads=cfg.threads)
    room = smi.load_room(out, scene, scene["integrator"])
    obj = scene["object"]
    log.info("%s: %d meshes, object at %s (radius %g m); %d cloud points, e = %.6g", out / "scene.json",
             len(scene["meshes"]), obj["center"], obj["radius"], len(gt), float(tr["e"]))
    img, info, vis = _panorama(tracer, room, cfg, obj["center"], obj["radius"], scene["views"]["view1"]["eye"],
                               float(tr["e"]), tr["overexposed"], gt.points, gt.normals, scene.get("lamps"))
    write_panorama(out, img, info, vis, float(tr["e"]), tr["overexposed"], bool(preview))
    scene["panorama"] = info
    io.write_json(out / "scene.json", scene)
    if isinstance(preview, (str, Path)):
        with io.atomic_path(preview) as tmp:
            shutil.copyfile(out / "previews" / "pano.png", tmp)
    log_panorama(info, time.perf_counter() - t0)
    return info


def _panorama(tracer, room, cfg: MakeSceneConfig, center, radius, towards, e, overexposed, points, normals,
              lamps: dict | None = None):
    """Place (``cfg.pano_at``, else by ``cfg.pano_rule``: :func:`pano_centre_place` or :func:`pano_lamps_place`) and
    render the panorama (both paths of make-scene). ``lamps``: scene.json's "lamps" entry (the lamp points it shows
    and their size in pixels are logged and recorded)."""
    points, normals = np.asarray(points, np.float64), np.asarray(normals, np.float64)
    if cfg.pano_at:
        centre, place = np.asarray(cfg.pano_at, np.float64), {"rule": "given (--pano-at)"}
        if free_space(tracer, room, centre) <= 0:
            raise ConfigError(f"--pano-at {','.join(f'{x:g}' for x in centre)} is not inside the room's free space")
    elif cfg.pano_rule == "lamps":
        centre, place = pano_lamps_place(tracer, room, points, normals, lamps, cfg)
    else:
        centre, place = pano_centre_place(tracer, room, center, radius, towards)
    if cfg.pano_rule == "lamps" or cfg.pano_at and lamps:
        lamp = lamp_points(points, lamps)
        shown = shown_points(tracer, room, points, normals, centre, lamp)
        place = {**place, "lamp_points_shown": int(shown.sum()), "lamp_points": int(lamp.sum()),
                 "lamp_min_pixels": lamp_pixels(centre, lamps, int(cfg.pano_size[0]))}
        log.info("panorama at %s: shows %d of the %d lamp points (facing it by cos ≥ %g); the farthest lamp is %.2f "
                 "pixels across at %d × %d", np.round(centre, 3).tolist(), place["lamp_points_shown"], place["lamp_points"],
                 LAMP_COS, place["lamp_min_pixels"], *cfg.pano_size)
        if place["lamp_min_pixels"] < 2.0:
            log.warning("panorama: a lamp is %.2f pixels across (< 2): its pixel-centre rays may miss it; a wider "
                        "--pano-size shows it", place["lamp_min_pixels"])
    img, info, vis = render_panorama(tracer, room, centre, cfg.pano_size, cfg.pano_spp, cfg.seed, e, overexposed,
                                     points, normals)
    return img, {**info, **place}, vis


# --------------------------------------------------------------------------- previews
def panorama(points, colors, center, size=(512, 256)) -> np.ndarray:
    """Equirectangular view of a cloud from ``center`` (nearest point per pixel, 2×2 splats):
    longitude 0 at −Z, increasing towards +X (the image centre looks along −Z), +Y at the top."""
    w, h = size
    d = points - np.asarray(center)
    r = np.linalg.norm(d, axis=1)
    lon = np.arctan2(d[:, 0], -d[:, 2])
    lat = np.arccos(np.clip(d[:, 1] / np.maximum(r, 1e-12), -1, 1))
    u = np.clip(((lon / (2 * np.pi) + 0.5) * w).astype(int), 0, w - 1)
    v = np.clip((lat / np.pi * h).astype(int), 0, h - 1)
    img = np.zeros((h, w, 4), np.float32)
    order = np.argsort(-r, kind="stable")      # far first: near points overwrite
    for du in (0, 1):
        for dv in (0, 1):
            uu, vv = (u[order] + du) % w, np.minimum(v[order] + dv, h - 1)
            img[vv, uu, :3] = colors[order]
            img[vv, uu, 3] = 1.0
    return img


# --------------------------------------------------------------------------- the references
def render_view(tracer, room, obj_scene, full_scenes: dict, view: dict, spp: int, bg_spp: int, tag: str,
                materials: dict, target: float = 0.0, cap: int = 0) -> dict:
    """gather_/full_ images of one view: {name: (rgba (H,W,4), var (H,W,3))} plus the mask.

    Object pixels (alpha 1; pixel-centre rays): ``spp`` paths a pixel for every material.
    Background pixels (alpha 0, informative only): ``bg_spp`` paths, rendered once per view —
    the room without the object for gather_*, the room with the Lambert object for full_*
    (its shadow and interreflections; the other materials change the room's light only at
    second order, so every material shares this background). ``target``/``cap``: adaptive
    sampling of the object pixels; ``precision`` of the result: :func:`precision_summary` of the
    object pixels of each image."""
    w, h = view["size"]
    M, K = view_camera(view)
    o, d = camera.camera_rays(M, K, (w, h))
    mask = smi.object_mask(tracer, obj_scene, o, d)
    bgs = {}
    for kind, sc in (("gather", room), ("full", full_scenes["lambert"])):
        bm, bv = np.zeros((len(o), 3)), np.zeros((len(o), 3))
        if np.any(~mask):
            m_, v_, _ = tracer.radiance(sc, o[~mask], d[~mask], bg_spp, f"{tag}/bg/{kind}")
            bm[~mask], bv[~mask] = m_, v_
        bgs[kind] = (bm, bv)
    out, counts = {}, {}
    a = mask.astype(np.float64)[:, None]
    for name, mat in materials.items():
        gm, gv = bgs["gather"][0].copy(), bgs["gather"][1].copy()
        fm, fv = bgs["full"][0].copy(), bgs["full"][1].copy()
        if np.any(mask):
            m_, v_, lv, n_ = tracer.gather(room, obj_scene, smi.material_bsdf(mat), o[mask], d[mask], spp,
                                           f"{tag}/gather/{name}", target, cap, counts=True)
            gm[mask], gv[mask] = m_, v_
            counts[f"gather_{name}"] = precision_summary(io.luminance(m_.astype(np.float32)), lv, n_, cap if target > 0 else 0)
            m_, v_, lv, n_ = tracer.radiance(full_scenes[name], o[mask], d[mask], spp, f"{tag}/full/{name}",
                                             target, cap, counts=True)
            fm[mask], fv[mask] = m_, v_
            counts[f"full_{name}"] = precision_summary(io.luminance(m_.astype(np.float32)), lv, n_, cap if target > 0 else 0)
        out[f"gather_{name}"] = (np.concatenate([gm, a], 1).reshape(h, w, 4), gv.reshape(h, w, 3))
        out[f"full_{name}"] = (np.concatenate([fm, a], 1).reshape(h, w, 4), fv.reshape(h, w, 3))
    return {"images": out, "mask": mask.reshape(h, w), "precision": counts}


PHOTO_REF_SUBPIXELS = 2   # the photo references: 2 × 2 stratified positions a pixel (a box filter: edges anti-aliased)


def photo_references(root: Path, spp: int, seed: int = 0, threads: int = 0) -> dict[str, Any]:
    """The composite's truth (issue 44): the first photo's view path-traced with the Lambert object in the room and
    without it, ``spp`` paths a pixel over :data:`PHOTO_REF_SUBPIXELS`² stratified sub-pixel positions, at the
    photo's scale k (the photo's own units). Writes ``truth/photo_with.exr`` / ``truth/photo_without.exr`` and their
    ``_var`` (variance of each pixel's mean) into the scene folder ``root`` (read: scene.json, truth/truth.npz, the
    meshes); returns what it rendered."""
    import json

    root = Path(root)
    scene = json.loads((root / "scene.json").read_text())
    tr = np.load(root / "truth" / "truth.npz")
    K, M = tr["photo_K"], tr["photo_world_to_camera"]
    w, h = (int(x) for x in tr["photo_size"])
    k = float(scene["photo_scale_k"])
    s = PHOTO_REF_SUBPIXELS
    per = max(1, spp // (s * s))
    tracer = smi.Tracer(seed, threads=threads)
    integrator = scene["integrator"]
    scenes = {"without": smi.load_room(root, scene, integrator),
              "with": smi.load_room(root, scene, integrator, scene["object"], smi.material_bsdf(MATERIALS["lambert"]))}
    t0 = time.perf_counter()
    out: dict[str, Any] = {"spp": per * s * s, "subpixels": s * s, "scale_k": k, "size": [w, h]}
    for name, sc in scenes.items():
        mean = np.zeros((h * w, 3))
        var = np.zeros((h * w, 3))
        for j, (a, b) in enumerate(itertools.product(range(s), range(s))):
            jit = np.tile([(a + 0.5) / s, (b + 0.5) / s], (h * w, 1))
            o, d = camera.camera_rays(M, K, (w, h), jitter=jit)
            m_, v_, _ = tracer.radiance(sc, o, d, per, f"photo_ref/{name}/{j}")
            mean += m_ / (s * s)
            var += v_ / (s * s) ** 2
        io.write_image(root / "truth" / f"photo_{name}.exr", (k * mean).reshape(h, w, 3).astype(np.float32))
        io.write_image(root / "truth" / f"photo_{name}_var.exr", (k * k * var).reshape(h, w, 3).astype(np.float32))
        out[name] = f"truth/photo_{name}.exr"
    out["seconds"] = round(time.perf_counter() - t0, 1)
    log.info("photo references: %s and %s, %d paths a pixel, %.0f s", out["with"], out["without"], out["spp"],
             out["seconds"])
    return out


# --------------------------------------------------------------------------- the action
def run_make_scene(out_dir, cfg: MakeSceneConfig, object_path=None, preview=True) -> dict:
    """Build the ground truth into ``out_dir`` (see the module docstring); returns the report."""
    cfg.check()
    user_obj = io.read_mesh(object_path) if object_path is not None else None  # bad input fails first
    t = Timings()
    t_cpu0 = time.process_time()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "meshes").mkdir(exist_ok=True)
    (out / "truth").mkdir(exist_ok=True)
    rng = np.random.default_rng([cfg.seed, 9])
    smi.mitsuba(cfg.threads)  # sets the variant and the thread count
    info = smi.llvm_info()
    log.info("Mitsuba %s, variant %s, %d threads, LLVM %s", info["mitsuba"], info["variant"], info["threads"], info.get("llvm", "?"))

    # ---- geometry
    with t.step("geometry"):
        if cfg.room == "atrium":
            params: Any = geo.AtriumParams(sky_radiance=cfg.sky_radiance, sun_radiance=cfg.sun_radiance, lamp_radiance=cfg.lamp_radiance)
            meshes = geo.atrium(params)
            lamp_centers = geo.LAMP_POSITIONS
        else:
            params = geo.LampRoomParams(lamp_radiance=cfg.lamp_radiance)
            meshes = geo.lamp_room(params)
            lamp_centers = geo.LAMP_ROOM_LAMPS
        mesh_entries = []
        for m in meshes:
            f = f"meshes/{m.name}.ply"
            io.write_mesh(out / f, m.vertices)
            mesh_entries.append({"name": m.name, "file": f, "albedo": [float(x) for x in m.albedo],
                                 "emission": [float(x) for x in m.emission],
                                 "area": float(geo.triangle_areas(m.triangles).sum()),
                                 "triangles": int(len(m.triangles))})
        if object_path is not None:
            V, F, N = user_obj
            obj = _write_object(out, "object", V, F, N, cfg, Path(object_path).name)
            other = "sphere"
        else:
            V, F, N = _default_object(cfg.default_object)
            obj = _write_object(out, "object", V, F, N, cfg, cfg.default_object)
            other = "sphere" if cfg.default_object != "sphere" else "knot"
        V2, F2, N2 = _default_object(other)
        obj2 = _write_object(out, "object2", V2, F2, N2, cfg, other)
        views = make_views(cfg.object_center, cfg.object_radius, cfg.ref_size)
        integrator = {"type": "path", "max_depth": int(cfg.max_depth), "rr_depth": int(cfg.rr_depth), "hide_emitters": False}
        scene: dict[str, Any] = {
            "units": "metres", "up": "+Y", "handedness": "right", "colour": "linear Rec.709 RGB radiance",
            "preset": cfg.name, "room": cfg.room, "seed": int(cfg.seed), "closed": True,
            "meshes": mesh_entries, "object": obj, "object2": obj2, "views": views,
            "camera_convention": "OpenCV: x right, y down, z forward; fov_deg vertical; pixel centres at +0.5; row 0 at the top",
            "materials": MATERIALS, "integrator": integrator,
            "renderer": {"name": "Mitsuba 3", **{k_: v_ for k_, v_ in info.items() if k_ not in ("threads", "llvm")}},
            "lamps": {"centers": [list(c) for c in lamp_centers], "radius": params.lamp_radius,
                      "radiance": [params.lamp_radiance * c for c in params.lamp_color]},
        }
        if cfg.room == "atrium":
            scene["sun"] = {"center": geo.sun_center(params.sun_radius).tolist(), "radius": params.sun_radius,
                            "shaft": "slanted light shaft above roof bay %d; opening x ∈ [%.2f, %.2f], z ∈ [%.2f, %.2f] at y = 12" % (geo.SUN_SLOT, *geo.sun_opening()),
                            "radiance": [params.sun_radiance * c for c in params.sun_color]}
    log.info("%s: %d meshes, %d triangles, %.0f m² of surface; object %s (%d triangles), object2 %s",
             cfg.room, len(meshes), sum(e["triangles"] for e in mesh_entries), sum(e["area"] for e in mesh_entries),
             obj["name"], obj["triangles"], obj2["name"])

    tracer = smi.Tracer(cfg.seed, lanes=cfg.lanes, threads=cfg.threads)
    room = smi.load_room(out, scene, integrator)

    # ---- the HDR cloud
    with t.step("cloud_bake"):
        b = bake_cloud(tracer, room, meshes, cfg.points, cfg.cloud_spp, rng, target=cfg.cloud_target, cap=cfg.cloud_max_spp)
    colors = b["mean"].astype(np.float32)
    lum = io.luminance(colors)
    se = np.sqrt(b["lum_var"]).astype(np.float32)
    cloud = io.Cloud(b["points"].astype(np.float32), b["normals"].astype(np.float32), colors, quality=se)
    io.write_cloud(out / "cloud_gt.ply", cloud)
    pos = lum[lum > 0]
    p999, p001 = np.percentile(lum, 99.9), np.percentile(lum, 0.1)
    dyn = float(p999 / p001) if p001 > 0 else float("inf")
    rel_se = float(np.median(se[lum > 0] / lum[lum > 0])) if pos.size else 0.0
    cloud_prec = precision_summary(lum, b["lum_var"], b["spp"], cfg.cloud_max_spp if cfg.cloud_target > 0 else 0)
    cap_txt = (f"target {cfg.cloud_target:.3g}; {100 * cloud_prec['share_at_cap']:.1f}% of the points stopped at the cap "
               f"{cfg.cloud_max_spp}" if cfg.cloud_target > 0 else "fixed spp")
    log.info("cloud_gt.ply: %d points (%d candidates rejected by the first-hit check), %d spp first, %.0f mean, "
             "dynamic range (99.9/0.1 pct luminance) %.3g; relative standard error median %.3g, p90 %.3g (%s)",
             len(cloud), b["rejected"], cfg.cloud_spp, cloud_prec["spp_mean"], dyn, cloud_prec["rel_se_median"],
             cloud_prec["rel_se_p90"], cap_txt)

    lights = light_stats(scene, b, lum, meshes, cfg.object_center)
    for key, v in lights.items():
        log.info("%s: %d of them cover %.3g %% of the directions from the object's centre; radiance %.4g = %.3g × the "
                 "median wall (non-emitting cloud point)", key, v["count"], 100 * v["solid_angle_share"], v["radiance_lum"],
                 v["over_wall_median"])

    # ---- the LDR cloud
    e, ldr_lin, codes = ldr_from_hdr(colors, cfg.saturate_share, cfg.ldr_noise, rng)
    io.write_cloud(out / "cloud_ldr.ply", io.Cloud(cloud.points, cloud.normals, ldr_lin), uchar_colors=True)
    over = ((io.luminance(ldr_lin) > T_L) | (codes == 255).any(axis=1)).astype(np.uint8)
    sat_share = float(np.mean((codes == 255).any(axis=1)))
    log.info("cloud_ldr.ply: exposure e = %.5g, %.2f%% points with a saturated channel, %d overexposed points (%s)",
             e, 100 * sat_share, int(over.sum()), OVEREXPOSED_RULE)

    # ---- the photos: one per camera rule, each with its own unknown scale k
    photos: list[dict[str, Any]] = []
    Kp = camera.intrinsics(cfg.photo_fov, cfg.photo_size)
    pw, ph = cfg.photo_size
    lum_top = float(lum.max()) if len(lum) else 0.0
    lamp = lamp_points(b["points"], scene.get("lamps"))
    with t.step("photo"):
        for i, rule in enumerate(cfg.photos):
            placed = None
            if rule.startswith("lamps"):
                before = np.any([p_["lamp_shown"] for p_ in photos], axis=0) if photos else np.zeros(len(lamp), bool)
                placed = lamps_camera_place(tracer, room, b["points"], b["normals"], lamp, before, cfg)
                if placed is None:
                    log.warning("photo '%s': no eye shows a lamp point the photos before it do not; using the 'bright' rule", rule)
            if rule == "sun" and "sun" in scene:
                placed = sun_camera_place(tracer, room, scene["sun"], cfg)
                if placed is None:
                    log.warning("photo 'sun': the sun is not seen from its beam; using the 'lights' rule")
            if rule in ("lights", "sun") and placed is None:
                placed = lights_camera_place(tracer, room, meshes, b, lum, lamp_centers, params.lamp_radius, cfg)
                if placed is None:
                    log.warning("photo '%s': no camera sees both the brightest patch and a lamp; using the 'bright' rule", rule)
            target, eye, extra = placed if placed is not None else (*photo_camera_place(meshes, b, lum, cfg), {})
            Mp = camera.look_at(eye, target, (0.0, 1.0, 0.0))
            jit = rng.random((pw * ph, 2))
            o, d = camera.camera_rays(Mp, Kp, (pw, ph), jitter=jit)
            pm, pv, _ = tracer.radiance(room, o, d, cfg.photo_spp, "photo" if i == 0 else f"photo/{rule}")
            k = float(10.0 ** rng.uniform(-1.0, 1.0))
            photo = k * pm
            if cfg.photo_noise > 0:
                photo = photo * np.maximum(0.0, 1.0 + cfg.photo_noise * rng.normal(size=photo.shape))
            photo = photo.reshape(ph, pw, 3).astype(np.float32)
            fname = photo_file(i, rule)
            io.write_image(out / fname, photo)
            vis = visible_points(tracer, room, b["points"], b["normals"], Mp, Kp, cfg.photo_size, eye)
            to_eye = eye - b["points"]
            lamp_shown = vis & lamp & (np.sum(to_eye * b["normals"], axis=1)
                                       >= LAMP_COS * np.linalg.norm(to_eye, axis=1))
            peak = float(io.luminance(photo).max()) / k
            ph_info = {"name": rule, "file": fname, "rule": PHOTO_RULES[rule] + ("" if placed is not None or rule == "bright" else " (fell back)"),
                       **({"lamp_points_shown": int(lamp_shown.sum()), "lamp_points": int(lamp.sum())} if rule.startswith("lamps") else {}), "truth": "truth/truth.npz" if i == 0 else f"truth/truth_{rule}.npz",
                       "scale_k": k, "alpha_true": e / k, "eye": eye.tolist(), "target": np.asarray(target).tolist(),
                       "visible_points": int(vis.sum()), "visible_overexposed": int((vis & over.astype(bool)).sum()),
                       "visible_lamp_points": int(np.sum(vis & np.isin(b["mesh"], np.flatnonzero(_emitting(meshes))))),
                       "peak_radiance_lum": peak, "peak_over_cloud_max": peak / max(lum_top, 1e-30), **extra}
            photos.append({**ph_info, "M": Mp, "vis": vis, "img": photo, "lamp_shown": lamp_shown})
            log.info("%s: %dx%d, %d spp, scale k = %.5g, camera at %s looking at %s (%s); alpha_true = e/k = %.5g; sees %d cloud "
                     "points (%d overexposed, %d on emitters); peak luminance %.4g = %.3g of the cloud's brightest point",
                     fname, pw, ph, cfg.photo_spp, k, np.round(eye, 2).tolist(), np.round(target, 2).tolist(), rule, e / k,
                     ph_info["visible_points"], ph_info["visible_overexposed"], ph_info["visible_lamp_points"], peak,
                     ph_info["peak_over_cloud_max"])
            if rule.startswith("lamps"):
                shown_all = np.any([p_["lamp_shown"] for p_ in photos], axis=0)
                log.info("%s: shows %d of the %d lamp points (facing it by cos ≥ %g); the photos so far %d", fname,
                         int(lamp_shown.sum()), int(lamp.sum()), LAMP_COS, int(shown_all.sum()))
    # ---- the HDR panorama (its own random stream: `--only panorama` renders the same into an existing folder)
    pano_info: dict[str, Any] | None = None
    if cfg.panorama:
        with t.step("panorama"):
            t_p = time.perf_counter()
            img, pano_info, pano_vis = _panorama(tracer, room, cfg, cfg.object_center, cfg.object_radius,
                                                 views["view1"]["eye"], e, over, cloud.points, cloud.normals,
                                                 scene.get("lamps"))
            write_panorama(out, img, pano_info, pano_vis, e, over, bool(preview))
        log_panorama(pano_info, time.perf_counter() - t_p)
    k, alpha_true, eye, Mp, photo = (photos[0]["scale_k"], photos[0]["alpha_true"], np.asarray(photos[0]["eye"]),
                                     photos[0]["M"], photos[0]["img"])

    # ---- the references
    ref_report: dict[str, Any] = {}
    if cfg.references:
        with t.step("references"):
            obj_scene = smi.load_object_only(out, obj)
            mats = {m: MATERIALS[m] for m in MATERIALS if m in cfg.materials}
            full_scenes = {name: smi.load_room(out, scene, integrator, obj, smi.material_bsdf(mat))
                           for name, mat in ({"lambert": MATERIALS["lambert"]} | mats).items()}
            for vname, v in views.items():
                r = render_view(tracer, room, obj_scene, full_scenes, v, cfg.ref_spp, cfg.ref_bg_spp, f"ref/{vname}", mats,
                                cfg.ref_target, cfg.ref_max_spp)
                mask = r["mask"]
                for key, (rgba, var) in r["images"].items():
                    kind, mname = key.split("_", 1)
                    io.write_image(out / "truth" / f"{kind}_{vname}_{mname}.exr", rgba.astype(np.float32))
                    io.write_image(out / "truth" / f"{kind}_{vname}_{mname}_var.exr", var.astype(np.float32))
                for mname in mats:
                    g, gv = r["images"][f"gather_{mname}"]
                    f_, fv = r["images"][f"full_{mname}"]
                    sel = mask
                    gl = io.luminance(g[..., :3][sel].astype(np.float32)).astype(np.float64)
                    fl = io.luminance(f_[..., :3][sel].astype(np.float32)).astype(np.float64)
                    gap = float(np.mean(fl - gl) / max(np.mean(gl), 1e-12)) if sel.any() else 0.0
                    rms = float(np.sqrt(np.mean((fl - gl) ** 2)) / max(np.mean(gl), 1e-12)) if sel.any() else 0.0
                    ref_report[f"{vname}/{mname}"] = {
                        "object_pixels": int(sel.sum()), "gather_mean_lum": float(gl.mean()) if sel.any() else 0.0,
                        "full_mean_lum": float(fl.mean()) if sel.any() else 0.0,
                        "gap_mean_rel": gap, "gap_rms_rel": rms,
                        "gather_rel_se_median": float(np.median(np.sqrt(gv[sel].mean(1)) / np.maximum(g[..., :3][sel].mean(1), 1e-12))) if sel.any() else 0.0,
                        "precision": {k_: r["precision"].get(f"{k_}_{mname}", {}) for k_ in ("gather", "full")}}
                    pg = r["precision"].get(f"gather_{mname}", {})
                    cap_txt = f", {100 * pg.get('share_at_cap', np.nan):.1f}% at the cap" if cfg.ref_target > 0 else " (fixed)"
                    log.info("%s %s: %d object pixels, full − gather = %+.1f%% of gather (mean), RMS %.1f%%; gather "
                             "relative standard error median %.3g, p90 %.3g, %.0f paths/pixel%s",
                             vname, mname, int(sel.sum()), 100 * gap, 100 * rms, pg.get("rel_se_median", np.nan),
                             pg.get("rel_se_p90", np.nan), pg.get("spp_mean", np.nan), cap_txt)
    else:
        log.info("references skipped (--no-references)")

    # ---- the precise subset: independent paths (own seeds and point choice), adaptive to precise_target
    precise_prec: dict[str, Any] = {}
    if cfg.precise_points > 0:
        with t.step("precise_subset"):
            idx = np.sort(np.random.default_rng([cfg.seed, 13]).choice(len(cloud), cfg.precise_points, replace=False))
            pp, pn = b["points"][idx], b["normals"][idx]
            pm_, pv_, plv, pc_ = tracer.radiance(room, pp + 2e-3 * pn, -pn, cfg.cloud_spp, "precise", cfg.precise_target,
                                                 cfg.precise_max_spp, counts=True)
            io.write_npz(out / "truth" / "cloud_precise.npz", "pcrelight.cloud_precise/1", index=idx.astype(np.int64),
                         colors=pm_, var=pv_, lum_var=plv, spp=pc_.astype(np.int64))
            plum = io.luminance(pm_.astype(np.float32)).astype(np.float64)
            precise_prec = precision_summary(plum, plv, pc_, cfg.precise_max_spp)
            from ..metrics import zscores

            z = zscores(lum[idx], b["lum_var"][idx], plum, plv)
            precise_prec.update(z_gt_over3=float(np.mean(np.abs(z) > 3)), pooled_ratio_gt=float(lum[idx].sum() / max(plum.sum(), 1e-30)))
        log.info("truth/cloud_precise.npz: %d points re-baked, relative standard error median %.3g, p90 %.3g, %.0f paths a "
                 "point, %.1f%% at the cap %d; cloud_gt.ply on them: |z| > 3 for %.1f%%, pooled ratio %.4f", len(idx),
                 precise_prec["rel_se_median"], precise_prec["rel_se_p90"], precise_prec["spp_mean"],
                 100 * precise_prec["share_at_cap"], cfg.precise_max_spp, 100 * precise_prec["z_gt_over3"],
                 precise_prec["pooled_ratio_gt"])

    # ---- truth, scene files
    over_share = float(over.mean())
    for ph_ in photos:
        io.write_npz(out / ph_["truth"], "pcrelight.truth/1",
                     k=np.float64(ph_["scale_k"]), e=np.float64(e), alpha_true=np.float64(ph_["alpha_true"]),
                     photo_K=Kp.astype(np.float64), photo_world_to_camera=ph_["M"].astype(np.float64),
                     photo_size=np.asarray(cfg.photo_size, np.int32), photo_eye=np.asarray(ph_["eye"], np.float64),
                     overexposed=over, photo_name=np.asarray(ph_["name"]), photo_visible=ph_["vis"].astype(np.uint8))
    scene.update({"exposure_e": e, "photo_scale_k": k, "alpha_true": alpha_true,
                  "overexposed_rule": OVEREXPOSED_RULE, "saturate_share": cfg.saturate_share,
                  "cloud": {"points": int(len(cloud)), "spp": cfg.cloud_spp, "target_rel_se": cfg.cloud_target,
                            "max_spp": cfg.cloud_max_spp, "precision": cloud_prec, "file": "cloud_gt.ply", "ldr": "cloud_ldr.ply",
                            **({"precise": {"file": "truth/cloud_precise.npz", "points": cfg.precise_points,
                                            "target_rel_se": cfg.precise_target, "max_spp": cfg.precise_max_spp,
                                            "precision": precise_prec}} if precise_prec else {}),
                            "quality": "standard error of the luminance estimate"},
                  "photo": {"file": "photo.exr", "size": list(cfg.photo_size), "spp": cfg.photo_spp,
                            "camera": "truth/truth.npz (photo_K, photo_world_to_camera); not given to the pipeline"},
                  "photos": [{k_: v_ for k_, v_ in ph_.items() if k_ not in ("M", "vis", "img", "lamp_shown")} for ph_ in photos],
                  "references": {"spp": cfg.ref_spp, "target_rel_se": cfg.ref_target, "max_spp": cfg.ref_max_spp,
                                 "background_spp": cfg.ref_bg_spp, "views": list(views),
                                 "materials": [m for m in MATERIALS if m in cfg.materials],
                                 "rendered": bool(cfg.references),
                                 "gather": "object lit by the room without it: one BSDF sample + one path per sample",
                                 "full": "the object inside the room, path-traced",
                                 "alpha": "object mask of the pixel-centre ray",
                                 "background": "alpha-0 pixels: the room seen by the camera (gather: without the object; full: with the Lambert object, shared by all materials)",
                                 "var": "variance of the pixel mean (RGB)"}})
    if pano_info is not None:
        scene["panorama"] = pano_info
    io.write_json(out / "scene.json", scene)
    if cfg.photo_ref_spp > 0 and cfg.references:       # reads scene.json and truth.npz as written above
        with t.step("photo_references"):
            scene["photo_references"] = photo_references(out, cfg.photo_ref_spp, cfg.seed, cfg.threads)
        io.write_json(out / "scene.json", scene)
    with io.atomic_path(out / "scene.xml") as tmp:
        tmp.write_text(smi.scene_xml(scene, integrator, "view2", 64))

    # ---- previews
    prev_paths = []
    if preview:
        pd = out / "previews"
        pano = panorama(cloud.points, cloud.colors, cfg.object_center)
        io.write_preview(pd / "cloud_gt_panorama.png", pano[..., :3])
        io.write_png(pd / "cloud_ldr_panorama.png", np.concatenate(
            [io.srgb_encode(panorama(cloud.points, ldr_lin, cfg.object_center)[..., :3]),
             np.ones(pano.shape[:2] + (1,), np.float32)], axis=2)[..., :3])
        prev_paths += ["previews/cloud_gt_panorama.png", "previews/cloud_ldr_panorama.png"]
        if pano_info is not None:
            prev_paths.append("previews/pano.png")
        for ph_ in photos:
            name = Path(ph_["file"]).stem + ".png"
            io.write_preview(pd / name, ph_["img"])
            prev_paths.append(f"previews/{name}")
        if cfg.references:
            for vname in views:
                for mname in cfg.materials:
                    for kind in ("gather", "full"):
                        img = io.read_image(out / "truth" / f"{kind}_{vname}_{mname}.exr")
                        io.write_preview(pd / f"{kind}_{vname}_{mname}.png", img[..., :3])
                        prev_paths.append(f"previews/{kind}_{vname}_{mname}.png")
        if isinstance(preview, (str, Path)):
            with io.atomic_path(preview) as tmp:  # (a stop or kill mid-copy leaves the previous preview)
                shutil.copyfile(pd / "cloud_gt_panorama.png", tmp)

    cpu = time.process_time() - t_cpu0
    report = {"stage": "make-scene", "out": str(out), "config": cfg.as_dict(), "object_input": None if object_path is None else str(object_path),
              "points": int(len(cloud)), "rejected_candidates": b["rejected"],
              "dynamic_range_999_001": dyn, "lum_p999": float(p999), "lum_p001": float(p001),
              "saturated_share": sat_share, "overexposed_points": int(over.sum()), "overexposed_share": over_share,
              "exposure_e": e, "photo_scale_k": k, "alpha_true": alpha_true,
              "photos": [{k_: v_ for k_, v_ in ph_.items() if k_ not in ("M", "vis", "img", "lamp_shown")} for ph_ in photos],
              "panorama": pano_info, "cloud_median_rel_se": rel_se, "cloud_precision": cloud_prec, "cloud_precise": precise_prec, "lights": lights, "references": ref_report, "previews": prev_paths,
              "paths_traced": int(tracer.paths), "timings_s": t.as_dict(), "cpu_s": cpu, "renderer": info}
    io.write_json(out / "report.json", report)
    log.info("make-scene done in %.1f s wall (%.1f s CPU), %.3g paths", t.total, cpu, tracer.paths)
    return report
