"""relight's inputs, read before anything is rendered (the planner reads them too, without rendering): the camera
of a view, the objects and their placement from scene.json, the BRDF the object's materials need, the glossy
bounces' directions. ``cfg`` is a :class:`pipeline.relight.relight.RelightConfig` (its camera and material fields)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..camera import parse_size
from ..errors import ConfigError, InputError


def camera_for(cfg: Any, scene: dict | None, scene_path: Any, view: str | None):
    """relight's camera (:class:`pipeline.camera.Camera`): ``--eye``/``--target``, else scene.json's ``view``;
    size ``--size``, else the view's, else 512²; the planner sizes the object's footprint with it."""
    from ..camera import Camera

    v: dict = {}
    if scene is not None and not cfg.eye:
        views = scene.get("views", {})
        name = view or "view1"
        if name not in views:
            raise InputError(scene_path, f"no view '{name}' (have: {', '.join(views) or 'none'})")
        v = views[name]
    if cfg.eye:
        eye, target, up = (np.asarray(x, np.float64) for x in (cfg.eye, cfg.target, cfg.up))
    elif v:
        try:
            eye, target, up = (np.asarray(v[k], np.float64).reshape(3) for k in ("eye", "target", "up"))
        except (KeyError, ValueError) as e:
            raise InputError(scene_path, f"view '{name}' lacks eye/target/up ({e})") from None
    else:
        raise InputError("relight", "needs a camera: --scene with --view, or --eye and --target")
    if np.linalg.norm(target - eye) <= 0:
        raise ConfigError("--eye and --target must differ")
    size = parse_size(cfg.size) if cfg.size else tuple(int(x) for x in v["size"]) if "size" in v else (512, 512)
    fov = cfg.fov if cfg.fov is not None else float(v.get("fov_deg", 45.0))
    return Camera(eye, target, up, fov, (int(size[0]), int(size[1])))


def object_entry(object_path: Any, scene: dict | None, scene_path: Any):
    """(path, to_world or None): --object, else scene.json's object; scene.json's to_world applies when
    the object is one of the scene's (``object``, ``object2``, …: same file name as its file/obj/ply entries)."""
    from pathlib import Path

    entries = [v for k, v in sorted((scene or {}).items()) if k.startswith("object") and isinstance(v, dict)]
    if object_path is None:
        obj = (scene or {}).get("object") or {}
        if not obj.get("file"):
            raise InputError("relight", "needs --object (or --scene with an object)")
        object_path = Path(scene_path).parent / obj["file"]
    name = Path(object_path).name
    to_world = next((e.get("to_world") for e in entries if name in {e.get(k) for k in ("file", "obj", "ply")}), None)
    return object_path, to_world


def objects_for(object_paths: Any, scene: dict | None, scene_path: Any) -> list[tuple[Any, Any]]:
    """[(path, to_world or None)] for one --object, several, or none (scene.json's object)."""
    if object_paths is None or isinstance(object_paths, (str, bytes)) or hasattr(object_paths, "__fspath__"):
        return [object_entry(object_paths, scene, scene_path)]
    return [object_entry(p, scene, scene_path) for p in object_paths]


def choose_brdf(cfg: Any, parts: list[dict]) -> tuple[str, str]:
    """(brdf, reason). Lambert unless the object (after overrides) has something glossy."""
    if cfg.brdf:
        return cfg.brdf, "--brdf"
    glossy = any(p.get("mr_tex") is not None
                 or (cfg.metallic if cfg.metallic is not None else p["metallic"]) > 0
                 or (cfg.roughness if cfg.roughness is not None else p["roughness"]) < 1
                 for p in parts if p.get("pbr"))
    if glossy:
        return "disney", "the object has glossy metallic-roughness materials"
    return "lambert", "every material is diffuse (metallic 0, roughness 1 or no PBR material)"


# --bounce-dirs auto: directional bounces for an object whose median roughness is below this (bench/README.md
# "The geometric horizon": the shipped knot's view2 GGX 0.1 / 0.25 means 0.978 / 0.975 of the full path trace with
# Lambert-reflector bounces, 1.013–1.016 with 16² directions; GGX 0.5 and 1.0 within 1 % either way)
GLOSSY_BOUNCE_ROUGHNESS = 0.5
AUTO_BOUNCE_DIRS = 16


def auto_bounce_dirs(brdf: str, roughness: np.ndarray) -> int:
    """``--bounce-dirs -1``: the octahedral map's side for the bounce passes — :data:`AUTO_BOUNCE_DIRS` for a glossy
    object (GGX, median surfel roughness < :data:`GLOSSY_BOUNCE_ROUGHNESS`), 0 (Lambert reflectors) otherwise."""
    if brdf == "lambert" or len(roughness) == 0:
        return 0
    return AUTO_BOUNCE_DIRS if float(np.median(roughness)) < GLOSSY_BOUNCE_ROUGHNESS else 0
