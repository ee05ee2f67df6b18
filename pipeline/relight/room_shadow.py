"""The room as the object leaves it: its shadow on the room and its light on the room (issue 22).

The cloud holds the radiance of the EMPTY room (the scan was taken before the object was placed). In the full
path trace the object sits in the room: the floor under and beside it gets less light (the object blocks some of
its sky and walls) and some light back (the object's own outgoing radiance). The object's pixels that see that
floor (a bowl's convex outside, view2 of the bowl room: the gather model 1.02 × the full trace) then read it
too bright. Measured with Mitsuba (bench/README.md "The room darkened (and lit) by the object"): the cloud's points
1.2–1.5 m from the bowl's centre (radius 0.96 m) carry 0.68 × their empty-room radiance in the full scene,
1.5–2 m 0.94 ×; relight with those points replaced by the path-traced values went from 1.022 / 1.020 / 1.007 to
0.997 / 0.997 / 0.990 of the full trace on view2 (Lambert).

Model (a diffuse room), at each room leaf of the BSH near the object: L' = L · E_black / E_empty + ρ · (E_obj −
E_black), from three classic walks with the leaf as a Lambert receiver (albedo 1, the leaf's normal as view
direction, emitters included: they are shadow-tested against the micro-buffer): E_empty in the room alone, E_black
with the object's surfels black (the light they block), E_obj with them lit by the last bounce pass (their colours,
or their directional maps, :mod:`.surfels`: the object's own light on the room). ρ = L / E_empty is the leaf's
reflectance, capped at the median over the walked leaves: a leaf lit by light that the walk does not gather (a sun
patch: the sun is not in the cloud) would otherwise reflect the object's light by its sun's brightness. Where ρ is
consistent this is L · E_obj / E_empty, and the walk's own errors at a room point (its neighbours at the horizon)
cancel in the ratio. The object's nodes stop at :data:`OBJECT_STOP` × ``object_stop`` in these walks (coarse
clusters overhang: a disc 2 m above a floor point hid 2 % too much at 1 ×).

Which leaves (:func:`near_leaves`): the object's bounding sphere (centre c, radius R) covers at most (R / d)², sin²
of its half-angle, of a receiver's cosine-weighted hemisphere (a sphere straight above a point at distance d); a
leaf is modelled when that bound is ≥ :data:`SHARE` and the sphere is not wholly below its tangent plane. At most
:data:`MAX_RECEIVERS` leaves walk, each with probability ∝ (R/d)⁴ (:func:`walk_subset`: every near leaf, a sparse
far field); the others take their walked neighbours' ratio (:func:`.surfels.spread`). The changed leaves' colours
and every ancestor's are then recomputed as build-bsh made them, the point-count-weighted mean of the node's points
(:func:`recolour_leaves`, ``bsh_core.range_sums``' numpy form). Emitters (isolated leaves) keep their light. Not
modelled: the bounce passes still see the empty room; an emitting room surface near the object (a skylight) would
be scaled like a reflector.

Units: metres, linear RGB radiance.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np

from ..bsh.format import LEAF, NODE_DTYPE, decode_cones, range_slots
from ..runtime import get_logger

log = get_logger("relight")

SHARE = 0.05          # model a room leaf when the object's bounding sphere may cover ≥ this of its cosine-weighted
                      # hemisphere ((R/d)² ≥ SHARE: d ≤ 4.5 R); the bowl's Mitsuba oracle: the room 0.4 % darker at
                      # 3–4 m, 0.1 % at 4–6 m (R 1.5 m), and 0.2 here left its view2 at 1.012 (bench/README.md)
MAX_RECEIVERS = 512   # room leaves that walk; the rest take their lit neighbours' ratio
LIFT = 0.01           # a receiver sits this × its splat radius above its leaf (at the leaf itself its own disc has distance 0)
OBJECT_STOP = 0.25    # the object's nodes stop at this × relight's --object-stop in the room leaves' walks
MICROBUFFER = 16      # the room leaves' micro-buffer side (0 = relight's --microbuffer): the bowl's oracle bins as close as at 24, half the time
RATIO_MAX = 8.0       # L' / L is clipped to [0, RATIO_MAX] (a leaf the room barely lit, lit by the object)


def near_leaves(centers: np.ndarray, normals: np.ndarray, is_leaf: np.ndarray, center: np.ndarray,
                radius: float, share: float = SHARE) -> np.ndarray:
    """Indices of the leaves (``is_leaf`` (M,) bool; ``centers``/``normals`` (M, 3)) where a sphere (``center``,
    ``radius`` [m]) may cover ≥ ``share`` of the cosine-weighted hemisphere, (R/d)² ≥ share, and is not wholly
    below the leaf's tangent plane."""
    v = np.asarray(center, np.float64)[None, :] - np.asarray(centers, np.float64)
    d2 = np.einsum("ij,ij->i", v, v)
    near = radius * radius >= share * d2
    above = np.einsum("ij,ij->i", v, np.asarray(normals, np.float64)) > -radius
    return np.flatnonzero(np.asarray(is_leaf, bool) & near & above)


def walk_subset(w: np.ndarray, n: int) -> np.ndarray:
    """Indices of about ``n`` of the leaves (in the BSH's depth-first order: spatially even) with weights ``w``
    (L,) ≥ 0, each kept with probability p = min(1, c·w), Σ p = n (c by bisection), by systematic sampling along
    the order (deterministic): all of them when L ≤ n."""
    w = np.asarray(w, np.float64)
    if np.count_nonzero(w > 0) <= n:
        return np.flatnonzero(w > 0) if len(w) > n else np.arange(len(w))
    lo, hi = 0.0, 1.0
    while np.minimum(1.0, hi * w).sum() < n:
        hi *= 2.0
    for _ in range(60):
        c = 0.5 * (lo + hi)
        lo, hi = (c, hi) if np.minimum(1.0, c * w).sum() < n else (lo, c)
    cs = np.cumsum(np.minimum(1.0, hi * w))
    return np.flatnonzero(np.diff(np.floor(np.concatenate([[0.0], cs]) + 0.5)) > 0)


def recolour_leaves(color: np.ndarray, first: np.ndarray, count: np.ndarray, leaves: np.ndarray,
                    scale: np.ndarray) -> np.ndarray:
    """(M, 3) float32 node colours after the colours of ``leaves`` are multiplied by ``scale`` (L, 3): every node's
    colour is its points' mean (``first``/``count``: each node's range of Morton-sorted points, bsh.npz), so each
    point of a scaled leaf changes by (scale − 1) · the leaf's colour and every node by the mean change of its
    points: differences of the changes' prefix sums, the numpy form of ``bsh_core.range_sums`` (bit for bit,
    tests/test_bsh.py). Not the numba kernel: importing numba and loading it cost ~0.55 CPU s of every relight
    for ~5 ms of numpy work (bench/README.md 'relight's fixed costs')."""
    first = np.asarray(first, np.int64)
    count = np.asarray(count, np.int64)
    leaves = np.asarray(leaves, np.int64)
    n = int((first + count).max()) if len(first) else 0
    dleaf = (np.asarray(scale, np.float64) - 1.0) * np.asarray(color, np.float64)[leaves]
    delta = np.zeros((n, 3))
    cnt = count[leaves]
    delta[range_slots(first[leaves], cnt)] = np.repeat(dleaf, cnt, axis=0)
    cs = np.concatenate([np.zeros((1, 3)), np.cumsum(delta, axis=0)])
    dsum = cs[first + count] - cs[first]
    return (np.asarray(color, np.float64) + dsum / np.maximum(count, 1)[:, None]).astype(np.float32)


def darken_room(ctx: Any, room: np.ndarray, room_splat: np.ndarray, merged: np.ndarray, merged_splat: np.ndarray,
                params: Any, bsh: dict, center: np.ndarray, radius: float, emitters: np.ndarray | None = None,
                object_dirs: np.ndarray | None = None, timings: Any = None) -> tuple[np.ndarray, dict]:
    """The merged node array (room + object, :func:`.surfels.merge_nodes`; ``params.object_first`` set) with the
    room's leaves near the object (``center``, bounding ``radius`` [m]) scaled by L' / L and their ancestors
    recoloured (module docstring). ``room``/``room_splat``: the room's nodes alone; ``bsh``: the
    bsh.npz dict (``first``, ``count``, ``normal``); ``object_dirs``: the object's directional radiance of the
    last bounce pass, if any. Returns (nodes, stats)."""
    from ..runtime import Timings
    from ..gather.base import Receivers
    from .surfels import spread

    t = timings if timings is not None else Timings()
    t0, c0 = time.perf_counter(), time.process_time()
    room = np.asarray(room).view(NODE_DTYPE)
    M = len(room)
    off = int(params.object_first) - M            # the room's node j is merged node off + j
    stats: dict[str, Any] = {"rule": f"room leaves with (R/d)^2 >= {SHARE} (R = the object's bounding radius, d the "
                                     "distance to its centre) and the object not below their plane",
                             "share": SHARE, "bounding_radius_m": float(radius), "leaves": 0, "walked": 0}
    if "first" not in bsh or "count" not in bsh or off < 0:
        stats["skipped"] = "the BSH has no point ranges (first/count)"
        log.info("room shadow: skipped (%s)", stats["skipped"])
        return merged, stats
    is_leaf = room["right"] == LEAF
    nrm = np.asarray(bsh["normal"], np.float64) if "normal" in bsh else decode_cones(room["cone"])[0]
    cen = room["center"].astype(np.float64)
    sel = near_leaves(cen, nrm, is_leaf, center, radius, SHARE)
    sel = sel[np.linalg.norm(room["color"][sel], axis=1) > 0]   # emitters (black in the nodes) keep their light
    stats["leaves"] = int(len(sel))
    if len(sel) == 0:
        log.info("room shadow: no room leaf near the object (rule %s)", stats["rule"])
        return merged, stats
    d2 = np.einsum("ij,ij->i", cen[sel] - center, cen[sel] - center)
    walk = sel[walk_subset(np.minimum(radius * radius / np.maximum(d2, 1e-300), 1.0) ** 2, MAX_RECEIVERS)]
    n = nrm[walk].astype(np.float32)
    lift = LIFT * np.asarray(room_splat, np.float64)[walk, None]   # just above the leaf's own disc
    recv = Receivers(np.ascontiguousarray((cen[walk] + lift * nrm[walk]).astype(np.float32)), n, n,
                     np.ones((len(walk), 3), np.float32), np.zeros(len(walk), np.float32),
                     np.ones(len(walk), np.float32), n)
    with t.step("room_shadow"):
        e_room, e_black, e_obj = irradiance_with_and_without(ctx, recv, room, room_splat, merged, merged_splat,
                                                             params, emitters, object_dirs)
        L = np.asarray(room["color"][walk], np.float64)
        ratio = changed_by_object(L, e_room, e_black, e_obj)
        if len(walk) < len(sel):
            ratio = spread(cen[walk], nrm[walk], ratio, cen[sel], nrm[sel]).astype(np.float64)
        out = merged.copy()
        out["color"][off:off + M] = recolour_leaves(room["color"], bsh["first"], bsh["count"], sel, ratio)
    lum = ratio @ np.array([0.2126, 0.7152, 0.0722])
    stats.update(walked=int(len(walk)), ratio_min=round(float(lum.min()), 4), ratio_mean=round(float(lum.mean()), 4),
                 ratio_max=round(float(lum.max()), 4), darker_10pct=int(np.count_nonzero(lum < 0.9)),
                 seconds=round(time.perf_counter() - t0, 3), cpu_s=round(time.process_time() - c0, 3))
    log.info("room shadow: %d room leaves near the object (%s), %d walked; L'/L (luminance) min %.3f, mean "
             "%.3f, max %.3f; %d leaves > 10 %% darker; %.2f s", len(sel), stats["rule"], len(walk), stats["ratio_min"],
             stats["ratio_mean"], stats["ratio_max"], stats["darker_10pct"], stats["seconds"])
    return out, stats


def irradiance_with_and_without(ctx: Any, recv: Any, room: np.ndarray, room_splat: np.ndarray, merged: np.ndarray,
                                merged_splat: np.ndarray, params: Any, emitters: np.ndarray | None = None,
                                object_dirs: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(E_empty, E_black, E_obj) / π (P, 3) float64 at room receivers ``recv`` (albedo-1 Lambert, unit normals): three
    classic walks, in the room alone (``room``), with the object's surfels black (the light they block) and with
    them lit (``merged``; ``params.object_first`` set; ``object_dirs`` their directional radiance). The object's
    nodes stop at :data:`OBJECT_STOP` × ``object_stop``; micro-buffer side :data:`MICROBUFFER`. Non-finite → 0."""
    from ..gather.classic import ClassicGatherer

    lam = dataclasses.replace(params, brdf="lambert", object_stop=OBJECT_STOP * params.object_stop,
                              m=MICROBUFFER or params.m)
    black = merged.copy()
    black["color"][params.object_first:] = 0.0
    irr = []
    for nodes, splat, p, dirs in ((room, room_splat, dataclasses.replace(lam, object_first=-1), None),
                                  (black, merged_splat, lam, None), (merged, merged_splat, lam, object_dirs)):
        g = ClassicGatherer(ctx, nodes, p, splat_radius=splat, emitters=emitters,
                            **({"object_dirs": dirs} if dirs is not None else {}))
        try:
            e, _ = g.run(recv, None, None)
        finally:
            g.release()
        irr.append(np.where(np.isfinite(e), np.maximum(e, 0), 0).astype(np.float64))
    return irr[0], irr[1], irr[2]


def changed_by_object(L: np.ndarray, e_room: np.ndarray, e_black: np.ndarray, e_obj: np.ndarray,
                      rho_cap: np.ndarray | None = None) -> np.ndarray:
    """L' / L (P, 3) of room points of radiance ``L`` (P, 3), any units, diffuse, with the object in the room
    (module docstring): L·E_black/E_empty + ρ·(E_obj − E_black), ρ = L / E_empty capped at ``rho_cap`` (default: the
    median over the points the room lights: a point lit by light the walk does not gather, a sun patch, must not
    reflect the object's light by its sun's brightness); clipped to [0, :data:`RATIO_MAX`]; 1 where the room
    gives no light."""
    lit = e_room > 1e-12 * max(float(e_room.max()) if e_room.size else 0.0, 1e-30)
    kept = np.where(lit, np.clip(e_black / np.maximum(e_room, 1e-300), 0.0, 1.0), 1.0)
    rho = np.where(lit, L / np.maximum(e_room, 1e-300), 0.0)
    if rho_cap is None:
        rho_cap = np.median(rho[lit.all(1)], axis=0) if lit.all(1).any() else 0.0
    rho = np.minimum(rho, rho_cap)
    return np.clip(kept + np.where(L > 0, rho * np.maximum(e_obj - e_black, 0.0) / np.maximum(L, 1e-300), 0.0),
                   0.0, RATIO_MAX)
