"""relight against the path tracer that made the references (issue 23, item 4): wall time against 4×4-block
error on the shipped scene, and the speed ratio at equal error.

    .venv/bin/python -m bench.peers.bench_vs_pathtracer [SCENE_DIR] [--views view1,view2] [--materials lambert,ggx0.25]
        [--spp 16,64,256,1024] [--poisson-spp 16,64,256] [--presets default,fast,balanced,exact]
        [--methods mipmapped,hybrid,importance,envmap] [--repeat 2]
        [--out bench/peers/vs_pathtracer_small] [--plot-only] [--scale 4]

SCENE_DIR is a make-scene output (default ``data_samples/``: scene.json, cloud_gt.ply,
truth/full_<view>_<material>[_var].exr). Every render is a whole process, timed from the outside as a user
would run it (Python start-up, imports, JIT, scene/BSH load, render, EXR write), ``--repeat`` times in
interleaved rounds (all renders once, then all again); ``seconds`` = the fastest, ``seconds_max`` = the
slowest, ``cpu_seconds`` = the least CPU time (user + system, every thread of the process; less sensitive to
other jobs on a shared machine, and ``speed_ratio_cpu`` is the equal-error ratio on it). Images are deterministic (fixed seeds), so the error is that of any repeat.

- **Mitsuba 3** (``llvm_ad_rgb``): ``bench_vs_pathtracer.py mitsuba-render`` — a ~20-line script through the
  functions that made the references (``smi.load_room`` with the object and ``smi.material_bsdf`` of the
  material, ``make_scene.view_camera``, ``camera.camera_rays``, ``smi.object_mask``, ``Tracer.radiance``): the
  same estimator, the same pixel-centre rays, the same integrator (``path``, max_depth −1, rr_depth 5), an
  independent seed. It shades the **object's pixels only** (the pixels relight shades, and the ones the
  error is measured on); a frame with the room behind costs ~1/coverage more (28 % of view1, 5 % of view2).
  Its error against the reference = its own noise + the reference's noise (same estimator, no bias).
- **Mitsuba 3 on the scan** (``mitsuba-poisson``; the peer a user with only the scan would choose):
  ``bench_vs_pathtracer.py poisson-mesh`` makes Open3D's screened Poisson surface of cloud_gt.ply once (depth 9,
  the 2 % least-supported vertices trimmed; timed as its own row like build-bsh), each vertex the inverse-distance
  radiance of its 4 nearest points; ``poisson-render`` path-traces the object (its material) lit by that surface as
  an emitter of the scan's radiance with a black BSDF, the same rays and integrator as above (``--poisson-spp``).
  Its error has a floor: the surface's radiance and shape are the scan's, smoothed.
- **relight**: ``cli.py relight`` with its defaults and ``--preset fast|balanced|exact``, the material as
  scene.json (Lambert 0.8; GGX α = roughness², F = 1, separable Smith masking), on a BSH built once from
  cloud_gt.ply with build-bsh defaults (build time reported separately, row ``build-bsh``). ``--methods``: one more
  relight row per other gatherer (``relight --method X`` with relight's other defaults; options ``method X``),
  so that the plot shows every gatherer beside Mitsuba 3 from the same run (classic is the ``default`` row).

Error (``pipeline.metrics.compare_to_reference``, block 4: 4×4 blocks entirely on the object; relight: its
alpha ∧ the reference's): ``mean_ratio`` = Σ est / Σ ref, ``block_rms`` = ‖est − ref‖ / ‖ref‖ on block
means, ``ref_block_noise`` = the reference's own block noise (from ``_var.exr``), ``est_block_noise`` =
Mitsuba's own block noise (its variance of the mean), ``block_rms_corrected`` = √(rms² − ref² − est²)
(the error against the noise-free truth).

``--scale s``: relight (``--size``) and Mitsuba render at s× the views' size; each of the reference's pixels is
then compared with the mean of its s×s rendered pixels (alpha: all of them on the object; Mitsuba's variance of
that mean = its pixels' / s²), so the 4×4 blocks are the reference's, (4·s)² rendered pixels. A reference at the
rendered size (4×4 rendered pixels a block): a SCENE_DIR whose scene.json views have that size and whose
truth/full_<view>_<material>[_var].exr were path-traced at it, e.g. by ``mitsuba-render --spp 16384 --seed 2026``.

Speed ratio per relight row: ``mitsuba_s_at_equal_error`` = Mitsuba's time interpolated (log–log, between
the neighbouring spp) at relight's block RMS on that view × material's curve; ``speed_ratio`` = that / relight's
seconds (> 1: relight is faster). Outside the measured curve it is a bound (``ratio_note``). A second,
model-based ratio against the noise-free truth: Mitsuba's own block noise ∝ 1/√spp, its time a + b·spp
(least squares over the measured spp), solved for relight's noise-corrected error
(``speed_ratio_vs_truth``).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]

from bench.benchlib import material_args

PRESET_ARGS = {"default": [], "fast": ["--preset", "fast"], "balanced": ["--preset", "balanced"],
               "exact": ["--preset", "exact"]}
METHOD_MARKS = {"mipmapped": "D", "hybrid": "P", "importance": "^", "envmap": "X"}   # plot markers of --methods rows


# --------------------------------------------------------------------------- the timed Mitsuba process
def mitsuba_render(scene_dir: Path, view: str, mat: str, spp: int, out: Path, seed: int, frame: bool,
                   scale: int = 1) -> None:
    """The object in the room from ``view`` at ``spp`` paths a pixel, as the references were made
    (make_scene.render_view's full_* branch), with an independent seed, at ``scale``× the view's size; writes
    out (RGBA, alpha = the object's mask) and out_var.exr."""
    import numpy as np

    from pipeline import camera, io
    from pipeline.scene import mitsuba_render as smi
    from pipeline.scene.make_scene import view_camera

    scene = json.loads((scene_dir / "scene.json").read_text())
    v = scene["views"][view]
    v = {**v, "size": [int(x) * scale for x in v["size"]]}
    w, h = v["size"]
    tracer = smi.Tracer(seed, threads=smi.env_threads())
    full = smi.load_room(scene_dir, scene, scene["integrator"], scene["object"],
                         smi.material_bsdf(scene["materials"][mat]))
    M, K = view_camera(v)
    o, d = camera.camera_rays(M, K, (w, h))
    mask = smi.object_mask(tracer, smi.load_object_only(scene_dir, scene["object"]), o, d)
    sel = np.ones_like(mask) if frame else mask
    rgb, var = np.zeros((len(o), 3)), np.zeros((len(o), 3))
    rgb[sel], var[sel], _ = tracer.radiance(full, o[sel], d[sel], spp, f"bench-vs-pathtracer/{view}/{mat}/{spp}")
    a = mask.astype(np.float64)[:, None]
    io.write_image(out, np.concatenate([rgb, a], 1).reshape(h, w, 4).astype(np.float32))
    io.write_image(out.with_name(out.stem + "_var.exr"), var.reshape(h, w, 3).astype(np.float32))


# --------------------------------------------------------------------------- the scan-only peer
def poisson_mesh(scene_dir: Path, out: Path, depth: int = 9, trim: float = 0.02) -> None:
    """What a user with only the scan would path-trace: Open3D's screened Poisson surface of cloud_gt.ply (octree
    ``depth``; the vertices of the lowest ``trim`` share of sample density removed: Poisson's closure over holes),
    each vertex's radiance the inverse-distance mean of its 4 nearest cloud points (linear RGB, the scan's HDR
    radiance: what the room sends, every bounce included). Written as an NPZ (vertices, faces, radiance)."""
    import numpy as np
    import open3d as o3d
    from scipy.spatial import cKDTree

    from pipeline import io

    cl = io.read_cloud(scene_dir / "cloud_gt.ply")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cl.points.astype(np.float64)))
    pcd.normals = o3d.utility.Vector3dVector(cl.normals.astype(np.float64))
    mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=depth)
    dens = np.asarray(dens)
    mesh.remove_vertices_by_mask(dens < np.quantile(dens, trim))
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.triangles)
    dist, idx = cKDTree(cl.points).query(v, k=4)
    w = 1.0 / np.maximum(dist, 1e-9)
    rad = (cl.colors[idx] * w[..., None]).sum(1) / w.sum(1, keepdims=True)
    np.savez(out, vertices=v.astype(np.float32), faces=f.astype(np.uint32), radiance=rad.astype(np.float32))


def poisson_render(scene_dir: Path, mesh_npz: Path, view: str, mat: str, spp: int, out: Path, seed: int) -> None:
    """The object (its material) lit by the Poisson surface of the scan as an emitter of the scan's radiance
    (black: it does not reflect, its radiance already holds every bounce), path-traced by Mitsuba 3 as
    :func:`mitsuba_render` (same camera rays, object pixels only, same integrator)."""
    import numpy as np

    from pipeline import camera, io
    from pipeline.scene import mitsuba_render as smi
    from pipeline.scene.make_scene import view_camera

    scene = json.loads((scene_dir / "scene.json").read_text())
    v = scene["views"][view]
    w, h = v["size"]
    tracer = smi.Tracer(seed, threads=smi.env_threads())
    mi = smi.mitsuba()
    z = np.load(mesh_npz)
    V, F, R = z["vertices"], z["faces"], z["radiance"]
    props = mi.Properties()
    # the scan mesh: an emitter of its vertex radiance with a black BSDF (its radiance holds every bounce)
    props["emitter"] = mi.load_dict({"type": "area", "radiance": {"type": "mesh_attribute", "name": "vertex_color"}})
    props["bsdf"] = mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}})
    mesh = mi.Mesh("scan", len(V), len(F), props, has_vertex_normals=False)
    mesh.add_attribute("vertex_color", 3, mi.Float(R.ravel().astype(np.float32)))
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(V.ravel().astype(np.float32))
    params["faces"] = mi.UInt32(F.ravel().astype(np.uint32))
    params.update()
    full = mi.load_dict({"type": "scene", "integrator": dict(scene["integrator"]), "scan": mesh,
                         "object": mi.load_dict(smi.object_shape(scene_dir, scene["object"],
                                                                 smi.material_bsdf(scene["materials"][mat])))})
    M, K = view_camera(v)
    o, d = camera.camera_rays(M, K, (w, h))
    mask = smi.object_mask(tracer, smi.load_object_only(scene_dir, scene["object"]), o, d)
    rgb, var = np.zeros((len(o), 3)), np.zeros((len(o), 3))
    rgb[mask], var[mask], _ = tracer.radiance(full, o[mask], d[mask], spp, f"bench-vs-pathtracer/poisson/{view}/{mat}/{spp}")
    a = mask.astype(np.float64)[:, None]
    io.write_image(out, np.concatenate([rgb, a], 1).reshape(h, w, 4).astype(np.float32))
    io.write_image(out.with_name(out.stem + "_var.exr"), var.reshape(h, w, 3).astype(np.float32))


# --------------------------------------------------------------------------- measuring
def timed(cmd: list[str]) -> tuple[float, float]:
    """(wall seconds, CPU seconds of the process and its threads: user + system from its rusage)."""
    import resource

    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime


def to_reference_grid(img, var, s: int):
    """An estimate rendered at ``s``× the reference's side on the reference's pixels: RGB the mean of each s×s
    block of pixels, alpha 1 where all of them are on the object, the variance of that mean (the pixels'
    independent: their mean variance / s²)."""
    import numpy as np

    H, W = img.shape[0] // s, img.shape[1] // s
    blk = img.reshape(H, s, W, s, -1)
    out = blk.mean((1, 3))
    out[..., 3] = (blk[..., 3] > 0.5).all((1, 3))
    return out, None if var is None else var.reshape(H, s, W, s, -1).mean((1, 3)) / (s * s)


def measure(img_path: Path, scene: Path, view: str, mat: str, est_var_path: Path | None) -> dict:
    from pipeline import io
    from pipeline.metrics import compare_to_reference

    img = io.read_image(img_path)
    ref = io.read_image(scene / "truth" / f"full_{view}_{mat}.exr")
    var = io.read_image(scene / "truth" / f"full_{view}_{mat}_var.exr")
    ev = io.read_image(est_var_path) if est_var_path is not None else None
    if img.shape[:2] != ref.shape[:2]:      # --scale: measured on the reference's pixels
        s = img.shape[0] // ref.shape[0]
        if s < 2 or img.shape[:2] != (ref.shape[0] * s, ref.shape[1] * s):
            raise SystemExit(f"{img_path}: {img.shape[1]}x{img.shape[0]} is not a multiple of the reference's "
                             f"{ref.shape[1]}x{ref.shape[0]}")
        img, ev = to_reference_grid(img, ev, s)
    sel = (img[..., 3] > 0.5) & (ref[..., 3] > 0.5)
    c = compare_to_reference(img, ref, sel, ref_var=var, est_var=ev, block=4)
    return {"mean_ratio": round(c["mean_ratio_block"], 4), "block_rms": round(c["rms_block"], 4),
            "ref_block_noise": round(c["ref_noise_block"], 4),
            "est_block_noise": round(c["est_noise_block"], 4) if ev is not None else "",
            "block_rms_corrected": round(c["rms_corrected_block"], 4), "n_blocks": c["n_blocks"]}


def _interp_log(x: float, xs: list[float], ys: list[float]) -> float:
    """y at x on the piecewise log–log line through (xs, ys) (xs in the order of the curve)."""
    for (x0, y0), (x1, y1) in zip(zip(xs, ys), zip(xs[1:], ys[1:])):
        if min(x0, x1) <= x <= max(x0, x1) and x0 != x1:
            f = (math.log(x) - math.log(x0)) / (math.log(x1) - math.log(x0))
            return math.exp(math.log(y0) + f * (math.log(y1) - math.log(y0)))
    return float("nan")


def speed_ratios(rows: list[dict]) -> None:
    """Adds the equal-error columns to the relight rows (see the module docstring); with ``cpu_seconds`` in the
    rows, ``speed_ratio_cpu`` too (the same interpolation on CPU seconds: less sensitive to other jobs)."""
    for r in rows:
        if r["renderer"] != "relight":
            continue
        pp = sorted((x for x in rows if x["renderer"] == "mitsuba-poisson" and x["view"] == r["view"]
                     and x["material"] == r["material"]), key=lambda x: x["spp"])
        if pp:
            best = min(x["block_rms"] for x in pp)
            if r["block_rms"] < best:
                r["poisson_note"] = (f"the scan-only peer never reaches relight's error (its best {best:.3f} at "
                                     f"{pp[-1]['spp']} spp; mean ratio {pp[-1]['mean_ratio']:.3f})")
            else:
                ts, es = [x["seconds"] for x in pp], [x["block_rms"] for x in pp]
                t = _interp_log(r["block_rms"], es, ts) if min(es) <= r["block_rms"] <= max(es) else ts[0]
                r["poisson_s_at_equal_error"] = round(t, 2)
                r["speed_ratio_poisson"] = round(t / r["seconds"], 3)
                r["poisson_note"] = "interpolated" if min(es) <= r["block_rms"] <= max(es) else "at most this"
    for r in rows:
        if r["renderer"] != "relight":
            continue
        mi = sorted((x for x in rows if x["renderer"] == "mitsuba" and x["view"] == r["view"]
                     and x["material"] == r["material"]), key=lambda x: x["spp"])
        if not mi:
            continue
        es = [x["block_rms"] for x in mi]
        e = r["block_rms"]
        for key, suffix in (("seconds", ""), ("cpu_seconds", "_cpu")):
            if any(x.get(key, "") == "" for x in mi) or r.get(key, "") == "":
                continue
            ts = [x[key] for x in mi]
            if e > max(es):
                t, note = ts[0], f"Mitsuba's {mi[0]['spp']} spp is already more accurate: ratio is at most this"
            elif e < min(es):
                t, note = ts[-1], f"more accurate than Mitsuba at {mi[-1]['spp']} spp: ratio is at least this"
            else:
                t, note = _interp_log(e, es, ts), "interpolated"
            r[f"mitsuba_s_at_equal_error{suffix}"] = round(t, 2)
            r[f"speed_ratio{suffix}"] = round(t / r[key], 3)
            r["ratio_note"] = note
        ts = [x["seconds"] for x in mi]
        # model: Mitsuba's own block noise ∝ 1/√spp, time a + b·spp
        n = len(mi)
        sx, sy = sum(x["spp"] for x in mi), sum(ts)
        sxx, sxy = sum(x["spp"] ** 2 for x in mi), sum(x["spp"] * t_ for x, t_ in zip(mi, ts))
        b = (n * sxy - sx * sy) / max(n * sxx - sx * sx, 1e-30)
        a = (sy - b * sx) / n
        k = mi[-1]["est_block_noise"] * math.sqrt(mi[-1]["spp"])
        ec = r["block_rms_corrected"]
        if ec > 0 and k > 0:
            spp = (k / ec) ** 2
            r["mitsuba_spp_vs_truth"] = round(spp, 1)
            r["speed_ratio_vs_truth"] = round((a + b * max(spp, 1.0)) / r["seconds"], 3)


# --------------------------------------------------------------------------- plot
def plot(rows: list[dict], png: Path, title: str = "data_samples 128²") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8.5, 6))
    keys = sorted({(r["view"], r["material"]) for r in rows if r["renderer"] not in ("build-bsh", "poisson-mesh")})
    marks = {"default": "o", "fast": "v", "balanced": "s", "exact": "*", **{f"method {m}": k for m, k in METHOD_MARKS.items()}}
    for i, (view, mat) in enumerate(keys):
        col = f"C{i}"
        mi = sorted((r for r in rows if r["renderer"] == "mitsuba" and r["view"] == view and r["material"] == mat),
                    key=lambda r: r["spp"])
        if mi:
            ax.plot([r["seconds"] for r in mi], [r["block_rms"] for r in mi], "-", color=col, marker=".",
                    label=f"Mitsuba 3, {view} {mat}")
            for r in mi:
                ax.annotate(f"{r['spp']}", (r["seconds"], r["block_rms"]), fontsize=7, color=col,
                            xytext=(3, 3), textcoords="offset points")
            ax.axhline(mi[0]["ref_block_noise"], color=col, lw=0.6, ls=":")
        pp = sorted((r for r in rows if r["renderer"] == "mitsuba-poisson" and r["view"] == view
                     and r["material"] == mat), key=lambda r: r["spp"])
        if pp:
            ax.plot([r["seconds"] for r in pp], [r["block_rms"] for r in pp], "--", color=col, marker="x",
                    label=f"Mitsuba 3 on the scan's Poisson surface, {view} {mat}")
        for r in rows:
            if r["renderer"] == "relight" and r["view"] == view and r["material"] == mat:
                ax.plot(r["seconds"], r["block_rms"], marks.get(r["options"], "x"), color=col, ms=8, mfc="none")
    for name, m in marks.items():
        if any(r["renderer"] == "relight" and r["options"] == name for r in rows):
            ax.plot([], [], m, color="k", mfc="none", label=f"relight {name}" + (" (classic)" if name == "default" else ""))
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall time of the whole process [s] (min of repeats; 2 shared CPU cores)")
    ax.set_ylabel("4×4-block relative RMS against truth/full_* (object pixels)")
    ax.set_title(f"relight vs Mitsuba 3 (spp labelled; dashed: on the scan's Poisson surface), {title};\n"
                 "dotted: the reference's own block noise", fontsize=8)
    ax.grid(True, which="both", lw=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


# --------------------------------------------------------------------------- main
def read_csv(path: Path) -> list[dict]:
    with open(path) as f:
        return [{k: (v if k in ("renderer", "options", "view", "material", "size", "ratio_note", "poisson_note") or v == "" else
                     (int(v) if k in ("spp", "n_blocks") else float(v))) for k, v in r.items()}
                for r in csv.DictReader(f)]


FIELDS = ["renderer", "options", "view", "material", "size", "spp", "seconds", "seconds_max", "cpu_seconds",
          "mean_ratio", "block_rms", "ref_block_noise", "est_block_noise", "block_rms_corrected", "n_blocks",
          "mitsuba_s_at_equal_error", "speed_ratio", "mitsuba_s_at_equal_error_cpu", "speed_ratio_cpu", "ratio_note", "mitsuba_spp_vs_truth", "speed_ratio_vs_truth", "poisson_s_at_equal_error",
          "speed_ratio_poisson", "poisson_note"]


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "poisson-mesh":
        poisson_mesh(Path(sys.argv[2]), Path(sys.argv[3]))
        return
    if len(sys.argv) > 1 and sys.argv[1] == "poisson-render":
        ap = argparse.ArgumentParser(prog="bench_vs_pathtracer.py poisson-render")
        for k in ("--scene-dir", "--mesh", "--out"):
            ap.add_argument(k, type=Path, required=True)
        ap.add_argument("--view", required=True)
        ap.add_argument("--material", required=True)
        ap.add_argument("--spp", type=int, required=True)
        ap.add_argument("--seed", type=int, default=23)
        a = ap.parse_args(sys.argv[2:])
        poisson_render(a.scene_dir, a.mesh, a.view, a.material, a.spp, a.out, a.seed)
        return
    if len(sys.argv) > 1 and sys.argv[1] == "mitsuba-render":
        ap = argparse.ArgumentParser(prog="bench_vs_pathtracer.py mitsuba-render")
        ap.add_argument("--scene-dir", type=Path, required=True)
        ap.add_argument("--view", required=True)
        ap.add_argument("--material", required=True)
        ap.add_argument("--spp", type=int, required=True)
        ap.add_argument("--out", type=Path, required=True)
        ap.add_argument("--seed", type=int, default=23)
        ap.add_argument("--frame", action="store_true", help="shade every pixel (the room too), not only the object's")
        ap.add_argument("--scale", type=int, default=1, help="render at this many times the view's width and height")
        a = ap.parse_args(sys.argv[2:])
        mitsuba_render(a.scene_dir, a.view, a.material, a.spp, a.out, a.seed, a.frame, a.scale)
        return
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path, nargs="?", default=ROOT / "data_samples")
    ap.add_argument("--views", default="view1,view2")
    ap.add_argument("--materials", default="lambert,ggx0.25")
    ap.add_argument("--spp", default="16,64,256,1024")
    ap.add_argument("--presets", default="default,fast,balanced,exact")
    ap.add_argument("--methods", default="mipmapped,hybrid,importance,envmap",
                    help="the other gatherers, one relight row each with relight's defaults (empty: none)")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--out", type=Path, default=HERE / "vs_pathtracer_small", help="CSV/PNG stem")
    ap.add_argument("--work", type=Path, default=ROOT / "bench" / "_work" / "vs_pathtracer")
    ap.add_argument("--plot-only", action="store_true", help="re-plot (and re-print) the CSV")
    ap.add_argument("--poisson-spp", default="16,64,256",
                    help="spp of the scan-only peer (Poisson surface of the cloud as an emitter); empty: not run")
    ap.add_argument("--merge", action="store_true",
                    help="merge these renders into the existing CSV (same renderer/options/view/material replaced)")
    ap.add_argument("--scale", type=int, default=1,
                    help="render relight and Mitsuba at this many times the views' width and height (e.g. 4: 128² → "
                         "512²); the error is then measured on the reference's pixels (each the mean of its s×s "
                         "rendered pixels), its 4×4 blocks = (4·s)² rendered pixels")
    a = ap.parse_args()
    csv_path, png_path = a.out.with_suffix(".csv"), a.out.with_suffix(".png")
    scene = a.scene.resolve()
    if a.plot_only:
        rows = read_csv(csv_path)
    else:
        a.work.mkdir(parents=True, exist_ok=True)
        py, cli = sys.executable, str(ROOT / "cli.py")
        bsh = a.work / "bsh.npz"
        jobs: list[tuple[dict, list[str], Path, Path | None]] = []
        presets = [p for p in a.presets.split(",") if p]
        methods = [m for m in a.methods.split(",") if m]
        unknown = sorted(set(methods) - set(METHOD_MARKS))
        if unknown:
            raise SystemExit(f"--methods: unknown {', '.join(unknown)} (of {', '.join(METHOD_MARKS)})")
        if presets or methods or not bsh.exists():
            jobs.append(({"renderer": "build-bsh", "options": "defaults", "view": "", "material": ""},
                         [py, cli, "build-bsh", str(scene / "cloud_gt.ply"), "--out", str(bsh), "-q"], bsh, None))
        mesh = a.work / "poisson_mesh.npz"
        pspp = [int(x) for x in a.poisson_spp.split(",") if x]
        if pspp:
            jobs.append(({"renderer": "poisson-mesh", "options": "Open3D depth 9", "view": "", "material": ""},
                         [py, "-m", __spec__.name, "poisson-mesh", str(scene), str(mesh)], mesh, None))
        for view in a.views.split(","):
            for mat in a.materials.split(","):
                for spp in pspp:
                    out = a.work / f"poisson_{view}_{mat}_{spp}.exr"
                    jobs.append(({"renderer": "mitsuba-poisson", "options": f"{spp} spp, object pixels", "view": view,
                                  "material": mat, "spp": spp},
                                 [py, "-m", __spec__.name, "poisson-render", "--scene-dir", str(scene),
                                  "--mesh", str(mesh), "--view", view, "--material", mat, "--spp", str(spp),
                                  "--out", str(out)], out, out.with_name(out.stem + "_var.exr")))
                for spp in (int(s) for s in a.spp.split(",") if s):
                    out = a.work / f"mitsuba_{view}_{mat}_{spp}.exr"
                    jobs.append(({"renderer": "mitsuba", "options": f"{spp} spp, object pixels", "view": view,
                                  "material": mat, "spp": spp},
                                 [py, "-m", __spec__.name, "mitsuba-render", "--scene-dir", str(scene),
                                  "--view", view, "--material", mat, "--spp", str(spp), "--out", str(out)],
                                 out, out.with_name(out.stem + "_var.exr")))
                for p in presets:
                    out = a.work / f"relight_{view}_{mat}_{p}"
                    jobs.append(({"renderer": "relight", "options": p, "view": view, "material": mat},
                                 [py, cli, "relight", "--bsh", str(bsh), "--scene", str(scene / "scene.json"),
                                  "--view", view, "--out", str(out), "-q", *PRESET_ARGS[p], *material_args(mat)],
                                 out / "relit.exr", None))
                for m in methods:
                    out = a.work / f"relight_{view}_{mat}_{m}"
                    jobs.append(({"renderer": "relight", "options": f"method {m}", "view": view, "material": mat},
                                 [py, cli, "relight", "--bsh", str(bsh), "--scene", str(scene / "scene.json"),
                                  "--view", view, "--out", str(out), "-q", "--method", m, *material_args(mat)],
                                 out / "relit.exr", None))
        if a.scale > 1:
            views = json.loads((scene / "scene.json").read_text())["views"]
            for info, cmd, _, _ in jobs:
                if info["renderer"] in ("mitsuba", "mitsuba-poisson", "relight"):
                    w, h = (int(x) * a.scale for x in views[info["view"]]["size"])
                    info["size"] = f"{w}x{h}"
                    cmd += ["--scale", str(a.scale)] if info["renderer"] == "mitsuba" else ["--size", f"{w}x{h}"]
            if any(info["renderer"] == "mitsuba-poisson" for info, _, _, _ in jobs):
                raise SystemExit("--scale: the scan-only peer has no --scale; run it with --poisson-spp ''")
        else:
            views = json.loads((scene / "scene.json").read_text())["views"]
            for info, _, _, _ in jobs:
                if info["view"]:
                    info["size"] = "x".join(str(int(x)) for x in views[info["view"]]["size"])
        times: list[list[tuple[float, float]]] = [[] for _ in jobs]
        t_all = time.perf_counter()
        for rep in range(a.repeat):
            for i, (info, cmd, _, _) in enumerate(jobs):
                times[i].append(timed(cmd))
                print(f"[{rep + 1}/{a.repeat}] {info['renderer']} {info['options']} {info['view']} {info['material']}: "
                      f"{times[i][-1][0]:.2f} s ({times[i][-1][1]:.2f} CPU s; load {os.getloadavg()[0]:.1f})", flush=True)
        print(f"all renders: {time.perf_counter() - t_all:.0f} s wall")
        rows = []
        for (info, _, out, ev), ts in zip(jobs, times):
            row = {**info, "seconds": round(min(w for w, _ in ts), 2), "seconds_max": round(max(w for w, _ in ts), 2),
                   "cpu_seconds": round(min(c for _, c in ts), 2)}
            if info["renderer"] not in ("build-bsh", "poisson-mesh"):
                row.update(measure(out, scene, info["view"], info["material"], ev))
            rows.append(row)
        if a.merge and csv_path.exists():
            key = ("renderer", "options", "view", "material")
            new = {tuple(r[k] for k in key) for r in rows}
            rows = [r for r in read_csv(csv_path) if tuple(r[k] for k in key) not in new] + rows
            order = {"build-bsh": 0, "poisson-mesh": 0, "mitsuba": 1, "mitsuba-poisson": 2, "relight": 3}
            rows.sort(key=lambda r: (r["renderer"] not in ("build-bsh", "poisson-mesh"), r["view"], r["material"],
                                     order[r["renderer"]],
                                     r.get("spp") or 0))
        speed_ratios(rows)
        with open(csv_path, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=FIELDS, extrasaction="ignore")
            w.writeheader()
            w.writerows(rows)
        print(f"wrote {csv_path}")
    sizes = sorted({r["size"] for r in rows if r.get("size")})
    plot(rows, png_path, f"{scene.name} {a.views} {','.join(sizes)}"
         + (f", errors on the {a.scale}× smaller reference's pixels" if a.scale > 1 else ""))
    print(f"wrote {png_path}")
    print("\nspeed ratio at equal 4×4-block error (Mitsuba seconds at relight's error / relight seconds; > 1: relight faster)")
    for r in rows:
        if r["renderer"] == "relight" and r.get("speed_ratio", "") != "":
            print(f"  {r['view']} {r['material']:8s} relight {r['options']:9s} {r['seconds']:7.2f} s  block RMS "
                  f"{r['block_rms']:.4f}  Mitsuba {r['mitsuba_s_at_equal_error']:7.2f} s  ratio {r['speed_ratio']:.3f}"
                  f"  ({r['ratio_note']});  on CPU s {r.get('speed_ratio_cpu', '')};  vs truth (model) {r.get('speed_ratio_vs_truth', '')};  scan-only peer: "
                  f"{r.get('speed_ratio_poisson', '') or ''} {r.get('poisson_note', '')}")


if __name__ == "__main__":
    main()
