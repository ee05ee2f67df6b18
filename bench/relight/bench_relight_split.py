"""Where does relight's bias against the path-traced gather come from? (issue 14, relight-acc)

    .venv/bin/python -m bench.relight.bench_relight_split [SCENE_DIR] [--view view1] [--bsh bsh.npz] [--m 16]
        [--disc-cone R] [--stop-multiple K] [--step 8] [--dirs 1024] [--label NAME] [--out bench/relight/relight_split_small.csv]

Three Lambert (albedo 0.8) estimates at the same G-buffer receivers (every ``step``-th covered pixel):

* ``truth``: ``truth/gather_<view>_lambert.exr`` (Mitsuba, room without the object);
* ``E1``: the TRUE room geometry (Mitsuba ``ray_intersect``, no object) with the radiance of the hit taken
  from the nearest front-facing ``cloud_gt.ply`` point — ``dirs`` jittered cosine-weighted rays per
  receiver. E1/truth tests the cloud's radiance (and the reference); PBGI/E1 tests the splat model alone;
* ``PBGI``: ``relight`` (classic) on the BSH of ``cloud_gt.ply``.

Then the cloud is split into radiance classes (luminance bins ``--bins``) and relight is rerun with every
node's colour replaced by the mean over its points of the class-restricted colour (same tree, same cut,
same occlusion), so PBGI's class share can be set against E1's (rays whose nearest point is in the class).
Rows: class, points, E1 share of the total, PBGI/E1 of the class, PBGI excess in % of the E1 total.
A bsh.npz without ``splat_radius`` (written before build-bsh had it) is splatted at its bounding radii.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]

from pipeline import gl, io  # noqa: E402
from pipeline.scene import mitsuba_render as smi  # noqa: E402
from pipeline.gather.walk import tangent_frame  # noqa: E402
from pipeline.camera import Camera  # noqa: E402
from pipeline.relight.gbuffer import place_parts, render_gbuffer  # noqa: E402
from pipeline.relight.relight import RelightConfig, run_relight  # noqa: E402
from pipeline.runtime import setup_logging  # noqa: E402

from bench.benchlib import truth_bsh

ALBEDO = 0.8


def e1_gather(scene_dir: Path, scene: dict, pos: np.ndarray, nrm: np.ndarray, cloud: io.Cloud, dirs: int,
              seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(E1 (K,3), index of the cloud point each ray took (K, dirs)): Lambert gather of the true room."""
    from scipy.spatial import cKDTree

    mi = smi.mitsuba()
    room = smi.load_room(scene_dir, scene, {"type": "path"})
    cp, cn, cc = (np.asarray(x, np.float64) for x in (cloud.points, cloud.normals, cloud.colors))
    tree = cKDTree(cp)
    rng = np.random.default_rng(seed)
    n1 = int(np.sqrt(dirs))
    grid = (np.stack(np.meshgrid(np.arange(n1), np.arange(n1)), -1).reshape(-1, 2) + 0.5) / n1
    t, b = tangent_frame(nrm)
    E1 = np.zeros((len(pos), 3))
    picks = np.zeros((len(pos), len(grid)), np.int64)
    for i in range(len(pos)):
        u = (grid + rng.uniform(-0.5 / n1, 0.5 / n1, grid.shape)) % 1.0
        r, ph = np.sqrt(u[:, 0]), 2 * np.pi * u[:, 1]
        d = (r * np.cos(ph))[:, None] * t[i] + (r * np.sin(ph))[:, None] * b[i] + np.sqrt(1 - u[:, :1]) * nrm[i]
        o = pos[i] + 1e-4 * nrm[i]
        si = room.ray_intersect(mi.Ray3f(mi.Point3f(*[np.full(len(d), float(x)) for x in o]), mi.Vector3f(*d.T.copy())))
        hit = np.asarray(si.p).T.astype(np.float64)
        valid = np.asarray(si.is_valid()).astype(bool)
        _, kk = tree.query(hit, k=16)
        front = (cn[kk] * (-d[:, None, :])).sum(-1) > 0          # a point facing the ray
        pick = kk[np.arange(len(d)), np.argmax(front, 1)]
        picks[i] = np.where(valid, pick, -1)
        E1[i] = ALBEDO * np.where(valid[:, None], cc[pick], 0.0).mean(0)
    return E1, picks


def class_bsh(bsh_path: Path, points: np.ndarray, colors: np.ndarray, keep: np.ndarray, out: Path) -> Path:
    """The BSH with every node's colour = mean over its points of colour·keep (same tree); its emitters
    (build-bsh ``--emitters``: one point each, found by position) stay out of the node colours and keep
    their radiance only when their point's colour is in the class (``keep``)."""
    from scipy.spatial import cKDTree

    d = io.read_npz(bsh_path, "pcrelight.bsh/1")
    emit_pts = np.zeros(len(d["order"]), bool)                # by sorted position
    if "emitters" in d and len(d["emitters"]):
        dist, j = cKDTree(np.asarray(points, np.float64)).query(d["emitters"][:, :3].astype(np.float64))
        if np.any(dist > 1e-4):
            raise ValueError("an emitter is not a cloud point (a voxel of several points)")
        inv = np.empty(len(d["order"]), np.int64)
        inv[d["order"]] = np.arange(len(d["order"]))
        emit_pts[inv[j]] = True
        em = d["emitters"].copy()
        em[:, 8:11] *= keep[j][:, None]
        d["emitters"] = em
    c = np.asarray(colors, np.float64)[d["order"]] * (keep[d["order"]] * ~emit_pts)[:, None]
    cs = np.concatenate([np.zeros((1, 3)), np.cumsum(c, 0)])
    f, n = d["first"], d["count"]
    col = ((cs[f + n] - cs[f]) / n[:, None]).astype(np.float32)
    nodes = d["nodes"].copy()
    nodes["color"] = col
    d.update(nodes=nodes, color=col)
    io.write_npz(out, "pcrelight.bsh/1", **{k: v for k, v in d.items() if k != "schema"})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path, nargs="?", default=ROOT / "data_samples")
    ap.add_argument("--view", default="view1")
    ap.add_argument("--bsh", type=Path)
    ap.add_argument("--m", type=int, default=16)
    ap.add_argument("--disc-cone", type=float, default=None)
    ap.add_argument("--stop-multiple", type=float, default=None)
    ap.add_argument("--step", type=int, default=8)
    ap.add_argument("--dirs", type=int, default=1024)
    ap.add_argument("--bins", default="3,30,1000", help="luminance class edges")
    ap.add_argument("--out", type=Path, default=HERE / "relight_split_small.csv")
    ap.add_argument("--label", default="", help="a name for the BSH/model in the CSV")
    ap.add_argument("--work", type=Path, default=ROOT / "bench" / "_work" / "relight_split")
    a = ap.parse_args()
    setup_logging(-1)
    bsh = truth_bsh(a.scene, a.bsh, a.work)
    scene_path = a.scene / "scene.json"
    scene = io.read_json(scene_path)
    kw = dict(brdf="lambert", albedo=(ALBEDO,) * 3, microbuffer=a.m)
    if a.disc_cone is not None:
        kw["disc_cone"] = a.disc_cone
    if a.stop_multiple is not None:
        kw["stop_multiple"] = a.stop_multiple
    cfg = RelightConfig(**kw)
    cfg.check()
    v = scene["views"][a.view]                           # relight's camera and object for --scene/--view
    cam = Camera(*(np.asarray(v[k], np.float64) for k in ("eye", "target", "up")), float(v["fov_deg"]),
                 tuple(int(x) for x in v["size"]))
    ctx = gl.create_context()
    gl.bind_dummy_framebuffer(ctx)
    gb = render_gbuffer(ctx, place_parts(io.read_object(a.scene / scene["object"]["file"]),
                                         scene["object"].get("to_world")), cam)
    ctx.release()
    flat = np.flatnonzero(gb["mask"].reshape(-1))[::a.step]
    pos = gb["position"].reshape(-1, 3)[flat].astype(np.float64)
    nrm = gb["normal"].reshape(-1, 3)[flat].astype(np.float64)
    cloud = io.read_cloud(a.scene / "cloud_gt.ply")
    E1, picks = e1_gather(a.scene, scene, pos, nrm, cloud, a.dirs)
    truth = io.read_image(a.scene / "truth" / f"gather_{a.view}_lambert.exr")[..., :3].reshape(-1, 3)[flat]

    def pbgi(b: Path, tag: str) -> np.ndarray:
        run_relight(b, a.work / tag, cfg, scene_path=scene_path, view=a.view)
        return io.read_image(a.work / tag / "relit.exr")[..., :3].reshape(-1, 3)[flat]

    full = pbgi(bsh, "all")
    lum = io.luminance(np.asarray(cloud.colors, np.float64))
    edges = [0.0, *(float(x) for x in a.bins.split(",")), np.inf]
    cc = np.asarray(cloud.colors, np.float64)
    rows = [{"label": a.label, "view": a.view, "m": a.m, "class": "all", "points": len(lum), "e1_share": 1.0,
             "pbgi_over_e1": round(float(full.mean() / E1.mean()), 4), "excess_pct_of_total": round(100 * (full.mean() / E1.mean() - 1), 2),
             "e1_over_truth": round(float(E1.mean() / truth.mean()), 4), "pbgi_over_truth": round(float(full.mean() / truth.mean()), 4),
             "receivers": len(flat), "dirs": a.dirs}]
    for lo, hi in zip(edges[:-1], edges[1:]):
        keep = (lum >= lo) & (lum < hi)
        ok = picks >= 0
        e1c = ALBEDO * np.where((ok & keep[np.maximum(picks, 0)])[..., None], cc[np.maximum(picks, 0)], 0).mean(1)
        pc = pbgi(class_bsh(bsh, cloud.points, cc, keep.astype(np.float64), a.work / "class.npz"), f"class_{lo:g}")
        share = float(e1c.mean() / E1.mean())
        rows.append({"label": a.label, "view": a.view, "m": a.m, "class": f"lum [{lo:g}, {hi:g})", "points": int(keep.sum()),
                     "e1_share": round(share, 4),
                     "pbgi_over_e1": round(float(pc.mean() / e1c.mean()), 4) if e1c.mean() > 0 else float("nan"),
                     "excess_pct_of_total": round(100 * float((pc.mean() - e1c.mean()) / E1.mean()), 2),
                     "e1_over_truth": "", "pbgi_over_truth": "", "receivers": len(flat), "dirs": a.dirs})
    for r in rows:
        print(r, flush=True)
    write_header = not a.out.exists()
    with open(a.out, "a", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        if write_header:
            w.writeheader()
        w.writerows(rows)
    print(f"appended to {a.out}")


if __name__ == "__main__":
    main()
