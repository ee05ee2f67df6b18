"""relight (DESIGN stage 7, paper 000 §5.2–§5.4): PBGI of a rasterised object by the HDR cloud's BSH.

The stage action: options (:class:`RelightConfig`, presets), G-buffer (``pipeline.relight.gbuffer``) →
receivers (covered pixels only) → the gatherer of ``--method`` from :data:`pipeline.gather.GATHERERS`
(walk + Eq. 9 gather) → relit.exr / relit.png / stats.json. relit.exr = the gathered light + the object's own
emission per pixel (glTF emissive × strength × texture, from the G-buffer); an emissive object's surfels also
light its other parts (:func:`pipeline.relight.surfels.in_micro_buffers`).

Units: metres, radians, radiance in linear RGB float32 (W·sr⁻¹·m⁻² up to a common scale).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any, Optional

import numpy as np

from ..bsh.format import nodes_from_bsh
from ..camera import parse_size
from ..config import StageConfig, preset_tables
from ..errors import ConfigError, InputError
from ..gather import BRDF_IDS, GATHERERS, MASK_IDS, MICROBUFFER_SIDES, SOLID_ANGLE_MODES, GatherParams, Receivers
from ..runtime import Timings, get_logger, process_age_s
from .inputs import GLOSSY_BOUNCE_ROUGHNESS, auto_bounce_dirs, camera_for, choose_brdf, objects_for

log = get_logger("relight")


# --------------------------------------------------------------------------- config
# --preset NAME: the [relight] table of configs/presets/NAME.toml (config.preset_tables), the points of the measured
# speed/accuracy trade that `pcrelight trade` picks by its documented rule (pipeline/measure/trade.py) from
# configs/presets/trade.csv; tests/test_trade.py checks that the shipped files are the rule's picks. Applied by
# config.resolve over the defaults; every option given explicitly (CLI or TOML) still wins.
def presets_table() -> dict[str, dict[str, Any]]:
    """``{name: relight options}`` of the shipped presets."""
    return preset_tables("relight")


@dataclass
class RelightConfig(StageConfig):
    """Options of ``pcrelight relight`` (units in brackets). Build it with :func:`pipeline.config.resolve`,
    which applies ``preset``; a direct constructor call takes the values as given."""

    preset: str = field(default="", metadata={"help": "speed/accuracy preset fast|balanced|exact from the measured front "
                                                      "(the [relight] table of configs/presets/NAME.toml, written by `pcrelight trade`; explicit options win); "
                                                      "empty = the individual defaults"})
    size: str = field(default="", metadata={"help": "viewport WxH [pixels]; empty = the view's size in scene.json, else 512x512"})
    eye: tuple[float, ...] = field(default=(), metadata={"help": "camera position x,y,z [m] (instead of --scene/--view)"})
    target: tuple[float, ...] = field(default=(), metadata={"help": "camera target x,y,z [m]"})
    up: tuple[float, ...] = field(default=(0.0, 1.0, 0.0), metadata={"help": "camera up vector x,y,z"})
    fov: Optional[float] = field(default=None, metadata={"help": "vertical field of view [degrees] (default 45 without a scene)"})
    microbuffer: int = field(default=24, metadata={"help": "micro-buffer side m (m×m texels; 8 for tests)", "choices": MICROBUFFER_SIDES})
    method: str = field(default="classic", metadata={
        "help": "gatherer (cut search, §5.2); envmap leaves the object out of its own light (no self-shadowing, no "
                "bounces: its papers' model, measured against gather_*, not full_*)",
        "choices": tuple(GATHERERS)})
    brdf: str = field(default="", metadata={"help": "BRDF; empty = disney if the object has PBR materials, else lambert", "choices": ("", *BRDF_IDS)})
    albedo: tuple[float, ...] = field(default=(), metadata={"help": "base colour r,g,b [linear, 0..1]; overrides the object's material"})
    roughness: Optional[float] = field(default=None, metadata={"help": "roughness [0..1] (GGX α = roughness²); overrides the object's"})
    metallic: Optional[float] = field(default=None, metadata={"help": "metallic [0..1]; overrides the object's"})
    masking: str = field(default="height-correlated", metadata={"expert": True, "help": "GGX Smith masking (separable = Mitsuba roughconductor)", "choices": tuple(MASK_IDS)})
    solid_angle: str = field(default="exact", metadata={"expert": True, "help": "micro-pixel solid angle in Eq. 9: exact per texel, or paper = Eq. 5's 2π/m²", "choices": SOLID_ANGLE_MODES})
    stop_multiple: float = field(default=4.0, metadata={"expert": True, "help": "stop rule Ω(A) ≤ k·Ω_pix (§5.3: k = 4)"})
    lobe_samples: int = field(default=GatherParams.lobe_samples, metadata={"expert": True, "help": "n: n×n VNDF samples integrate specular lobes narrower than --lobe-texels texels (0 = texel sum only; 16 left GGX 1.0 +2 %: bench/relight/lobe_samples_small.csv)"})
    lobe_texels: float = field(default=64.0, metadata={"expert": True, "help": "VNDF lobe sampling when GGX α·m < this (default: always for m ≤ 32), else the texel sum"})
    lobe_buffer: int = field(default=16, metadata={"expert": True, "help": "side of the lobe micro-buffer of a glossy receiver: a second micro-buffer around "
                                                          "the mirror direction, --lobe-cover·α wide, walked from the root (0 = none)",
                                                  "choices": (0, 8, 16, 24, 32)})
    lobe_cover: float = field(default=6.0, metadata={"expert": True, "help": "the lobe buffer's half-angle as a multiple of GGX α [rad] (6: ~90 % of the "
                                                            "VNDF samples); it applies where that is ≤ 0.6 rad"})
    disc_cone: float = field(default=1.0, metadata={"expert": True, "help": "splat nodes whose normal-cone half-angle ≤ this [rad] as discs (flat patches), others as spheres; -1 = spheres only (§5.2)"})
    splat_lambda: float = field(default=4.0, metadata={"expert": True, "help": "splat depth = centre distance + λ·(centre-to-ray distance); 0 = §5.2's centre distance"})
    omega_tr: float = field(default=32.0, metadata={"expert": True, "help": "hybrid threshold Ω_tr as a multiple of Ω_pix (§5.2.2: 32)"})
    composite: bool = field(default=False, metadata={"help": "also write composite.exr/.png: the object over the room's "
                                                             "BSH leaves drawn as Gaussian splats from this camera, with its "
                                                             "shadow and light on them (with --photo/--exposure: over the "
                                                             "photo, from its camera)"})
    surfels: int = field(default=0, metadata={"help": "surfels of the object in its own micro-buffers (its own shadows and bounces, "
                                                      "Christensen 2008): 0 = auto (spacing = bounding radius / m, 2000…50000), -1 = off (the paper's "
                                                      "gather: the object absent from its own micro-buffers)"})
    bounces: int = field(default=-1, metadata={"help": "light bounces between the object's parts: -1 = auto (2, then more "
                                                       "up to 4 while the bounces still to come would add ≥ 1 % of the "
                                                       "object's mean radiance: a concave bowl takes 3–4, a convex knot 2); "
                                                       "0 = its own shadows only; a glossy concave object mirrors itself "
                                                       "3–5 times: 3–4 with --bounce-dirs, bench/README.md",
                                               "choices": (-1, 0, 1, 2, 3, 4)})
    bounce_surfels: int = field(default=0, metadata={"expert": True, "help": "surfels lit in each bounce pass (the others take their "
                                                              "nearest lit neighbours' light); 0 = auto: 512, every surfel (at most 4096) "
                                                              "of a glossy object that sees itself (mean self-visibility ≥ 0.05)"})
    bounce_microbuffer: int = field(default=0, metadata={"expert": True, "help": "micro-buffer side of the bounce passes (the object's "
                                                                 "surfels lit by the room and each other); 0 = --microbuffer",
                                                         "choices": (0, *MICROBUFFER_SIDES)})
    bounce_dirs: int = field(default=-1, metadata={"expert": True, "help": "a glossy object's bounces: each surfel's light by direction "
                                                           "in an N×N octahedral map, e.g. 16 (a bounce pass ~5× a plain one; "
                                                           "bench/README.md); 0 = each surfel a Lambert reflector of its "
                                                           "hemispherical albedo; -1 = auto: 16 when the object's median "
                                                           "roughness is < 0.5 (its reflections of itself are sharp), else 0; "
                                                           "Lambert objects ignore it"})
    self_reflect: str = field(default="auto", metadata={"expert": True, "help": "a glossy object's reflections of itself at pixel "
                                                                "resolution: K lobe rays a pixel cast against the object's "
                                                                "triangles, each hit gathered as a secondary receiver over the "
                                                                "object's lit surfels (pipeline/relight/self_reflect.py); auto = "
                                                                "on for a glossy object with directional bounces whose "
                                                                "self-visibility is ≥ 0.05 (K from its roughness), off = the "
                                                                "surfels' light only, or K (1…256)"})
    object_stop: float = field(default=1.0, metadata={"expert": True, "help": "stop rule multiple k for the object's own nodes (its "
                                                              "silhouettes seen from itself: a cluster disc overhangs its edge)"})
    object_near: float = field(default=1.0, metadata={"expert": True, "help": "near field: an object surfel less than this × its splat radius "
                                                              "above a receiver's tangent plane and within 2 splat radii "
                                                              "of it (its neighbours) does not occlude it"})
    room_shadow: str = field(default="on", metadata={"expert": True, "help": "the object's shadow and light on the room near it: the room "
                                                             "leaves of the BSH near the object take L·E_with/E_without "
                                                             "the object (pipeline/relight/room_shadow.py; needs the "
                                                             "object in its own micro-buffers)", "choices": ("on", "off")})
    adaptive: float = field(default=0.3, metadata={"help": "image-space adaptive shading (paper 001): shade a 4×4 grid, "
                                                          "refine blocks whose corners differ by more than this relative "
                                                          "luminance (or in normal, or at the silhouette), upsample the rest "
                                                          "on the G-buffer; 0 = shade every pixel"})
    memory_budget: float = field(default=1.0, metadata={"expert": True, "help": "GPU memory for micro-buffers and pair buffers [GiB]"})
    bloom: float = field(default=0.0, metadata={"help": "bloom strength in relit.png (0 = off)"})
    vignette: float = field(default=0.0, metadata={"help": "vignette strength in relit.png (0 = off)"})
    key: Optional[float] = field(default=None, metadata={"help": "Reinhard key for relit.png (default: automatic, Reinhard 2002)"})
    hdr_out: bool = field(default=False, metadata={"help": "also write relit.hdr beside relit.exr: Radiance RGBE (paper 004), "
                                                           "linear RGB without alpha (black off the object), 8-bit mantissas "
                                                           "with a shared exponent (within 2⁻⁷ of a pixel's largest channel)"})

    @classmethod
    def presets(cls) -> dict[str, dict[str, Any]]:
        return presets_table()

    def check(self) -> None:
        self.check_choices()
        if self.size:
            parse_size(self.size)
        self._require(self.method in GATHERERS, "method", "must be one of " + ", ".join(GATHERERS))
        self._require(self.stop_multiple > 0, "stop_multiple", "must be > 0")
        self._require(self.omega_tr >= 1, "omega_tr", "must be ≥ 1")
        self._require(0 <= self.splat_lambda <= 100, "splat_lambda", "must be in [0, 100]")
        self._require(0 <= self.lobe_samples <= 64, "lobe_samples", "must be in [0, 64]")
        self._require(-1 <= self.disc_cone <= math.pi, "disc_cone", "must be in [-1, π]")
        self._require(self.lobe_texels >= 0, "lobe_texels", "must be ≥ 0")
        self._require(0 < self.lobe_cover <= 100, "lobe_cover", "must be in (0, 100]")
        self._require(self.memory_budget > 0, "memory_budget", "must be > 0")
        self._require(self.surfels == -1 or 0 <= self.surfels <= 2_000_000, "surfels", "must be -1, 0 (auto) or ≤ 2000000")
        self._require(0 <= self.bounce_surfels <= 2_000_000, "bounce_surfels", "must be in [0, 2000000] (0 = auto)")
        self._require(-1 <= self.bounce_dirs <= 64, "bounce_dirs", "must be in [-1, 64] (0 = off, -1 = auto)")
        self._require(self.object_stop > 0, "object_stop", "must be > 0")
        try:
            from .self_reflect import parse_option

            parse_option(self.self_reflect)
        except ValueError:
            self._require(False, "self_reflect", "must be auto, off or a number of rays K in [1, 256]")
        self._require(0 <= self.adaptive <= 100 and math.isfinite(self.adaptive), "adaptive", "must be in [0, 100] (0 = off)")
        self._require(0 <= self.object_near <= 100 and math.isfinite(self.object_near), "object_near", "must be in [0, 100]")
        self._require(self.bloom >= 0, "bloom", "must be ≥ 0")
        self._require(0 <= self.vignette <= 2, "vignette", "must be in [0, 2]")
        if self.roughness is not None:
            self._require(0 <= self.roughness <= 1, "roughness", "must be in [0, 1]")
        if self.metallic is not None:
            self._require(0 <= self.metallic <= 1, "metallic", "must be in [0, 1]")
        if self.fov is not None:
            self._require(0 < self.fov < 180, "fov", "must be in (0, 180) degrees")
        for name in ("albedo", "eye", "target", "up"):
            v = getattr(self, name)
            self._require(len(v) in ((0, 3) if name != "up" else (3,)) and bool(np.all(np.isfinite(v))), name,
                          "must be three numbers x,y,z")
        self._require(bool(np.all(np.asarray(self.albedo) >= 0)), "albedo", "must be ≥ 0")
        if bool(self.eye) != bool(self.target):
            raise ConfigError("--eye and --target go together")
        if self.surfels > 0 and not getattr(GATHERERS.get(self.method), "OBJECT_SURFELS", True):
            raise ConfigError(f"--surfels {self.surfels}: --method {self.method} does not put the object in its own "
                              "lighting (no self-shadowing); use --surfels 0 (auto: off for it) or -1")

    def gather_params(self, brdf: str) -> GatherParams:
        """The gatherer's parameters (``brdf``: the chosen BRDF, see :func:`choose_brdf`)."""
        return GatherParams(m=self.microbuffer, stop_multiple=self.stop_multiple, omega_tr=self.omega_tr,
                            memory_budget_bytes=self.memory_budget * 2 ** 30, solid_angle=self.solid_angle,
                            brdf=brdf, masking=self.masking, splat_lambda=self.splat_lambda,
                            lobe_samples=self.lobe_samples, lobe_texels=self.lobe_texels, disc_cone=self.disc_cone,
                            object_near=self.object_near, object_stop=self.object_stop, lobe_m=self.lobe_buffer,
                            lobe_cover=self.lobe_cover, seed=self.seed)


# --------------------------------------------------------------------------- the stage action
def _object_surfels(cfg: RelightConfig, parts: list[dict], t: Timings) -> tuple[dict, float, float]:
    """(surfels, area [m²], bounding radius [m]) of the object: their count (``--surfels``, else from its size and m:
    :func:`pipeline.relight.surfels.auto_count`) and the material overrides."""
    from . import surfels as sf

    with t.step("surfels"):
        area = sf.parts_area(parts)
        allp = np.concatenate([p["positions"] for p in parts]).astype(np.float64)
        radius = float(np.linalg.norm(allp.max(0) - allp.min(0)) / 2)
        count = cfg.surfels or sf.auto_count(area, radius, cfg.microbuffer)
        srf = sf.sample_surfels(parts, count, seed=cfg.seed)
        if cfg.albedo:
            srf["base_color"][:] = np.asarray(cfg.albedo, np.float32)
        if cfg.metallic is not None:
            srf["metallic"][:] = cfg.metallic
        if cfg.roughness is not None:
            srf["roughness"][:] = cfg.roughness
    log.info("object in its own micro-buffers: %d surfels (%s; area %.4g m², bounding radius %.4g m)",
             len(srf["position"]), "--surfels" if cfg.surfels else f"auto: spacing radius/m = {radius / cfg.microbuffer:.3g} m",
             area, radius)
    return srf, area, radius


def _object_in_micro_buffers(ctx: Any, cfg: RelightConfig, srf: dict, area: float, radius: float, nodes: np.ndarray,
                             splat: np.ndarray | None, params: Any, t: Timings,
                             emitters: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, Any, dict]:
    """The object's surfels ``srf`` (:func:`_object_surfels`) in the node array, lit:
    :func:`pipeline.relight.surfels.in_micro_buffers` with the bounce options and build-bsh's ``emitters``."""
    from . import surfels as sf

    lit = cfg.bounce_surfels   # 0: auto (surfels.in_micro_buffers: sf.LIT, every surfel of a glossy object that sees itself)
    dirs = auto_bounce_dirs(params.brdf, srf["roughness"]) if cfg.bounce_dirs < 0 else cfg.bounce_dirs
    if cfg.bounce_dirs < 0 and params.brdf != "lambert":
        log.info("--bounce-dirs auto: %d (the object's median roughness %.3g; directional bounces below %.2g)", dirs,
                 float(np.median(srf["roughness"])), GLOSSY_BOUNCE_ROUGHNESS)
    merged, msplat, params, stats = sf.in_micro_buffers(ctx, srf, nodes, splat, params, cfg.bounces, lit, t,
                                                        dirs_side=dirs, bounce_m=cfg.bounce_microbuffer,
                                                        emitters=emitters)
    stats.update(area_m2=area, bounding_radius_m=radius, bounce_dirs_side=int(dirs) if params.brdf != "lambert" else 0)
    return merged, msplat, params, stats


def _lit_object(ctx: Any, cfg: RelightConfig, parts: list[dict], nodes: np.ndarray, splat: np.ndarray | None,
                params: Any, bsh: dict, gl_info: dict, t: Timings) -> tuple[np.ndarray, np.ndarray, Any, dict, Any, Any]:
    """The object in its own micro-buffers, lit by its bounce passes (:func:`_object_in_micro_buffers`), and with
    ``--room-shadow on`` the room near it changed by it (:func:`pipeline.relight.room_shadow.darken_room`): (nodes,
    splat radii, ``params`` with ``object_first``, the object's stats, its directional radiance or None, the room
    shadow's stats or why it is off).

    None of it depends on the view: it is kept in :func:`pipeline.io.cache.cache_dir` ("lit_object") under a digest of
    everything it is computed from — the placed parts and the surfel options, the BSH arrays read, the gather parameters and bounce options, the
    GL renderer and pipeline's sources — and the next relight of the same object in the same room (another view,
    size or adaptive setting) reads it there instead of walking its bounce passes and the room shadow again, the same
    bytes (bench/README.md 'relight's fixed costs'). Stored: the object's nodes and splat radii, the room nodes whose
    colour the room shadow changed, the directional radiance and the stats."""
    import json

    from .surfels import subtree
    from .room_shadow import darken_room
    from ..io.cache import cache_dir, cache_write, code_digest, content_digest

    room, room_splat = nodes, np.asarray(splat if splat is not None else nodes["radius"], np.float32)
    room_shadow_on = cfg.room_shadow == "on"
    folder = cache_dir("lit_object")
    path = None
    if folder is not None:   # the key holds what the surfels are sampled from (a hit samples none: no trimesh)
        with t.step("lit_object_cache"):
            key = content_digest(LIT_OBJECT_FORMAT, parts, [cfg.surfels, cfg.seed, cfg.microbuffer, cfg.albedo,
                                                            cfg.metallic, cfg.roughness],
                                 room, room_splat, bsh.get("emitters"),
                                 [bsh.get(k) for k in ("first", "count", "normal")] if room_shadow_on else None,
                                 repr(params), [cfg.bounces, cfg.bounce_surfels, cfg.bounce_dirs, cfg.bounce_microbuffer,
                                                cfg.room_shadow], gl_info,
                                 code_digest(packages=("numpy", "numba", "trimesh", "scipy")))
            path = folder / f"{key}.npz"
            hit = _read_lit_object(path, room, room_splat)
        if hit is not None:
            merged, msplat, first, obj_stats, obj_dirs, room_shadow = hit
            obj_stats["lit_object_cache"] = "hit"
            log.info("object lit by %s bounce pass(es)%s: from the cache (%s)", obj_stats.get("bounces"),
                     " and the room shadow" if room_shadow_on else "", path)
            return merged, msplat, replace(params, object_first=first), obj_stats, obj_dirs, room_shadow
    srf, area, radius = _object_surfels(cfg, parts, t)
    merged, msplat, params, obj_stats = _object_in_micro_buffers(ctx, cfg, srf, area, radius, room, splat, params, t,
                                                                 bsh.get("emitters"))
    obj_dirs = obj_stats.pop("object_dirs", None)
    room_shadow: dict[str, Any] | str = "off (--room-shadow off)"
    if room_shadow_on:
        merged, room_shadow = darken_room(ctx, room, room_splat, merged, msplat, params, bsh,
                                          np.asarray(params.object_center), obj_stats["bounding_radius_m"],
                                          bsh.get("emitters"), obj_dirs, t)
    obj_stats["lit_object_cache"] = "off" if path is None else "miss"
    if path is not None:
        first, M = int(params.object_first), len(room)
        room_part = merged[first - M:first]
        changed = np.flatnonzero((room_part["color"].view(np.uint32) != room["color"].view(np.uint32)).any(1))
        obj, osplat = subtree(merged, msplat, first, len(merged))   # the object's tree as merge_nodes took it
        arrays = {"object_nodes": obj, "object_splat": osplat, "room_changed": changed,
                  "room_color": room_part["color"][changed],
                  "meta": np.array(json.dumps({"object_first": first, "object_stats": obj_stats,
                                               "room_shadow": room_shadow}, default=_json_scalar))}
        if obj_dirs is not None:
            arrays["object_dirs"] = np.asarray(obj_dirs)
        cache_write(path, arrays)
    return merged, msplat, params, obj_stats, obj_dirs, room_shadow


LIT_OBJECT_FORMAT = "pcrelight.lit_object/1"   # :func:`_lit_object`'s cache entries (in their digest)


def _json_scalar(x: Any) -> Any:
    """A numpy scalar or array in a cache entry's stats as JSON (``json.dumps`` ``default``)."""
    return x.tolist() if hasattr(x, "tolist") else str(x)


def _read_lit_object(path: Any, room: np.ndarray, room_splat: np.ndarray) -> tuple | None:
    """:func:`_lit_object`'s cache entry at ``path`` rebuilt over the room's nodes: (nodes, splat radii, object_first,
    object stats, directional radiance or None, room shadow stats); None where there is none or it does not fit."""
    import json

    from ..bsh.format import NODE_DTYPE
    from .surfels import merge_nodes
    from ..io.cache import cache_read

    d = cache_read(path)
    if d is None or any(k not in d for k in ("meta", "object_nodes", "object_splat", "room_changed", "room_color")):
        return None
    obj, osplat, changed, colour = d["object_nodes"], d["object_splat"], d["room_changed"], d["room_color"]
    try:
        meta = json.loads(str(d["meta"]))
    except ValueError:
        return None
    if obj.dtype != NODE_DTYPE or osplat.shape != (len(obj),) or colour.shape != (len(changed), 3) \
            or (len(changed) and (changed.min() < 0 or changed.max() >= len(room))):
        return None
    merged, msplat, first = merge_nodes(room, room_splat, obj, osplat)
    if first != meta.get("object_first"):
        return None
    merged["color"][first - len(room) + changed] = colour
    return merged, msplat, first, meta["object_stats"], d.get("object_dirs"), meta["room_shadow"]


def _self_reflect_setup(ctx: Any, cfg: RelightConfig, parts: list[dict], recv: Receivers, nodes: np.ndarray,
                        splat: Any, params: Any, obj_stats: dict, obj_dirs: Any, emitters: Any,
                        t: Timings) -> tuple[Optional[dict], str]:
    """``--self-reflect``: the decision (:func:`pipeline.relight.self_reflect.decide`, logged) and, when on, the lobe
    rays cast (the plan), the object-black gatherer (A) and the secondary gatherer over the lit surfels (B)."""
    from . import self_reflect as sr
    from .surfels import GLOSSY_SELF_VIS, subtree

    k, rule = sr.decide(cfg.self_reflect, params.brdf, obj_dirs is not None, obj_stats.get("self_visibility"),
                        recv.roughness, GLOSSY_SELF_VIS)
    log.info("self-reflection %s", rule)
    if k <= 0:
        return None, rule
    with t.step("self_reflect_rays"):
        caster = sr.MeshCaster(parts)
        pl = sr.plan(caster, recv, k, params.brdf, params.masking, cfg.seed)
    hits = int(pl.hit.sum())
    log.info("self-reflection: %d of %d pixels have a lobe ray on the object (%d hits of %d rays)", int(pl.sees.sum()),
             len(recv), hits, int((pl.weight.max(2) > 0).sum()))
    with t.step("gatherer"):
        fac = GATHERERS[cfg.method]
        black = fac(ctx, sr.black_object(nodes, params.object_first), params, splat_radius=splat, emitters=emitters)
        second = fac(ctx, nodes, sr.secondary_params(params), splat_radius=splat, emitters=emitters,
                     **({"object_dirs": obj_dirs} if obj_dirs is not None else {}))
        cover = room = None
        if sr.COVER:   # A's correction (self_reflect module doc): the surfels' coverage of the lobe, the room alone
            cover = fac(ctx, sr.cover_nodes(nodes, params.object_first), params, splat_radius=splat)
            rnodes, rsplat = subtree(nodes, splat, 1, params.object_first)   # the room alone (merge_nodes' layout)
            room = fac(ctx, rnodes, replace(params, object_first=-1), splat_radius=rsplat, emitters=emitters)
    overrides = {"base_color": cfg.albedo or None, "metallic": cfg.metallic, "roughness": cfg.roughness}
    stats = {"k": k, "pixels_seeing_object": int(pl.sees.sum()), "hits": hits, "secondary_microbuffer": sr.SECONDARY_M}
    return {"plan": pl, "caster": caster, "black": black, "second": second, "cover": cover, "room": room,
            "overrides": overrides, "stats": stats}, rule


def _merge_run_stats(runs: list[dict]) -> dict:
    """One gather's stats from those of several ``run`` calls (adaptive shading's levels): counts added,
    peaks and iteration counts their maxima, per-iteration lists added element by element; the cut's alike."""
    def merge(ds: list[dict]) -> dict:
        out = dict(ds[0])
        for k, v in ds[0].items():
            vals = [d.get(k) for d in ds]
            if isinstance(v, bool) or not all(isinstance(x, (int, float, list, dict)) and not isinstance(x, bool) for x in vals):
                continue
            if isinstance(v, dict):
                out[k] = merge([x for x in vals if x]) if any(vals) else v
            elif isinstance(v, list):
                n = max(len(x) for x in vals)
                out[k] = [sum(x[i] for x in vals if i < len(x)) for i in range(n)]
            elif k.startswith(("peak", "max")) or k in ("iterations", "walk_passes", "tile_receivers", "microbuffer_bytes",
                                                         "gather_budget_bytes", "walk_iteration_budget",
                                                         "start_list_limit_bytes", "levels"):
                out[k] = max(vals)
            else:
                out[k] = sum(vals)
        return out

    return merge(runs)


def _photo_plate(photo: Any, exposure: Any, cfg: RelightConfig, scene: dict | None, scene_path: Any,
                 view: str | None) -> tuple[np.ndarray | None, Any, float]:
    """(the photo (H, W, 3) in its units, its registered camera, α: the cloud's units ÷ the photo's) for the
    composite; without a registered camera in ``exposure``: one warning, relight's own camera and no plate
    (``cfg.composite`` then composites over the room's leaves)."""
    from .. import io
    from .composite import photo_camera, registered

    if exposure is None:
        raise ConfigError("--photo needs --exposure (exposure.npz from expose-match: the photo's camera and α)")
    ex = io.read_npz(exposure, "pcrelight.exposure/1")
    img = io.read_image(photo)[..., :3]
    if "photos" in ex:
        raise InputError(exposure, "records a photo set: composite into one photo needs a single-photo expose-match "
                                   "(the set's per-photo cameras are not composited yet)")
    if not registered(ex):
        log.warning("composite: %s has no registered camera in %s (expose-match without --photo-fov, or registration "
                    "not confident): relight's camera instead, over the room's cloud", photo, exposure)
        return None, camera_for(cfg, scene, scene_path, view), 1.0
    H, W = img.shape[:2]
    cam = photo_camera(ex["photo_K"], ex["photo_world_to_camera"], (W, H), exposure)
    log.info("composite: the camera of %s registered in %s (eye %s, fov %.2f°, %d×%d); the photo is the background",
             photo, exposure, np.round(cam.eye, 3).tolist(), cam.fov_deg, W, H)
    return np.asarray(img, np.float32), cam, float(ex["alpha"])


def _composite(ctx: Any, cfg: RelightConfig, parts: list[dict], cam: Any, gb: dict, rad: np.ndarray,
               plate: np.ndarray | None, alpha: float, room: np.ndarray, room_splat: np.ndarray, bsh: dict,
               merged: np.ndarray, merged_splat: Any, params: Any, obj_dirs: Any, obj_stats: dict, P: int,
               out: Any, t: Timings) -> dict:
    """composite.exr / composite.png (:mod:`pipeline.relight.composite`): the object's radiance ``rad`` (its covered
    pixels, the cloud's units) over ``plate`` (else the room's leaves seen from ``cam``) changed by the object."""
    from ..bsh.format import LEAF
    from . import composite as cp

    t0, c0 = time.perf_counter(), time.process_time()
    W, H = cam.size
    from_photo = plate is not None
    leaf = np.flatnonzero((room["right"] == LEAF) & (np.linalg.norm(room["color"], axis=1) > 0))
    normals = np.asarray(bsh["normal"], np.float32)[leaf]
    with t.step("composite_room"):
        surface = cp.room_surface(room["center"][leaf], normals, room_splat[leaf], cam)
    seen = np.zeros((H, W, 3), np.float32)                      # the room leaf's radiance at each pixel
    hit = surface["mask"]
    seen[hit] = room["color"][leaf][surface["index"][hit]]
    if plate is None:                                           # the room's leaves as Gaussians, holes filled
        with t.step("composite_background"):
            plate = cp.room_background(ctx, room["center"][leaf], normals, room["color"][leaf], cam)
    mask = gb["mask"]
    with t.step("composite_coverage"):
        cover = cp.coverage(ctx, parts, cam) if P else np.zeros((H, W), np.float32)
    cover = np.maximum(cover, mask.astype(np.float32))          # a centre-covered pixel is shaded: never see-through
    center = np.asarray(params.object_center, np.float64)
    receive = cp.near_pixels(surface, center, float(obj_stats.get("bounding_radius_m", 0.0)) if P else 0.0) & (cover < 1)
    behind = int(np.count_nonzero(surface["mask"] & (cover > 0)))
    if P and behind == 0:
        log.warning("composite: the camera sees no room point behind the object (the room's cloud misses that "
                    "part of the view): the object is over the plate only")
    if P:
        ratio, dstats = cp.differential(ctx, surface, receive, seen, cam, room, room_splat, merged,
                                        np.asarray(merged_splat, np.float32), params, bsh.get("emitters"), obj_dirs, t)
    else:
        log.warning("composite: the object is outside the camera's view: the plate unchanged")
        ratio, dstats = np.ones((H, W, 3), np.float32), {"receivers": 0}
    obj = np.zeros((H, W, 3), np.float32)
    obj.reshape(-1, 3)[np.flatnonzero(mask.reshape(-1))] = rad / alpha
    obj = obj + gb["emission"] / alpha                          # the object's own light (relit.exr adds it after this)
    odepth = np.linalg.norm(gb["position"] - np.asarray(cam.eye, np.float32), axis=-1)
    layers = cp.composite_layers(plate, ratio, obj, mask, cover, surface, odepth, gb["normal"])
    with t.step("composite_write"):
        cp.write_composite(out, layers, plate, cfg.key, cfg.hdr_out)
    info = {"background": "photo" if from_photo else "the room's BSH leaves as Gaussian splats (no registered photo)",
            "alpha_photo": alpha, "room_pixels": int(surface["mask"].sum()), "room_behind_object": behind,
            "object_edge_pixels": int(np.count_nonzero((cover > 0) & (cover < 1))), **dstats,
            "seconds": round(time.perf_counter() - t0, 3), "cpu_s": round(time.process_time() - c0, 3),
            "layers": list(layers)}
    log.info("composite: %s (%d room pixels, %d receivers walked, P'/P mean %.3f min %.3f; %d pixels > 5 %% darker) "
             "in %.1f s", out / "composite.exr", info["room_pixels"], dstats.get("walked", 0),
             dstats.get("ratio_mean", 1.0), dstats.get("ratio_min", 1.0), dstats.get("darker_5pct", 0), info["seconds"])
    return info


def run_relight(bsh_path: Any, out_dir: Any, cfg: RelightConfig, object_path: Any = None, scene_path: Any = None,
                view: str | None = None, preview: Any = None, ctx: Any = None, photo: Any = None,
                exposure: Any = None) -> dict:
    """Render the object relit by the BSH: writes relit.exr (float32 RGBA, alpha = mask), relit.png
    (Reinhard with automatic key, optional bloom/vignette), with ``cfg.hdr_out`` relit.hdr (Radiance RGBE, RGB)
    and stats.json in ``out_dir``. With ``photo`` and ``exposure`` (expose-match's exposure.npz holding its registered
    camera) the camera is the photo's and composite.exr / composite.png put the object into it
    (:mod:`pipeline.relight.composite`); ``cfg.composite`` does the same over the room's leaves from relight's camera."""
    from pathlib import Path

    from .. import display, gl, io
    from .gbuffer import place_parts, render_gbuffer

    startup: dict[str, Any] = {"process_before_relight": process_age_s()}   # interpreter, imports, CLI [s]
    t = Timings()
    t_start = time.perf_counter()
    cpu_start = time.process_time()                              # every thread's (llvmpipe's too) [CPU s]
    out = Path(out_dir)
    scene = io.read_json(scene_path) if scene_path is not None else None
    if scene is not None and not isinstance(scene, dict):
        raise InputError(scene_path, "not a scene.json object")
    plate, alpha_photo = None, 1.0                               # the composite's background, its units ÷ the cloud's
    if photo is not None:
        plate, cam, alpha_photo = _photo_plate(photo, exposure, cfg, scene, scene_path, view)
    else:
        cam = camera_for(cfg, scene, scene_path, view)
    compose = photo is not None or cfg.composite
    objects = objects_for(object_path, scene, scene_path)
    object_path = ", ".join(str(p) for p, _ in objects)
    to_world = [w for _, w in objects if w is not None] or None
    # the object in its own micro-buffers (its shadows, bounces, geometric horizon and the room shadow)
    own_surfels = cfg.surfels != -1 and getattr(GATHERERS[cfg.method], "OBJECT_SURFELS", True)
    if not getattr(GATHERERS[cfg.method], "OBJECT_SURFELS", True):
        log.warning("--method %s models the room's light alone: the object is absent from its own light (no "
                    "self-shadowing, no bounces between its parts; the shipped knot's view1 Lambert, envmap: 4×4-block RMS 32 %% "
                    "against the full path trace, 2026-12-03): use classic, mipmapped or hybrid for the object in its room",
                    cfg.method)
    with t.step("read"):
        parts = [q for p, w in objects for q in place_parts(io.read_object(p, cache=True), w)]
        keys = ("nodes", "splat_radius", "emitters")
        if cfg.room_shadow == "on" and own_surfels:
            keys += ("count", "first", "normal")                 # the room shadow's point ranges and leaf normals
        elif compose:
            keys += ("normal",)                                  # the room receivers' normals
        bsh = io.read_npz(bsh_path, "pcrelight.bsh/1", keys=keys)
        nodes = nodes_from_bsh(bsh, str(bsh_path))
    out.mkdir(parents=True, exist_ok=True)                       # after the inputs are read: bad input leaves nothing
    log.info("read %s: %d part(s), %d triangles%s", object_path, len(parts), sum(len(p["faces"]) for p in parts),
             f" ({len(to_world)} placed by scene.json to_world)" if to_world is not None else "")
    log.info("read %s: %d nodes (%.1f MiB)", bsh_path, len(nodes), nodes.nbytes / 2 ** 20)
    brdf_kind, why = choose_brdf(cfg, parts)
    log.info("BRDF %s (%s)%s", brdf_kind, why, "; glossy work skipped (no BRDF evaluation in the gather)"
             if brdf_kind == "lambert" else "")
    own_ctx = ctx is None
    t_ctx = time.perf_counter()
    if own_ctx:
        ctx = gl.create_context()
    gl.bind_dummy_framebuffer(ctx)
    startup["context"] = time.perf_counter() - t_ctx
    try:
        info = gl.context_info(ctx)
        log.info("GL: %s / %s", info["vendor"], info["renderer"])
        W, H = cam.size
        with t.step("gbuffer"):
            gb = render_gbuffer(ctx, parts, cam)
        mask = gb["mask"]
        P = int(mask.sum())
        log.info("G-buffer %dx%d: %d covered pixels (%.1f %%); the %d others are never processed", W, H, P,
                 100.0 * P / (W * H), W * H - P)
        flat = np.flatnonzero(mask.reshape(-1))
        base = gb["base_color"].reshape(-1, 3)[flat]
        if cfg.albedo:
            base = np.broadcast_to(np.asarray(cfg.albedo, np.float64).astype(np.float32), base.shape)
        met = gb["metallic"].reshape(-1)[flat] if cfg.metallic is None else np.full(P, cfg.metallic, np.float32)
        rgh = gb["roughness"].reshape(-1)[flat] if cfg.roughness is None else np.full(P, cfg.roughness, np.float32)
        recv = Receivers(gb["position"].reshape(-1, 3)[flat], gb["normal"].reshape(-1, 3)[flat],
                         gb["view"].reshape(-1, 3)[flat], np.ascontiguousarray(base, np.float32),
                         np.ascontiguousarray(met, np.float32), np.ascontiguousarray(rgh, np.float32))
        params = cfg.gather_params(brdf_kind)
        if parts:                                                 # the object's bounding-box centre [m] (envmap's eye)
            allp = np.concatenate([p["positions"] for p in parts]).astype(np.float64)
            params = replace(params, object_center=tuple(float(x) for x in (allp.min(0) + allp.max(0)) / 2))
        splat = bsh.get("splat_radius")
        obj_stats: dict[str, Any] = {"surfels": 0, "bounces": None}
        obj_dirs = None
        room_shadow: dict[str, Any] | str = ("off (--room-shadow off)" if cfg.room_shadow == "off" else
                                             "off (the object is not in its own micro-buffers)")
        if cfg.surfels == 0 and not own_surfels:
            log.info("--surfels auto: off for --method %s (it does not put the object in its own lighting)", cfg.method)
        if own_surfels:   # the object occludes itself: first its own face (no light from below the triangle's plane)
            recv = replace(recv, geom_normal=np.ascontiguousarray(gb["geom_normal"].reshape(-1, 3)[flat]))
        if compose and not own_surfels:
            raise ConfigError("the composite needs the object in its own micro-buffers (its shadow on the room): "
                              f"--surfels -1 and --method {cfg.method} leave it out")
        room_nodes, room_splat = nodes, np.asarray(splat if splat is not None else nodes["radius"], np.float32)
        if own_surfels and P > 0:   # the object lit (bounces) and the room shadow: cached, view-independent
            nodes, splat, params, obj_stats, obj_dirs, room_shadow = _lit_object(ctx, cfg, parts, nodes, splat, params,
                                                                                bsh, info, t)
            # the object's surfel BSH [s]: numba's kernels load the first time, then the cache (object_bsh_cache); 0
            # when the lit object came from the cache (a hit's object stats are those of the run that lit it)
            startup["object_bsh"] = 0.0 if obj_stats.get("lit_object_cache") == "hit" else obj_stats.get("object_bsh_s")
        with t.step("gatherer"):                                 # programs, texel tables, BSH upload
            g = GATHERERS[cfg.method](ctx, nodes, params, splat_radius=splat, emitters=bsh.get("emitters"),
                                      **({"object_dirs": obj_dirs} if obj_dirs is not None else {}))
        startup.update(getattr(g, "startup_s", {}))
        sr, self_reflect = None, "off (the object is not in its own micro-buffers)"
        if own_surfels and P > 0:
            sr, self_reflect = _self_reflect_setup(ctx, cfg, parts, recv, nodes, splat, params, obj_stats, obj_dirs,
                                                   bsh.get("emitters"), t)
        n_second = [0]

        def gather_px(k: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, list[dict]]:
            """The radiance of receivers k (viewport pixels idx) and the gathers' stats."""
            if sr is None:
                r, st_ = g.run(recv.take(k), idx, (H, W), timings=t)
                return r, [st_]
            from .self_reflect import shade as sr_shade

            r, sts, n2 = sr_shade(recv, k, idx, (H, W), sr["plan"], sr["caster"], g, sr["black"], sr["second"],
                                  sr["overrides"], t, sr["cover"], sr["room"])
            n_second[0] += n2
            return r, sts

        if cfg.adaptive > 0 and P > 0:
            from .adaptive import shade_adaptive

            runs: list[dict] = []
            shading = [0.0]                                       # [s] inside shade(): the gatherer's own steps

            def shade(idx: np.ndarray) -> np.ndarray:
                t0 = time.perf_counter()
                k = np.searchsorted(flat, idx)
                r, sts = gather_px(k, idx)
                runs.extend(sts)
                shading[0] += time.perf_counter() - t0
                return r

            t_ad = time.perf_counter()
            img_a, astats = shade_adaptive(shade, mask, gb["normal"], gb["position"], cfg.adaptive)
            adaptive_s = time.perf_counter() - t_ad - shading[0]  # grid, coherence tests, interpolation, upsample
            rad = img_a.reshape(-1, 3)[flat]
            gstats = _merge_run_stats(runs)
            gstats["adaptive"] = astats
            log.info("adaptive shading (ε %g): %d of %d covered pixels shaded (%.0f %%; per level %s), the rest "
                     "upsampled on the G-buffer", cfg.adaptive, astats["shaded"], P, 100 * astats["shaded_share"],
                     astats["levels"])
        else:
            adaptive_s = None
            if sr is None:
                rad, gstats = g.run(recv, flat, (H, W), timings=t)
            else:
                rad, sts = gather_px(np.arange(P), flat)
                gstats = _merge_run_stats(sts)
        g.release()
        if sr is not None:
            for key in ("black", "second", "cover", "room"):
                if sr[key] is not None:
                    sr[key].release()
            sr["stats"]["secondary_receivers"] = n_second[0]
            self_reflect = {**sr["stats"], "rule": self_reflect}
            log.info("self-reflection: %d secondary receivers (%.2f a covered pixel)", n_second[0], n_second[0] / max(P, 1))
        if compose:
            comp = _composite(ctx, cfg, parts, cam, gb, rad, plate, alpha_photo, room_nodes, room_splat, bsh, nodes,
                              splat, params, obj_dirs, obj_stats, P, out, t)
    finally:
        if own_ctx:
            ctx.release()
    bad = ~np.isfinite(rad)
    if bad.any():
        log.warning("%d non-finite radiance values set to 0", int(bad.sum()))
        rad[bad] = 0
    emit = gb["emission"].reshape(-1, 3)[flat]
    if np.any(emit > 0):                                   # the object's own light (glTF emissive): added as it is
        rad = rad + emit
        log.info("emission: %d of %d covered pixels emit (max %.4g, linear radiance), added to the gathered light",
                 int(np.count_nonzero(emit.max(axis=1) > 0)), P, float(emit.max()))
    img = np.zeros((H * W, 4), np.float32)
    img[flat, :3] = rad
    img[flat, 3] = 1.0
    img = img.reshape(H, W, 4)
    with t.step("write"):
        io.write_image(out / "relit.exr", img)
        if cfg.hdr_out:                                # RGBE has no alpha: RGB, 0 off the object
            io.write_image(out / "relit.hdr", img[..., :3])
        png = display.tonemap(img[..., :3], mask=mask if P else None, key=cfg.key, bloom_strength=cfg.bloom,
                              vignette_strength=cfg.vignette)
        io.write_png(out / "relit.png", png)
        if preview is not None:
            io.write_png(preview, png)
    stats = {
        "stage": "relight", "inputs": {"bsh": str(bsh_path), "object": str(object_path),
                                       "scene": None if scene_path is None else str(scene_path), "view": view},
        "config": cfg.as_dict(), "gl": info, "camera": {"eye": cam.eye.tolist(), "target": cam.target.tolist(),
                                                        "up": np.asarray(cam.up).tolist(), "fov_deg": cam.fov_deg,
                                                        "size": [W, H]},
        "method": cfg.method, "brdf": brdf_kind, "brdf_reason": why,
        "decisions": {"glossy_work_skipped": brdf_kind == "lambert", "pixels_off_object_skipped": W * H - P,
                      "to_world_applied": to_world is not None,
                      "object_in_own_micro_buffers": own_surfels, "geometric_horizon": own_surfels, "bounces": obj_stats["bounces"], "bounce_dirs": obj_stats.get("bounce_dirs_side"), "bounce_surfels": obj_stats.get("lit_surfels"), "bounce_surfels_rule": obj_stats.get("lit_rule"), "room_shadow": room_shadow, "self_reflect": self_reflect, "walk_iteration_budget": gstats.get("walk_iteration_budget")},
        "object_surfels": obj_stats, "adaptive": gstats.get("adaptive"), "method_stats": gstats.get("method_stats"),
        "pixels": W * H, "covered_pixels": P, "nodes": int(len(nodes)), "microbuffer": cfg.microbuffer,
        "memory_budget_bytes": int(params.memory_budget_bytes),
        "gather_budget_bytes": int(gstats.get("gather_budget_bytes", params.memory_budget_bytes)),
        **{k: gstats.get(k, 0) for k in ("tiles", "tile_receivers", "microbuffer_bytes", "nodes_visited", "start_nodes")},
        "nodes_visited_per_pixel": gstats.get("nodes_visited", 0) / max(P, 1),
        "walk_passes": gstats.get("walk_passes", 0), "mipmapped": gstats.get("cut", {}),
        "start_list_limit_bytes": gstats.get("start_list_limit_bytes"), "start_list_splits": gstats.get("start_list_splits", 0),
        "time_s": {**t.as_dict(), **({} if adaptive_s is None else {"adaptive": round(adaptive_s, 6)})},
        "total_s": time.perf_counter() - t_start, "cpu_s": round(time.process_time() - cpu_start, 4),
        "startup_s": {k: None if v is None else round(v, 4) for k, v in startup.items()},
    }
    if compose:
        stats["composite"] = comp
    io.write_json(out / "stats.json", stats)
    if cfg.hdr_out:
        log.info("wrote %s (Radiance RGBE) beside relit.exr", out / "relit.hdr")
    log.info("relit %dx%d (%s, m=%d, %s): %d tiles, %.0f nodes visited a pixel, %.2f s", W, H, cfg.method,
             cfg.microbuffer, brdf_kind, stats["tiles"], stats["nodes_visited_per_pixel"], stats["total_s"])
    return stats
