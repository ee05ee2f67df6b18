"""relight's error split by room surface: each mesh of a make-scene room alone lights the object, in Mitsuba 3 and
in relight, so that a surface the micro-buffers show too much or too little of cannot hide behind another's error.

    .venv/bin/python -m bench.relight.bench_surface_split SCENE_DIR --view view1 [--meshes floor,column_walls]
        [--cases '[{"stop_multiple": 1.0, "microbuffer": 32}]'] [--spp 256] --out bench/X.csv

For each mesh M (default: every non-emitting mesh of scene.json): the room's meshes all emit (area lights, no
reflection: albedo 0), M at radiance 1 and the others at 0.01 (a floor under the cloud's median, so that build-bsh's
relative thresholds stay defined), the object Lambert 0.8 in its place; Mitsuba renders the view with one bounce
(max_depth 2: camera → object → emitter, the object's own shadows included) at ``--spp`` (two halves with their own
seeds: the noise column is their half-difference over their mean). relight gets the scene's cloud_gt.ply with each
point recoloured the same way by its nearest mesh (Open3D's closest point), build-bsh's defaults, and Lambert 0.8
with ``bounces 0`` (its surfels black), ``room_shadow off`` and ``self_reflect off`` (the path tracer's room does not
reflect), plus each of ``--cases``' option sets. Columns: the relight / Mitsuba ratio of the object's summed radiance
(the relit image's alpha), and Mitsuba's mean and noise.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]

from bench.benchlib import material_kw, write_rows

FLOOR = 0.01


def nearest_mesh(scene_dir: Path, scene: dict, points: np.ndarray) -> np.ndarray:
    """(N,) index into scene["meshes"] of each point's nearest mesh."""
    import open3d as o3d
    import trimesh

    rs = o3d.t.geometry.RaycastingScene()
    for m in scene["meshes"]:
        t = trimesh.load(scene_dir / m["file"], process=False)
        rs.add_triangles(o3d.core.Tensor(np.asarray(t.vertices, np.float32)), o3d.core.Tensor(np.asarray(t.faces, np.uint32)))
    return rs.compute_closest_points(o3d.core.Tensor(np.asarray(points, np.float32)))["geometry_ids"].numpy().astype(np.int64)


def mitsuba_image(scene_dir: Path, scene: dict, view: str, lit: int, spp: int, seed: int) -> np.ndarray:
    """(H, W, 3): the view with mesh ``lit`` emitting 1, the others FLOOR, no reflection, the Lambert object."""
    from pipeline.scene import mitsuba_render as smi

    mi = smi.mitsuba()
    d = smi.room_dict(scene_dir, scene, {"type": "path", "max_depth": 2})
    for i, m in enumerate(scene["meshes"]):
        sh = d[f"m{i:03d}_{m['name']}"]
        sh["bsdf"] = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}
        sh["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": [1.0 if i == lit else FLOOR] * 3}}
    d["object"] = smi.object_shape(scene_dir, scene["object"], smi.material_bsdf({"type": "lambert", "albedo": 0.8}))
    v = scene["views"][view]
    w, h = v["size"]
    d["sensor"] = {"type": "perspective", "fov": float(v["fov_deg"]), "fov_axis": "y",
                   "to_world": mi.ScalarTransform4f().look_at(origin=v["eye"], target=v["target"], up=v["up"]),
                   "film": {"type": "hdrfilm", "width": int(w), "height": int(h), "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": int(spp)}}
    return np.asarray(mi.render(mi.load_dict(d), seed=seed), np.float64)[..., :3]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--view", default="view1")
    ap.add_argument("--meshes", default="")
    ap.add_argument("--cases", default="[]")
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()
    from pipeline import io
    from pipeline.io.clouds import read_cloud, write_cloud
    from pipeline.relight.relight import RelightConfig, run_relight
    from pipeline.runtime import setup_logging

    setup_logging(-1)
    scene = json.loads((a.scene / "scene.json").read_text())
    names = [m["name"] for m in scene["meshes"]]
    todo = a.meshes.split(",") if a.meshes else [m["name"] for m in scene["meshes"] if not any(e > 0 for e in m["emission"])]
    base = {"bounces": 0, "room_shadow": "off", "self_reflect": "off", "adaptive": 0}
    cases = [base] + [{**base, **c} for c in json.loads(a.cases)]
    cloud = read_cloud(a.scene / "cloud_gt.ply")
    owner = nearest_mesh(a.scene, scene, cloud.points)
    work = ROOT / "bench" / "_work" / "surface_split" / a.scene.name
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in todo:
        lit = names.index(name)
        ims = [mitsuba_image(a.scene, scene, a.view, lit, a.spp // 2, seed) for seed in (1, 2)]
        c = dataclasses.replace(cloud, colors=np.repeat(np.where(owner == lit, 1.0, FLOOR)[:, None], 3, 1).astype(np.float32))
        write_cloud(work / f"{name}.ply", c)
        subprocess.run([sys.executable, str(ROOT / "cli.py"), "build-bsh", str(work / f"{name}.ply"), "--out",
                        str(work / f"{name}_bsh.npz"), "-q"], check=True)
        for i, opts in enumerate(cases):
            out = work / f"{a.view}_{name}_{i}"
            cfg = RelightConfig(**opts, **material_kw("lambert"))
            run_relight(work / f"{name}_bsh.npz", out, cfg, scene_path=a.scene / "scene.json", view=a.view)
            img = io.read_image(out / "relit.exr")
            sel = img[..., 3] > 0.5
            s0, s1 = (float(x[sel].sum()) for x in ims)
            mts = (s0 + s1) / 2
            row = {"view": a.view, "mesh": name, "options": json.dumps({k: v for k, v in opts.items() if base.get(k) != v}),
                   "relight_over_mitsuba": round(float(img[sel][:, :3].sum()) / max(mts, 1e-300), 4),
                   "mitsuba_mean": round(mts / max(sel.sum() * 3, 1), 5), "mitsuba_noise": round(abs(s0 - s1) / 2 / max(mts, 1e-300), 4),
                   "spp": a.spp}
            rows.append(row)
            print(json.dumps(row), flush=True)
    write_rows(a.out, rows)


if __name__ == "__main__":
    main()
