"""The room as the object leaves it, measured by Mitsuba (issue 22; pipeline/relight/room_shadow.py).

    .venv/bin/python -m bench.relight.room_shadow_oracle make SCENE_DIR OUT [--within 6] [--spp 1024] [--material lambert]
    .venv/bin/python -m bench.relight.room_shadow_oracle compare SCENE_DIR OUT --bsh BSH [--view view2]

``make``: the exact cloud's points within ``--within`` metres of the object's centre (scene.json ``object.center``)
path traced along their normals (as make-scene bakes the cloud) in the room with the object (``--material``) and
without it, the same seeds; OUT/cloud.ply = cloud_gt.ply + (L_with − L_without) at those points (the "oracle"
cloud of the room with the object in it); OUT/oracle.npz the estimates. Prints L_with / L_without (luminance sums)
by distance. Then ``cli.py build-bsh OUT/cloud.ply`` and ``bench_relight_cases.py --bsh`` with ``room_shadow: off``
measure relight on the room as the path trace sees it.

``compare``: relight (defaults, Lambert 0.8, ``--view``) on the scene's own BSH ``--bsh``; for the room leaves of
one point each, the ratio relight's room shadow gave them against the oracle's L_with / L_without, by distance.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]

from pipeline.color import luminance  # noqa: E402

BINS = ((0.0, 1.2), (1.2, 1.5), (1.5, 2.0), (2.0, 3.0), (3.0, 4.0), (4.0, 6.0))


def lum(x: np.ndarray) -> np.ndarray:
    return luminance(np.asarray(x, np.float64), np.float64)


def make(scene_dir: Path, out: Path, within: float, spp: int, material: str) -> None:
    from pipeline.scene import mitsuba_render as smi
    from pipeline.io.clouds import read_cloud, write_cloud
    from pipeline.scene.make_scene import MATERIALS

    scene = json.loads((scene_dir / "scene.json").read_text())
    integ = {"type": "path", "max_depth": scene["integrator"]["max_depth"], "rr_depth": scene["integrator"]["rr_depth"]}
    room = smi.load_room(scene_dir, scene, integ)
    full = smi.load_room(scene_dir, scene, integ, scene["object"], smi.material_bsdf(MATERIALS[material]))
    c = read_cloud(scene_dir / "cloud_gt.ply")
    d = np.linalg.norm(c.points - np.asarray(scene["object"]["center"]), axis=1)
    sel = np.flatnonzero(d < within)
    p, n = c.points[sel].astype(np.float64), c.normals[sel].astype(np.float64)
    tr = smi.Tracer(seed=7)
    t0 = time.process_time()
    lw, vw, _ = tr.radiance(full, p + 2e-3 * n, -n, spp, "oracle")
    le, ve, _ = tr.radiance(room, p + 2e-3 * n, -n, spp, "oracle")
    print(f"{len(sel)} points within {within} m, {spp} spp, {time.process_time() - t0:.1f} CPU s")
    for r0, r1 in BINS:
        m = (d[sel] >= r0) & (d[sel] < r1)
        if m.any():
            print(f"{r0}-{r1} m: {m.sum()} points, L_with / L_without {lum(lw[m]).sum() / lum(le[m]).sum():.4f}")
    cols = c.colors.astype(np.float64)
    cols[sel] = np.maximum(cols[sel] + (lw - le), 0.0)
    c.colors = cols.astype(np.float32)
    out.mkdir(parents=True, exist_ok=True)
    write_cloud(out / "cloud.ply", c)
    np.savez(out / "oracle.npz", sel=sel, lw=lw, le=le, vw=vw, ve=ve)
    print(f"wrote {out / 'cloud.ply'}")


def compare(scene_dir: Path, out: Path, bsh_path: Path, view: str) -> None:
    from pipeline import io
    from pipeline.relight import room_shadow as rs
    from pipeline.relight.relight import RelightConfig, run_relight
    from pipeline.runtime import setup_logging

    setup_logging(-1)
    cap: dict = {}
    darken = rs.darken_room

    def keep(ctx, room, room_splat, merged, msplat, params, bsh, *a, **k):
        res, st = darken(ctx, room, room_splat, merged, msplat, params, bsh, *a, **k)
        off = params.object_first - len(room)
        cap.update(old=room["color"].copy(), new=res["color"][off:off + len(room)].copy(), bsh=bsh, room=room)
        return res, st

    rs.darken_room = keep
    try:
        st = run_relight(bsh_path, out / f"relight_{view}", RelightConfig(brdf="lambert", albedo=(0.8, 0.8, 0.8)),
                         scene_path=scene_dir / "scene.json", view=view)
    finally:
        rs.darken_room = darken
    print(st["decisions"]["room_shadow"])
    o = np.load(out / "oracle.npz")
    b, room = cap["bsh"], cap["room"]
    leaf = np.flatnonzero((room["right"] == 0xFFFFFFFF) & (np.asarray(b["count"]) == 1))
    leaf_of = dict(zip(np.asarray(b["order"])[np.asarray(b["first"])[leaf]].tolist(), leaf.tolist()))
    have = np.array([q in leaf_of for q in o["sel"]])
    li = np.array([leaf_of[q] for q in o["sel"][have]])
    old, new = lum(cap["old"][li]), lum(cap["new"][li])
    centre = np.asarray(json.loads((scene_dir / "scene.json").read_text())["object"]["center"])
    d = np.linalg.norm(room["center"][li] - centre, axis=1)
    for r0, r1 in BINS:
        m = (d >= r0) & (d < r1)
        if m.any():
            print(f"{r0}-{r1} m: {m.sum()} leaves, relight {new[m].sum() / old[m].sum():.4f}, "
                  f"Mitsuba {lum(o['lw'][have][m]).sum() / lum(o['le'][have][m]).sum():.4f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("action", choices=("make", "compare"))
    ap.add_argument("scene", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--within", type=float, default=6.0)
    ap.add_argument("--spp", type=int, default=1024)
    ap.add_argument("--material", default="lambert")
    ap.add_argument("--bsh", type=Path)
    ap.add_argument("--view", default="view2")
    a = ap.parse_args()
    if a.action == "make":
        make(a.scene, a.out, a.within, a.spp, a.material)
    else:
        compare(a.scene, a.out, a.bsh, a.view)


if __name__ == "__main__":
    main()
