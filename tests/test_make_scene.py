"""make-scene's lamp-room capture (issue 25): the "lamps" photos and the panorama placed by ``--pano-rule lamps``
show the lamps, by line of sight traced against the room's meshes; the atrium's presets keep their rules."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline import io
from pipeline.scene import make_scene as ms
from pipeline.scene import mitsuba_render as smi

LAMPS_FAST = {"points": 40000, "cloud_spp": 4, "cloud_target": 0.0, "photo_size": (96, 64), "photo_spp": 4,
              "pano_size": (256, 128), "pano_spp": 2, "references": False}


@pytest.fixture(scope="module")
def lamp_room(tmp_path_factory):
    out = tmp_path_factory.mktemp("lamp_room")
    rep = ms.run_make_scene(out, ms.apply_preset("lamps", LAMPS_FAST), preview=False)
    return out, rep


def _grid_shown(out, sj, cfg, lamp, heights, clearance):
    """Every grid eye's shown lamp points (brute force, the rule's own test): {eye: (N,) bool}."""
    room = smi.load_room(out, sj, sj["integrator"])
    tr = smi.Tracer(0)
    gt = io.read_cloud(out / "cloud_gt.ply")
    P, N = gt.points.astype(np.float64), gt.normals.astype(np.float64)
    res = {}
    for y in heights:
        for eye in ms._grid_eyes(cfg, y, clearance):
            res[tuple(eye)] = ms.shown_points(tr, room, P, N, eye, lamp)
    return res, room, tr


def test_lamps_photos_show_the_lamp_points_a_person_can(lamp_room):
    """The set bright + lights + lamps + lamps2 + lamps3 shows (facing it by cos ≥ LAMP_COS, unoccluded, in frame:
    the truth masks) every lamp point that any eye of the rule's grid (1.7 m, 2.5 m) shows, more than bright +
    lights alone; each lamps photo adds lamp points; the rule is in scene.json."""
    out, rep = lamp_room
    sj = io.read_json(out / "scene.json")
    cfg = ms.apply_preset("lamps", LAMPS_FAST)
    gt = io.read_cloud(out / "cloud_gt.ply")
    P, N = gt.points.astype(np.float64), gt.normals.astype(np.float64)
    lamp = ms.lamp_points(P, sj["lamps"])
    assert lamp.sum() >= 5
    names = [p["name"] for p in sj["photos"]]
    assert names == ["bright", "lights", "lamps", "lamps2", "lamps3"]
    shown = {}
    for p in sj["photos"]:
        t = io.read_npz(out / p["truth"], "pcrelight.truth/1")
        d = np.asarray(p["eye"]) - P
        cos = np.sum(d * N, axis=1) / np.linalg.norm(d, axis=1)
        shown[p["name"]] = t["photo_visible"].astype(bool) & lamp & (cos >= ms.LAMP_COS)
        if p["name"].startswith("lamps"):
            assert p["rule"] == ms.PHOTO_RULES[p["name"]] and p["lamp_points_shown"] == int(shown[p["name"]].sum())
    grid, _, _ = _grid_shown(out, sj, cfg, lamp, ms.LAMP_EYE_HEIGHTS, 0.5)
    reachable = np.any(list(grid.values()), axis=0)
    union = np.any(list(shown.values()), axis=0)
    assert (union | ~reachable).all(), (int(union.sum()), int(reachable.sum()))
    assert union.sum() > (shown["bright"] | shown["lights"]).sum()
    before = shown["bright"] | shown["lights"]
    for name in ("lamps", "lamps2", "lamps3"):
        if (reachable & ~before).any():
            assert (shown[name] & ~before).any(), name
        before |= shown[name]


def test_pano_rule_lamps_stands_where_it_shows_the_most_lamps(lamp_room):
    """--pano-rule lamps: no eye of the rule's grid shows more lamps (then lamp points) than the panorama's centre;
    scene.json records the rule, what it shows and the lamps' size in pixels; the default rule is unchanged."""
    out, rep = lamp_room
    sj = io.read_json(out / "scene.json")
    cfg = ms.apply_preset("lamps", LAMPS_FAST)
    pano = sj["panorama"]
    assert pano["rule"] == ms.PANO_LAMPS_RULE and cfg.pano_rule == "lamps"
    gt = io.read_cloud(out / "cloud_gt.ply")
    P = gt.points.astype(np.float64)
    lamp = ms.lamp_points(P, sj["lamps"])
    C = np.asarray(sj["lamps"]["centers"])
    which = np.argmin(np.linalg.norm(P[:, None] - C[None], axis=2), axis=1)
    grid, room, tr = _grid_shown(out, sj, cfg, lamp, (ms.PANO_LAMPS_HEIGHT,), ms.PANO_CLEARANCE)
    key = lambda s: (len(np.unique(which[s])), int(s.sum()))   # noqa: E731
    best = max(key(s) for e, s in grid.items() if ms.free_space(tr, room, np.asarray(e)) >= ms.PANO_FREE)
    assert (pano["lamps_shown"], pano["lamp_points_shown"]) == best
    assert pano["lamp_points"] == int(lamp.sum())
    assert np.isclose(pano["lamp_min_pixels"], ms.lamp_pixels(pano["centre"], sj["lamps"], 256))
    assert ms.apply_preset("small", {}).pano_rule == "object" and ms.apply_preset("tiny", {}).pano_rule == "object"


def test_lamp_helpers():
    """lamp_points: within the radius + 1 cm of a centre; lamp_pixels: 2·asin(r/d) over 2π/W."""
    lamps = {"centers": [[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]], "radius": 0.04}
    pts = np.array([[0.045, 0, 0], [0, 0.06, 0], [5.0, 0.04, 0], [2.5, 0, 0]])
    assert ms.lamp_points(pts, lamps).tolist() == [True, False, True, False]
    assert not ms.lamp_points(pts, None).any()
    px = ms.lamp_pixels([1.0, 0, 0], lamps, 2048)
    assert np.isclose(px, 2 * np.arcsin(0.04 / 4.0) / (2 * np.pi / 2048))
    assert ms.lamp_pixels([0, 0, 0], None, 1024) == float("inf")
