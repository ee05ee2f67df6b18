"""Your object in your room (issue 24): what ``pcrelight run --cloud SCAN --photo PHOTO --object ASSET --out DIR``
does before the stages and after them. Not a stage: it prepares the workspace the stages read and composites
what relight wrote.

Before (:func:`prepare`):

1. the scan → ``<out>/cloud_ldr.ply`` through :mod:`pipeline.ingest.import_scan` (outliers removed and counted, units
   and up axis detected or ``--units``/``--up``, normals estimated; its report ``cloud_ldr.json``); redone only
   when the scan, its path or the import options changed (or ``--force``);
2. the photo's vertical field of view: ``--photo-fov``, else ``[expose-match] photo_fov``, else the photo's EXIF
   (:func:`exif_fov`, OpenImageIO's reader: EXR, JPEG, TIFF carry it; Radiance ``.hdr`` does not), else unknown
   (expose-match then matches histograms only);
3. the object's placement (:mod:`pipeline.run.place`: resting on the floor in the largest free space near the
   room's centre, ``--object-size``; or ``--place x,y,z --scale s --rotate-y deg``) with its warnings;
4. the camera: ``--eye/--target`` (``--fov``), else automatic (:func:`pipeline.run.place.auto_camera`);
5. ``<out>/scene.json`` with the object (its file name and ``to_world``) and the view, rewritten only when it
   changes (so relight reruns exactly when the placement or camera moved).

Every decision is logged with the number that decided it and returned for ``run.json`` (``own``).

After (:func:`composite`): ``composite.exr`` / ``composite.png``, the relit object (relit.exr, alpha = its
mask) over the room's cloud (the HDR cloud relight was lit by) splatted from the same camera
(:func:`pipeline.expansion.splats.render_view`, the cube-map splatter's disc rule), in the cloud's units, linear.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..camera import exif_fov, parse_size
from ..config import StageConfig
from ..errors import ConfigError, InputError
from ..runtime import get_logger

log = get_logger("own")

UP_CHOICES = ("auto", "x", "y", "z", "-x", "-y", "-z")


@dataclass
class OwnConfig(StageConfig):
    """The inputs and scene-setup options of ``pcrelight run --cloud … --photo … --object …`` (the ``[run]``
    table's keys; :class:`pipeline.run.stages.RunConfig` adds the workspace's)."""

    cloud: str = field(default="", metadata={
        "help": "your scan (PLY, PCD, XYZRGB/PTS, E57, LAS/LAZ): imported into the workspace (metres, +Y up); "
                "empty: <inputs>/cloud_ldr.ply as make-scene writes it"})
    photo: tuple[str, ...] = field(default=(), metadata={
        "help": "your HDR photo of the room (EXR or Radiance .hdr); several: repeat it, or give a folder of them (issue 25); "
                "empty: <inputs>/photo.exr", "multiple": True})
    units: str = field(default="auto", metadata={"help": "the scan's units (import)", "choices": ("auto", "m", "cm", "mm")})
    up: str = field(default="auto", metadata={"help": "the scan's up axis (import's --up; output +Y up)", "choices": UP_CHOICES})
    object_size: float = field(default=0.0, metadata={
        "help": "the object's size (largest side of its box) [m]; 0: its own size when plausible, else 0.15 × the "
                "room's smaller side"})
    place: tuple[float, ...] = field(default=(), metadata={
        "help": "put the object's box bottom centre here x,y,z [m] instead of the automatic placement"})
    scale: float = field(default=0.0, metadata={"help": "the object's scale factor (with --place; 0: from --object-size)"})
    rotate_y: float = field(default=0.0, metadata={"help": "turn the object about +Y [degrees]"})
    eye: tuple[float, ...] = field(default=(), metadata={"help": "camera position x,y,z [m] (with --target); empty: automatic"})
    target: tuple[float, ...] = field(default=(), metadata={"help": "camera target x,y,z [m]"})
    fov: float = field(default=40.0, metadata={"help": "the camera's vertical field of view [degrees]"})
    size: str = field(default="384x288", metadata={"help": "the picture's size WxH [pixels]"})
    photo_fov: float = field(default=0.0, metadata={
        "help": "the photo's vertical field of view [degrees]; 0: from its EXIF, else unknown"})

    def check(self) -> None:
        self.check_choices()
        self._require(self.object_size >= 0, "object_size", "must be ≥ 0 (0: automatic)")
        self._require(len(self.place) in (0, 3), "place", "must be three numbers x,y,z")
        self._require(self.scale >= 0, "scale", "must be ≥ 0 (0: from --object-size)")
        self._require(len(self.eye) in (0, 3), "eye", "must be three numbers x,y,z")
        self._require(len(self.target) in (0, 3), "target", "must be three numbers x,y,z")
        if bool(self.eye) != bool(self.target):
            raise ConfigError("--eye and --target go together")
        self._require(0 < self.fov < 180, "fov", "must be in (0, 180) degrees")
        self._require(self.photo_fov == 0 or 0 < self.photo_fov < 170, "photo_fov", "must be 0 (unknown) or in (0, 170)")
        parse_size(self.size)


# --------------------------------------------------------------------------- the photo's field of view
# --------------------------------------------------------------------------- before the stages
def _import_cloud(scan: Path, out: Path, cfg: OwnConfig, force: bool) -> dict[str, Any]:
    from .. import io
    from ..ingest.import_scan import ImportConfig, run_import
    from ..io.workspace import report_of

    icfg = ImportConfig(units=cfg.units, up=cfg.up, seed=cfg.seed)
    icfg.check()
    rep_path = report_of(out)
    if not force and out.exists() and rep_path.exists() and out.stat().st_mtime >= scan.stat().st_mtime:
        try:
            old = io.read_json(rep_path)
        except InputError:
            old = {}
        if old.get("input") == str(scan) and old.get("config") == icfg.as_dict():
            log.info("import: %s up to date (same scan, same options), kept", out)
            return old
    return run_import(scan, out, icfg)


def photo_fov_for(cfg: OwnConfig, photo: Path, stage_fov: float) -> tuple[float, dict[str, Any]]:
    """The photo's vertical field of view [degrees] (0: unknown) and why: ``--photo-fov``, else
    ``[expose-match] photo_fov`` (``stage_fov``), else its EXIF (:func:`exif_fov`), else unknown."""
    if cfg.photo_fov > 0:
        return cfg.photo_fov, {"fov_deg": cfg.photo_fov, "by": "--photo-fov"}
    if stage_fov > 0:
        return stage_fov, {"fov_deg": stage_fov, "by": "[expose-match] photo_fov"}
    fov, info = exif_fov(photo)
    if fov is None:
        info["fov_deg"] = 0.0
        log.info("photo: field of view unknown (%s; --photo-fov sets it): exposure from the histograms only", info["by"])
        return 0.0, info
    log.info("photo: vertical field of view %.3g° (%s)", fov, info["by"])
    return fov, info


def scene_dict(object_file: str, M: np.ndarray, view: str, camera: dict[str, Any], size: tuple[int, int],
               extra: dict[str, Any]) -> dict[str, Any]:
    """The scene.json relight reads: ``object`` (``file`` = the asset's file name, ``to_world`` 4×4 row-major)
    and ``views[view]`` (eye, target, up, vertical ``fov_deg``, ``size``)."""
    return {"object": {"file": object_file, "to_world": np.asarray(M, float).tolist(), **extra},
            "views": {view: {**camera, "size": [int(size[0]), int(size[1])]}},
            "units": "m", "up": "+Y", "handedness": "right",
            "written_by": "pcrelight run --cloud/--photo/--object (pipeline/run/own.py)"}


def check_inputs(cfg: Any) -> tuple[Path, list[Path], Path, list[dict]]:
    """Your scan, photos and object (``[run]``'s ``cloud``, ``photo``, ``object``) checked before anything is
    written: (scan, photos, object, the object's parts). A missing file, an unknown scan format, an LDR photo or an
    unreadable object is one InputError line naming it."""
    from .. import io
    from ..expansion.photo_set import PHOTO_SUFFIXES, expand_photos

    if not cfg.photo:
        raise ConfigError("--cloud needs --photo (your HDR photo of the room)")
    if not cfg.object:
        raise ConfigError("--cloud needs --object (the asset to relight)")
    scan, obj = Path(cfg.cloud), Path(cfg.object)
    for p in map(Path, cfg.photo):
        if not p.exists():
            raise InputError(p, "no such file (the photo)")
    photos = expand_photos(cfg.photo)                          # a folder: its HDR photos
    for p, what in ((scan, "scan"), *((q, "photo") for q in photos), (obj, "object")):
        if not p.exists():
            raise InputError(p, f"no such file (the {what})")
        if p.is_dir():
            raise InputError(p, f"is a directory, expected the {what} file")
    io.scan_reader(scan)                                       # an unknown scan format: refused before anything
    for p in photos:
        if p.suffix.lower() not in PHOTO_SUFFIXES:
            raise InputError(p, f"the photo must be HDR: OpenEXR (.exr) or Radiance (.hdr), got '{p.suffix}'")
    parts = io.read_object(obj)                                # bad input is refused before anything is written
    for p in photos:
        io.image_channels(p)
    return scan, photos, obj, parts


def explain_before_import(cfg: Any, stage_photo_fov: float, t_l: float, relight_cfg: Any) -> list[str]:
    """``run --explain --cloud`` before the scan is imported: the plan from the inputs alone — the scan's header
    (format, point count where the header holds it, size), the photos' field of view (``--photo-fov``, the
    expose-match table or EXIF), the object's parts and the BRDF they need — reading nothing else and writing
    nothing; the decisions that need the cloud's colours are named as taken after the import."""
    from .. import io
    from ..relight.inputs import choose_brdf

    scan, photos, obj, parts = check_inputs(cfg)
    n = io.scan_point_count(scan)
    count = f"{n} points in its header" if n is not None else "its point count read on import"
    fovs = [photo_fov_for(cfg, p, stage_photo_fov) for p in photos]
    brdf, why = choose_brdf(relight_cfg, parts)
    lines = [f"plan of --cloud {scan} (not imported yet: read from the inputs' headers, nothing written; the "
             f"decisions that need the cloud's colours are taken after the import)"]
    lines.append(f"  import: {scan} ({scan.suffix.lstrip('.').upper()}, {count}, {scan.stat().st_size / 1e6:.1f} MB) → "
                 f"cloud_ldr.ply: outliers removed, units {cfg.units} and up axis {cfg.up}"
                 f"{' (detected from the points)' if 'auto' in (cfg.units, cfg.up) else ''}, normals where missing")
    lines.append("  place and frame: the object on the imported floor's largest free region, the camera from 20° above "
                 "(--place, --rotate-y, --eye/--target/--fov override)")
    for p, (fov, how) in zip(photos, fovs):
        lines.append(f"  expose-match: {p}: " + (f"registered against the cloud (vertical field of view {fov:.3g}° from "
                                                 f"{how['by']})" if fov else
                                                 f"exposure from the histograms only (field of view unknown: {how['by']}; "
                                                 "--photo-fov sets it)"))
    lines.append(f"  render-cubemaps, patchmatch, reproject: run if the imported cloud has overexposed points (LDR "
                 f"luminance > t_l {t_l:g}): decided after the import")
    lines.append("  poisson: runs if reproject leaves points without HDR colour: decided after reproject")
    lines.append("  build-bsh: runs")
    lines.append(f"  relight: {obj} ({len(parts)} part{'s' if len(parts) != 1 else ''}), BRDF {brdf} ({why})")
    lines.append("  composite: the relit object over the room's HDR cloud from the same camera")
    return lines


def prepare(cfg: Any, root: Path, view: str, stage_photo_fov: float, force: bool = False) -> dict[str, Any]:
    """Steps 1–5 of the module docstring for the ``[run]`` options ``cfg`` (an :class:`OwnConfig`) into the
    workspace folder ``root``; returns the decisions (``run.json``'s ``own``), among them ``photo_fov``."""
    from .. import io
    from . import place

    t0 = time.perf_counter()
    scan, photos, obj, parts = check_inputs(cfg)
    photo = photos[0]
    w, h = parse_size(cfg.size)
    out: dict[str, Any] = {"inputs": {"cloud": str(scan), "photo": str(photo), "object": str(obj)}}
    if len(photos) > 1:
        out["inputs"]["photos"] = [str(p) for p in photos]
    root.mkdir(parents=True, exist_ok=True)
    rep = _import_cloud(scan, root / "cloud_ldr.ply", cfg, force)
    out["import"] = {k: rep.get(k) for k in ("format", "outliers", "units", "up", "normals", "shift_m", "output")}
    out["import"]["report"] = str((root / "cloud_ldr.json"))
    if len(photos) == 1:
        fov_photo, out["photo"] = photo_fov_for(cfg, photo, stage_photo_fov)
    else:                       # several: a given field of view applies to all; else expose-match reads each one's EXIF
        fov_photo = cfg.photo_fov or stage_photo_fov
        out["photo"] = {"fov_deg": fov_photo, "by": "--photo-fov" if cfg.photo_fov else "[expose-match] photo_fov"
                        if stage_photo_fov else "each photo's EXIF (expose-match)"}
        log.info("%d photos: field of view %s", len(photos), f"{fov_photo:g}° ({out['photo']['by']})" if fov_photo
                 else "from each photo's EXIF (expose-match)")
    out["photo_fov"] = fov_photo

    cloud = io.read_cloud(root / "cloud_ldr.ply")
    pts, nrm = cloud.points.astype(np.float64), cloud.normals.astype(np.float64)
    verts = np.concatenate([p["positions"] for p in parts]).astype(np.float64)
    lmin, lmax = verts.min(axis=0), verts.max(axis=0)
    lo, hi = place.room_box(pts)
    out["room"] = {"min_m": lo.tolist(), "max_m": hi.tolist()}
    log.info("room: %s m (0.5–99.5th percentile box of %d points)",
             " × ".join(f"{s:.3g}" for s in hi - lo), len(pts))
    if cfg.scale > 0:
        scale, out["scale"] = cfg.scale, {"scale": cfg.scale, "by": "--scale", "size_m": float((lmax - lmin).max()) * cfg.scale}
        log.info("object scale %.4g (--scale)", scale)
    else:
        scale, out["scale"] = place.choose_scale(lmin, lmax, lo, hi, cfg.object_size)
    if cfg.place:
        pos = np.asarray(cfg.place, np.float64)
        floor_y, floor = place.find_floor(pts, nrm)           # for the intersection check: floor points do not count
        out["placement"] = {"position": pos.tolist(), "by": "--place", "floor": floor}
        log.info("placement: %s m (--place)", pos.round(3).tolist())
    else:
        pos, out["placement"] = place.auto_place(pts, nrm, lmin, lmax, scale, cfg.rotate_y)
        floor_y = out["placement"]["floor"]["y"]
    out["placement"]["rotate_y_deg"] = cfg.rotate_y
    M = place.to_world(pos, scale, cfg.rotate_y, lmin, lmax)
    bmin, bmax = place.placed_box(M, verts)
    out["checks"] = place.check_placement(pts, bmin, bmax, floor_y)
    if cfg.eye:
        cam = {"eye": list(cfg.eye), "target": list(cfg.target), "up": [0.0, 1.0, 0.0], "fov_deg": cfg.fov}
        out["camera"] = {**cam, "by": "--eye/--target/--fov"}
        log.info("camera: eye %s, target %s, fov %g° (given)", list(cfg.eye), list(cfg.target), cfg.fov)
    else:
        placed = verts @ M[:3, :3].T + M[:3, 3]
        radius = float(np.linalg.norm(placed - (bmin + bmax) / 2, axis=1).max())
        cam, why = place.auto_camera(pts, bmin, bmax, cfg.fov, w / h, radius)
        out["camera"] = {**cam, **why}
    out["camera"]["size"] = [w, h]
    scene = scene_dict(obj.name, M, view, cam, (w, h), {"size_m": out["scale"]["size_m"]})
    sp = root / "scene.json"
    old = None
    if sp.exists():
        try:
            old = json.loads(sp.read_text())
        except ValueError:
            old = None
    if old != json.loads(json.dumps(scene)):
        io.write_json(sp, scene)
        log.info("wrote %s (object %s, view %s)", sp, obj.name, view)
    else:
        log.info("%s unchanged (same placement and camera), kept", sp)
    out["seconds"] = round(time.perf_counter() - t0, 3)
    return out


# --------------------------------------------------------------------------- after the stages
def composite(relit_exr: Path, cloud_path: Path, scene_path: Path, view: str, out_dir: Path,
              key: float | None = None) -> dict[str, Any]:
    """``composite.exr`` (RGBA float32, linear, the cloud's units) and ``composite.png`` (Reinhard) in
    ``out_dir``: relit.exr over the cloud splatted from relit's camera (stats.json's, else scene.json's view)."""
    from .. import display, io
    from ..relight.gbuffer import Camera
    from ..expansion.splats import knn_splat_radii, render_view

    t0 = time.perf_counter()
    relit = io.read_image(relit_exr)
    if relit.shape[2] < 4:
        raise InputError(relit_exr, "has no alpha channel (relit.exr is RGBA)")
    stats_path = relit_exr.with_name("stats.json")
    cam_d = io.read_json(stats_path).get("camera") if stats_path.exists() else None
    if not cam_d:
        v = io.read_json(scene_path)["views"][view]
        cam_d = {**v, "size": v.get("size", [relit.shape[1], relit.shape[0]])}
    cam = Camera(np.asarray(cam_d["eye"], float), np.asarray(cam_d["target"], float), np.asarray(cam_d["up"], float),
                 float(cam_d["fov_deg"]), (int(cam_d["size"][0]), int(cam_d["size"][1])))
    if (relit.shape[1], relit.shape[0]) != cam.size:
        raise InputError(relit_exr, f"is {relit.shape[1]}×{relit.shape[0]}, its camera {cam.size[0]}×{cam.size[1]}")
    cloud = io.read_cloud(cloud_path)
    radii = knn_splat_radii(cloud.points.astype(np.float64))
    room = render_view(cloud.points, cloud.colors, radii, cam.view_matrix(), cam.fov_deg, cam.size)
    a = relit[..., 3:4]
    rgb = relit[..., :3] * a + room[..., :3] * (1.0 - a)
    cover = np.maximum(a[..., 0], room[..., 3])
    img = np.concatenate([rgb, cover[..., None]], axis=2).astype(np.float32)
    io.write_image(out_dir / "composite.exr", img)
    png = display.tonemap(rgb, mask=cover > 0 if cover.any() else None, key=key)
    io.write_png(out_dir / "composite.png", png)
    info = {"room_pixels": int(room[..., 3].sum()), "object_pixels": int((a > 0).sum()), "pixels": int(a.size),
            "cloud": str(cloud_path), "seconds": round(time.perf_counter() - t0, 3)}
    log.info("composite: %s (the object over %d room pixels of %d, splatted from %s) in %.1f s",
             out_dir / "composite.png", info["room_pixels"], info["pixels"], cloud_path, info["seconds"])
    return info
