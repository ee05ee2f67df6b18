"""Where the object stands and where the camera looks from, for ``pcrelight run --cloud … --object …``
(issue 24): pure functions on arrays; every decision returns the numbers that decided it.

Conventions: metres, right-handed, +Y up (the imported cloud's frame, :mod:`pipeline.ingest.import_scan`), angles
of the options in degrees (as a user types them), 4×4 row-major local → world matrices (scene.json's
``to_world``, :func:`pipeline.relight.gbuffer.place_parts`).

**Floor** (:func:`find_floor`): the median height of the upward-facing points (normal within 25° of +Y)
in the lowest 5 % of the room's height (0.5th–99.5th percentile of y: a few stray points do not move it).

**Object size** (:func:`choose_scale`): the object's size is the largest side of its bounding box. Given
``object_size`` [m], the object is scaled to it; else it keeps its own size when that is plausible (between
:data:`PLAUSIBLE_MIN` and half the room's smaller horizontal side, and below 80 % of its height), else it
is scaled to :data:`DEFAULT_SHARE` × the room's smaller horizontal side.

**Placement** (:func:`auto_place`): a grid on the floor (cells of 1/64 of the room's larger horizontal side,
at least 2 cm). A cell is *floor* when floor points lie in it, *blocked* when a cloud point lies above it
between :data:`FLOOR_CLEARANCE` × the room height over the floor and the object's height (+10 %). The free
cells (floor, not blocked) form connected regions; the largest region (by area) is the free space, and the
object goes to its cell nearest the room's centre (the middle of the 0.5–99.5th percentile box) among those
whose distance to the nearest non-free cell is at least the object's footprint radius (half the diagonal of
its box in plan). When no cell of that region is wide enough, the widest one is taken and the check below
warns. The object rests on the floor: its box's lowest point at the floor height.

**Checks** (:func:`check_placement`, for automatic and given placements): the cloud points inside the
placed object's bounding box (above the floor by the clearance), and how far the box leaves the room's box.

**Camera** (:func:`auto_camera`): the target is the object's box centre; the eye is where the object's
bounding sphere about it (its farthest vertex) fills :data:`FILL` of the vertical field of view, at an elevation of :data:`ELEVATION` above
the horizontal, from the azimuth (every 15°) whose eye has the most room around it (distance to the nearest
cloud point) among those inside the room box with a clear line of sight (no cloud point within one splat
spacing of the segment, the object's sphere excluded); when no azimuth qualifies at that distance the eye
moves in by 20 % steps (at most 5) and the field of view widens to keep the framing.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..runtime import get_logger

log = get_logger("place")

FLOOR_COS = math.cos(math.radians(25.0))   # an upward-facing point: normal within 25° of +Y
FLOOR_SLAB = 0.05                          # the floor is in the lowest 5 % of the room's height
FLOOR_CLEARANCE = 0.02                     # points lower than 2 % of the room height over the floor are floor
PLAUSIBLE_MIN = 0.05                       # [m] an object's own size below this is not plausible (units?)
DEFAULT_SHARE = 0.15                       # implausible size → this share of the room's smaller horizontal side
ROOM_Q = 0.5                               # percentiles of the room box
FILL = 0.75                                # the bounding sphere fills this share of the vertical field of view
ELEVATION = 20.0                           # [degrees] the camera looks down on the object by this much


def rotation_y(deg: float) -> np.ndarray:
    """3×3 rotation about +Y by ``deg`` degrees (right-handed: +X turns towards −Z)."""
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def to_world(position: np.ndarray, scale: float, rotate_y_deg: float, local_min: np.ndarray,
             local_max: np.ndarray) -> np.ndarray:
    """4×4 row-major local → world: scale, turn about +Y, then put the object's box bottom centre (local
    coordinates: the middle of its box in x and z, its lowest y) at ``position``."""
    base = np.array([(local_min[0] + local_max[0]) / 2, local_min[1], (local_min[2] + local_max[2]) / 2])
    A = rotation_y(rotate_y_deg) * float(scale)
    M = np.eye(4)
    M[:3, :3] = A
    M[:3, 3] = np.asarray(position, np.float64) - A @ base
    return M


def placed_box(M: np.ndarray, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The world bounding box (min, max) of ``vertices`` (V,3) placed by ``M``."""
    w = np.asarray(vertices, np.float64) @ M[:3, :3].T + M[:3, 3]
    return w.min(axis=0), w.max(axis=0)


def room_box(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The room's box: the 0.5th–99.5th percentiles of every axis [m]."""
    lo, hi = np.percentile(points, [ROOM_Q, 100.0 - ROOM_Q], axis=0)
    return lo, hi


def find_floor(points: np.ndarray, normals: np.ndarray) -> tuple[float, dict[str, Any]]:
    """The floor height [m] and the numbers that decided it (module docstring)."""
    lo, hi = room_box(points)
    slab = FLOOR_SLAB * float(hi[1] - lo[1])
    sel = (normals[:, 1] >= FLOOR_COS) & (points[:, 1] <= lo[1] + slab)
    if sel.sum() < 3:
        y = float(lo[1])
        info = {"y": y, "points": int(sel.sum()), "by": f"no upward-facing points in the lowest {FLOOR_SLAB:.0%}: "
                                                          f"the room box's bottom ({ROOM_Q}th percentile of y)"}
        log.warning("floor: %s, y = %.3f m", info["by"], y)
        return y, info
    y = float(np.median(points[sel, 1]))
    info = {"y": y, "points": int(sel.sum()),
            "by": f"median height of the {int(sel.sum())} upward-facing points (normal within 25° of +Y) in the "
                  f"lowest {FLOOR_SLAB:.0%} of the room's height"}
    log.info("floor: y = %.3f m (%s)", y, info["by"])
    return y, info


def choose_scale(local_min: np.ndarray, local_max: np.ndarray, room_lo: np.ndarray, room_hi: np.ndarray,
                 object_size: float = 0.0) -> tuple[float, dict[str, Any]]:
    """The object's scale factor and why (module docstring). ``object_size`` [m]: 0 = automatic."""
    side = np.asarray(local_max, np.float64) - np.asarray(local_min, np.float64)
    own = float(side.max())
    room_h = float(room_hi[1] - room_lo[1])
    room_small = float(min(room_hi[0] - room_lo[0], room_hi[2] - room_lo[2]))
    if own <= 0:
        raise ValueError("the object has no extent")
    if object_size > 0:
        s, by = object_size / own, f"--object-size {object_size:g} m (its own size {own:.3g})"
    else:
        fits = PLAUSIBLE_MIN <= own <= 0.5 * room_small and side[1] <= 0.8 * room_h
        if fits:
            s, by = 1.0, (f"its own size {own:.3g} (largest side) is plausible: within [{PLAUSIBLE_MIN:g}, "
                          f"{0.5 * room_small:.3g}] m (half the room's smaller side) and its height below 80 % of the "
                          f"room's {room_h:.3g} m")
        else:
            target = DEFAULT_SHARE * room_small
            s, by = target / own, (f"its own size {own:.3g} (largest side, file units taken as metres) is not "
                                   f"plausible in a room of {room_small:.3g} × {room_h:.3g} m: scaled to "
                                   f"{DEFAULT_SHARE:g} × the room's smaller side = {target:.3g} m (--object-size sets it)")
    info = {"scale": s, "own_size": own, "size_m": own * s, "by": by}
    log.info("object size: %.3g m, scale %.4g (%s)", own * s, s, by)
    return s, info


def _grid(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[float, np.ndarray, tuple[int, int]]:
    cell = max(float(max(hi[0] - lo[0], hi[2] - lo[2])) / 64.0, 0.02)
    nx = max(1, int(math.ceil((hi[0] - lo[0]) / cell)))
    nz = max(1, int(math.ceil((hi[2] - lo[2]) / cell)))
    return cell, np.array([lo[0], lo[2]]), (nx, nz)


def _cells(xz: np.ndarray, origin: np.ndarray, cell: float, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    ij = np.floor((xz - origin) / cell).astype(np.int64)
    ok = (ij[:, 0] >= 0) & (ij[:, 0] < shape[0]) & (ij[:, 1] >= 0) & (ij[:, 1] < shape[1])
    return ij[ok], ok


def auto_place(points: np.ndarray, normals: np.ndarray, local_min: np.ndarray, local_max: np.ndarray,
               scale: float, rotate_y_deg: float = 0.0) -> tuple[np.ndarray, dict[str, Any]]:
    """The position [m] of the object's box bottom centre (module docstring, "Placement") and why."""
    from scipy import ndimage

    floor_y, floor_info = find_floor(points, normals)
    lo, hi = room_box(points)
    room_h = float(hi[1] - lo[1])
    corners = np.array([[(local_min, local_max)[b >> k & 1][k] for k in range(3)] for b in range(8)], np.float64)
    placed = (corners - [(local_min[0] + local_max[0]) / 2, local_min[1], (local_min[2] + local_max[2]) / 2]) \
        @ (rotation_y(rotate_y_deg) * scale).T
    height = float(placed[:, 1].max())
    foot = float(np.linalg.norm(placed[:, [0, 2]], axis=1).max())   # footprint radius [m]
    cell, origin, shape = _grid(points, lo, hi)
    clear = FLOOR_CLEARANCE * room_h
    near_floor = np.abs(points[:, 1] - floor_y) <= clear
    ij, _ = _cells(points[near_floor][:, [0, 2]], origin, cell, shape)
    floor = np.zeros(shape, bool)
    floor[ij[:, 0], ij[:, 1]] = True
    floor = ndimage.binary_closing(floor, iterations=1) | floor    # a sparse scan leaves holes between points
    above = (points[:, 1] > floor_y + clear) & (points[:, 1] < floor_y + 1.1 * height + clear)
    ij, _ = _cells(points[above][:, [0, 2]], origin, cell, shape)
    blocked = np.zeros(shape, bool)
    blocked[ij[:, 0], ij[:, 1]] = True
    free = floor & ~blocked
    centre = (lo[[0, 2]] + hi[[0, 2]]) / 2
    info: dict[str, Any] = {"floor": floor_info, "cell_m": cell, "grid": list(shape), "floor_cells": int(floor.sum()),
                            "blocked_cells": int((floor & blocked).sum()), "footprint_radius_m": foot,
                            "height_m": height, "room_centre_xz": centre.tolist()}
    if not free.any():
        pos = np.array([centre[0], floor_y, centre[1]])
        info.update(by="no free floor cell: the room's centre", position=pos.tolist())
        log.warning("placement: no free floor (%d floor cells, all blocked): the room's centre %s", int(floor.sum()),
                    np.round(pos, 3).tolist())
        return pos, info
    labels, n = ndimage.label(free)
    areas = np.bincount(labels.ravel())[1:] * cell * cell
    best = int(np.argmax(areas)) + 1
    region = labels == best
    room = ndimage.distance_transform_edt(region) * cell             # distance to the nearest non-free cell [m]
    ii, kk = np.nonzero(region)
    cxz = origin + (np.stack([ii, kk], axis=1) + 0.5) * cell
    dist = np.linalg.norm(cxz - centre, axis=1)
    width = room[ii, kk]
    fits = width >= foot
    if fits.any():
        j = int(np.flatnonzero(fits)[np.argmin(dist[fits])])
        by = (f"the largest free floor region ({areas[best - 1]:.3g} m² of {n} region(s)); its cell nearest the room's "
              f"centre ({dist[j]:.3g} m away) with {width[j]:.3g} m of free floor around it ≥ the footprint radius "
              f"{foot:.3g} m")
    else:
        j = int(np.argmax(width))
        by = (f"the largest free floor region ({areas[best - 1]:.3g} m² of {n} region(s)) has no cell with {foot:.3g} m "
              f"(the footprint radius) of free floor around it: its widest cell ({width[j]:.3g} m), {dist[j]:.3g} m "
              f"from the centre")
    pos = np.array([cxz[j, 0], floor_y, cxz[j, 1]])
    info.update(regions=int(n), region_area_m2=float(areas[best - 1]), clearance_m=float(width[j]),
                centre_distance_m=float(dist[j]), position=pos.tolist(), by=by)
    log.info("placement: %s → %s m", by, np.round(pos, 3).tolist())
    return pos, info


def check_placement(points: np.ndarray, box_min: np.ndarray, box_max: np.ndarray, floor_y: float | None
                    ) -> dict[str, Any]:
    """Warnings for a placed object: cloud points inside its box (above the floor clearance) and how far the
    box leaves the room's box [m]."""
    lo, hi = room_box(points)
    bottom = box_min[1] if floor_y is None else max(box_min[1], floor_y + FLOOR_CLEARANCE * float(hi[1] - lo[1]))
    inside = np.all((points >= [box_min[0], bottom, box_min[2]]) & (points <= box_max), axis=1)
    out = float(max(0.0, *(lo - box_min), *(box_max - hi)))
    info = {"points_inside": int(inside.sum()), "outside_room_m": out, "box_min": np.asarray(box_min).tolist(),
            "box_max": np.asarray(box_max).tolist(), "room_min": lo.tolist(), "room_max": hi.tolist(), "warnings": []}
    if inside.any():
        msg = (f"the object intersects the cloud: {int(inside.sum())} scan point(s) inside its bounding box "
               f"{np.round(box_min, 3).tolist()}–{np.round(box_max, 3).tolist()} m")
        info["warnings"].append(msg)
        log.warning("%s", msg)
    if out > 0:
        msg = (f"the object leaves the room: its box reaches {out:.3g} m beyond the room's box "
               f"{np.round(lo, 2).tolist()}–{np.round(hi, 2).tolist()} m")
        info["warnings"].append(msg)
        log.warning("%s", msg)
    return info


def _segment_clear(tree: Any, a: np.ndarray, b: np.ndarray, radius: float, skip_centre: np.ndarray,
                   skip_r: float) -> bool:
    n = max(2, int(math.ceil(np.linalg.norm(b - a) / max(radius, 1e-6))) + 1)
    s = a[None] + np.linspace(0.0, 1.0, n)[:, None] * (b - a)[None]
    s = s[np.linalg.norm(s - skip_centre, axis=1) > skip_r]
    if not len(s):
        return True
    d, _ = tree.query(s, k=1)
    return bool(np.all(d > radius))


def auto_camera(points: np.ndarray, box_min: np.ndarray, box_max: np.ndarray, fov_deg: float,
                aspect: float, radius: float | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """An eye, target and vertical field of view [degrees] framing the object's box from inside the room
    (module docstring, "Camera") and why. ``radius``: the object's bounding sphere about the box centre [m]
    (its farthest vertex); default half the box's diagonal."""
    from scipy.spatial import cKDTree

    tree = cKDTree(points)
    lo, hi = room_box(points)
    target = (np.asarray(box_min, np.float64) + np.asarray(box_max, np.float64)) / 2
    r = float(radius) if radius else float(np.linalg.norm(np.asarray(box_max) - np.asarray(box_min))) / 2
    sample = points[:: max(1, len(points) // 2000)]
    spacing = float(np.median(tree.query(sample, k=2)[0][:, 1]))
    half = math.radians(fov_deg) / 2 * FILL
    half = min(half, math.atan(math.tan(half) * aspect)) if aspect < 1 else half  # portrait: the width frames it
    dist0 = r / math.sin(half)
    el = math.radians(ELEVATION)
    tried = []
    for step in range(6):
        dist = dist0 * 0.8 ** step
        best: tuple[float, int] | None = None
        for k in range(24):
            az = math.radians(15.0 * k)
            d = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
            eye = target + dist * d
            inside = bool(np.all(eye > lo) and np.all(eye < hi))
            room_d = float(tree.query(eye, k=1)[0])
            clear = inside and room_d > spacing and _segment_clear(tree, eye, target, spacing, target, r)
            tried.append({"azimuth_deg": 15.0 * k, "distance_m": dist, "inside": inside, "clearance_m": room_d,
                          "line_of_sight": clear})
            if clear and (best is None or room_d > best[0]):
                best = (room_d, k)
        if best is not None:
            k = best[1]
            az = math.radians(15.0 * k)
            d = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
            eye = target + dist * d
            fov = fov_deg if step == 0 else math.degrees(2 * math.asin(min(0.99, r / dist)) / FILL)
            fov = min(fov, 120.0)
            by = (f"azimuth {15 * k}° (of 24), elevation {ELEVATION:g}°, {dist:.3g} m from the object (its bounding "
                  f"sphere of radius {r:.3g} m fills {FILL:.0%} of the view): the eye with the most room around it "
                  f"({best[0]:.3g} m to the nearest scan point) among those inside the room with a clear line of sight"
                  + (f"; moved in {step} step(s) of 20 % (none qualified farther), field of view widened to {fov:.3g}°"
                     if step else ""))
            log.info("camera: %s", by)
            return ({"eye": eye.tolist(), "target": target.tolist(), "up": [0.0, 1.0, 0.0], "fov_deg": float(fov)},
                    {"by": by, "azimuth_deg": 15.0 * k, "distance_m": dist, "clearance_m": best[0], "steps_in": step,
                     "spacing_m": spacing, "candidates": len(tried)})
    # nothing qualified: the farthest-in step's eye with the most room, said loudly
    dist = dist0 * 0.8 ** 5
    eye = target + dist * np.array([0.0, math.sin(el), math.cos(el)])
    fov = min(120.0, math.degrees(2 * math.asin(min(0.99, r / dist)) / FILL))
    by = (f"no eye within {dist0:.3g}–{dist:.3g} m of the object is inside the room with a clear line of sight: "
          f"azimuth 0° at {dist:.3g} m (pass --eye/--target)")
    log.warning("camera: %s", by)
    return ({"eye": eye.tolist(), "target": target.tolist(), "up": [0.0, 1.0, 0.0], "fov_deg": float(fov)},
            {"by": by, "azimuth_deg": 0.0, "distance_m": dist, "clearance_m": None, "steps_in": 6,
             "spacing_m": spacing, "candidates": len(tried), "warning": by})
