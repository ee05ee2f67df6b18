"""Table 3 equivalent (paper 000 §6.3): Classic / Mipmapped / Hybrid PBGI × viewport × micro-buffer ×
view — time, peak transform-feedback bytes, micro-buffer bytes, pairs, and error against classic at the
same micro-buffer. Writes bench/gatherers/relight_table3.csv (+ .json with the machine) and
bench/relight_table3.png.

Scene: the shipped ground truth when ``--scene-dir`` (default ``data_samples/``) holds ``scene.json``
and the HDR cloud ``cloud_gt.ply``: the scene's object is rasterised by ``pipeline.relight.gbuffer`` from
view1/view2 at size×size. Otherwise a synthetic closed room (coloured walls, a bright ceiling panel,
~20k points) with two built-in views and a sphere (radius 0.35 m) ray-cast analytically (45° field of
view). The BSH comes from build-bsh's ``build_bsh`` (default pruning). Lambert, albedo 0.8; the same
receivers for all three methods.

    .venv/bin/python -m bench.gatherers.bench_relight --quick          # 64², 128² × m 16, 24, 32 × view1, view2
    .venv/bin/python -m bench.gatherers.bench_relight --full           # 128²…1024² × 16, 24, 32 × view1, view2
    .venv/bin/python -m bench.gatherers.bench_relight                  # quick on llvmpipe, full on a GPU (make bench)

On Mesa llvmpipe (CPU GL, vertex/geometry stages single-threaded) the full grid takes hours; the
paper's numbers are GPU figures (GTX 1080).
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]

from bench.benchlib import sphere_gbuffer, synthetic_room

from pipeline import gl  # noqa: E402
from pipeline.gather import GATHERERS, GatherParams, Receivers  # noqa: E402

OUT = HERE


def shipped_scene(folder: Path):
    """(points, normals, colours, scene dict, folder, name) of a make-scene folder (``scene.json`` with
    views and an object, ``cloud_gt.ply`` — the HDR cloud), or None when the folder lacks them."""
    scene = folder / "scene.json"
    cloud_path = folder / "cloud_gt.ply"
    if not scene.exists() or not cloud_path.exists():
        return None
    from pipeline import io

    meta = io.read_json(scene)
    if not meta.get("views") or not (meta.get("object") or {}).get("file"):
        return None
    cloud = io.read_cloud(cloud_path)
    return cloud.points, cloud.normals, cloud.colors, meta, folder, f"{folder.name}/cloud_gt.ply"


def object_gbuffer(ctx, size: int, meta: dict, folder: Path, view: str):
    """The scene's object rasterised (pipeline.relight.gbuffer) from the view's camera at size×size (the
    view's field of view): (mask, position, normal, view dir, flat index), as run_relight does."""
    from pipeline import io
    from pipeline.camera import Camera
    from pipeline.relight.gbuffer import place_parts, render_gbuffer

    v = meta["views"][view]
    cam = Camera(np.asarray(v["eye"], np.float64), np.asarray(v["target"], np.float64),
                 np.asarray(v.get("up", [0, 1, 0]), np.float64), float(v.get("fov_deg", 45.0)), (size, size))
    obj = meta["object"]
    parts = place_parts(io.read_object(folder / obj["file"]), obj.get("to_world"))
    gb = render_gbuffer(ctx, parts, cam)
    gl.bind_dummy_framebuffer(ctx)
    mask = gb["mask"]
    flat = np.flatnonzero(mask.reshape(-1))
    P = np.ascontiguousarray(gb["position"].reshape(-1, 3)[flat], np.float32)
    N = np.ascontiguousarray(gb["normal"].reshape(-1, 3)[flat], np.float32)
    V = np.ascontiguousarray(gb["view"].reshape(-1, 3)[flat], np.float32)
    return mask, P, N, V, flat


def run_cell(ctx, nodes, nodes_cache, size, m, view, method, gbuf, budget_gib, omega_tr):
    mask, P, N, V, flat = gbuf
    n = len(flat)
    recv = Receivers(P, N, V, np.full((n, 3), 0.8, np.float32), np.zeros(n, np.float32), np.full(n, 0.5, np.float32))
    key = (m, method)
    if key not in nodes_cache:  # the gatherer of the table, as relight builds it (shaders compiled once)
        params = GatherParams(m, stop_multiple=4.0, omega_tr=omega_tr, memory_budget_bytes=budget_gib * 2 ** 30)
        nodes_cache[key] = GATHERERS[method](ctx, nodes, params)
    g = nodes_cache[key]
    t0 = time.perf_counter()
    rad, st = g.run(recv, flat, mask.shape)
    cut = st.get("cut", {})
    dt = time.perf_counter() - t0
    return rad, {"receivers": n, "time_s": dt, "cut_time_s": cut.get("time_s", 0.0),
                 "peak_tf_bytes": cut.get("peak_tf_bytes", 0), "microbuffer_bytes": st["microbuffer_bytes"],
                 "tiles": st["tiles"], "nodes_visited": st["nodes_visited"], "start_nodes": st["start_nodes"],
                 "tf_passes": cut.get("passes", 0), "iterations": cut.get("iterations", 0),
                 "pairs_total": int(sum(cut.get("pairs_per_iteration", []))),
                 "host_spills": cut.get("host_spills", 0)}


def plot(rows, path, device: str = "llvmpipe (CPU GL)"):
    """Time and peak transform-feedback bytes vs viewport: colour = method, line style = micro-buffer."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pipeline import io

    views = sorted({r["view"] for r in rows})
    colours = dict(zip(GATHERERS, ("tab:blue", "tab:red", "tab:green", "tab:purple", "tab:brown", "tab:olive")))
    styles = {16: ":", 24: "--", 32: "-"}
    fig, axes = plt.subplots(2, len(views), figsize=(6 * len(views), 7.5), squeeze=False)
    for col, view in enumerate(views):
        for method in GATHERERS:
            for m in sorted({int(r["m"]) for r in rows}):
                sel = sorted([r for r in rows if r["view"] == view and r["method"] == method and int(r["m"]) == m],
                             key=lambda r: int(r["size"]))
                if not sel:
                    continue
                x = [int(r["size"]) for r in sel]
                kw = dict(color=colours[method], ls=styles.get(m, "-"), marker="o", label=f"{method} m={m}")
                axes[0, col].plot(x, [1e3 * float(r["time_s"]) for r in sel], **kw)
                if any(float(r["peak_tf_bytes"]) > 0 for r in sel):   # the gatherers with a cut
                    axes[1, col].plot(x, [float(r["peak_tf_bytes"]) / 2 ** 20 for r in sel], **kw)
        for row, ylabel in ((0, "time [ms]"), (1, "peak transform-feedback [MiB]")):
            ax = axes[row, col]
            ax.set_xscale("log", base=2)
            ax.set_yscale("log")
            ax.set_xlabel("viewport side [pixels]")
            ax.set_ylabel(ylabel)
            ax.set_title(f"{view} — {device}")
            ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    io.save_figure(path, fig)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="64² and 128² × m 16, 24, 32 (llvmpipe-sized)")
    ap.add_argument("--full", action="store_true", help="128²…1024² × m 16, 24, 32 (default on a GPU; "
                    "without --quick/--full the grid follows the GL renderer: quick on llvmpipe)")
    ap.add_argument("--sizes", default="", help="viewport sides, comma separated (default 128,256,512,1024)")
    ap.add_argument("--microbuffers", default="", help="micro-buffer sides (default 16,24,32)")
    ap.add_argument("--views", default="view1,view2")
    ap.add_argument("--methods", default=",".join(GATHERERS))
    ap.add_argument("--omega-tr", type=float, default=32.0)
    ap.add_argument("--memory-budget", type=float, default=1.0, help="GiB")
    ap.add_argument("--points", type=int, default=20000, help="synthetic room points")
    ap.add_argument("--scene-dir", default=str(ROOT / "data_samples"),
                    help="make-scene folder (scene.json + cloud_gt.ply); the synthetic room when it lacks them")
    ap.add_argument("--out", default="", help="output stem (default bench/relight_table3, "
                    "bench/gatherers/relight_table3_gpu on a non-llvmpipe renderer)")
    ap.add_argument("--plot-only", action="store_true", help="redraw the PNG from an existing CSV")
    a = ap.parse_args(argv)
    out = Path(a.out or OUT / "relight_table3")
    if a.plot_only:
        with open(out.with_suffix(".csv")) as fh:
            rows = list(csv.DictReader(fh))
        meta = json.loads(out.with_suffix(".json").read_text()) if out.with_suffix(".json").exists() else {}
        plot(rows, out.with_suffix(".png"), (meta.get("gl") or {}).get("renderer", "?"))
        return
    ctx = gl.create_context()
    gl.bind_dummy_framebuffer(ctx)
    info = gl.context_info(ctx)
    cpu_gl = "llvmpipe" in str(info["renderer"]).lower()
    quick = a.quick or (cpu_gl and not a.full)
    if not a.out and not cpu_gl:
        out = OUT / "relight_table3_gpu"
    sizes = [int(s) for s in (a.sizes or ("64,128" if quick else "128,256,512,1024")).split(",")]
    ms = [int(s) for s in (a.microbuffers or "16,24,32").split(",")]
    views = a.views.split(",")
    methods = a.methods.split(",")

    sc = shipped_scene(Path(a.scene_dir))
    if sc is None:
        pts, nrm, col, view_defs, centre, scene_name = synthetic_room(a.points)
        meta = folder = None
    else:
        pts, nrm, col, meta, folder, scene_name = sc
    from pipeline.bsh.builder import build_bsh

    t0 = time.perf_counter()
    bsh = build_bsh(pts, nrm, col)
    nodes = bsh["nodes"]
    print(f"scene {scene_name}: {len(pts)} points → {len(nodes)} nodes ({time.perf_counter() - t0:.1f} s)", flush=True)
    print(f"GL: {info['renderer']} ({info['version']}); grid {sizes} × m {ms} × {views}", flush=True)
    rows = []
    cache: dict = {}
    for view in views:
        for size in sizes:
            if meta is None:
                gbuf = sphere_gbuffer(size, view_defs[view]["eye"], view_defs[view]["target"], centre)
            else:
                gbuf = object_gbuffer(ctx, size, meta, folder, view)
            for m in ms:
                ref = None
                for method in methods:
                    rad, st = run_cell(ctx, nodes, cache, size, m, view, method, gbuf, a.memory_budget, a.omega_tr)
                    if method == "classic":
                        ref = rad
                    err = float("nan")
                    if ref is not None and len(ref):
                        err = float(np.sqrt(np.mean((rad - ref) ** 2)) / max(np.sqrt(np.mean(ref ** 2)), 1e-30))
                    row = {"scene": scene_name, "view": view, "size": size, "m": m, "method": method,
                           "rel_rms_vs_classic": err, **st}
                    rows.append(row)
                    print(f"{view} {size}² m={m} {method:9s} P={st['receivers']:6d} {1e3 * st['time_s']:10.1f} ms  "
                          f"(cut {1e3 * st['cut_time_s']:8.1f} ms) tf {st['peak_tf_bytes'] / 2**20:7.2f} MiB  mb {st['microbuffer_bytes'] / 2**20:8.1f} MiB  "
                          f"err {err:.2e}", flush=True)
    with open(out.with_suffix(".csv"), "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0].keys()))
        w.writeheader()
        w.writerows(rows)
    with open(out.with_suffix(".json"), "w") as fh:
        json.dump({"gl": info, "scene": scene_name, "points": int(len(pts)), "nodes": int(len(nodes)),
                   "omega_tr": a.omega_tr, "memory_budget_gib": a.memory_budget, "quick": quick,
                   "sizes": sizes, "microbuffers": ms, "views": views}, fh, indent=1)
    plot(rows, out.with_suffix(".png"), info["renderer"])
    print(f"wrote {out.with_suffix('.csv')}, .json, .png")


if __name__ == "__main__":
    main()
