"""Speed/accuracy trade of relight against the path-traced gather references (issue 7, "Measure" 2).

    .venv/bin/python bench/bench_relight_tradeoff.py [SCENE_DIR] [--quick | --full] [--plot-only]

SCENE_DIR (default data_samples/) is a make-scene output: scene.json, cloud_gt.ply and
truth/gather_<view>_<material>[_var].exr. The BSH is built from the exact HDR cloud with build-bsh's
defaults (t_c 0.01, t_n 0.98) and with pruning variants, so the numbers measure PBGI alone.

One knob at a time around a base point (hybrid, m = 16, Ω_tr = 32, stop multiple 4, default BSH):
method ∈ {classic, mipmapped}, m ∈ {8, 24, 32}, Ω_tr ∈ {8, 128}, stop multiple ∈ {1, 2, 8},
BSH (t_c, t_n) ∈ {(0, ·) = no pruning, (0.05, 0.98), (0.01, 0.9), (0.05, 0.9)}, plus a few combined
points along the front (m 32 + stop 2, m 24 + stop 2, m 8 + stop 8) and "model only what the scene
requires" rows (Lambert's default path vs the glossy code path: GGX roughness 1, metallic 0, same albedo).

--quick (default): view1, Lambert and GGX 0.25. --full: view1 + view2, all five materials.
Per row: wall seconds of run_relight (own GL context, G-buffer, walk, gather, writes; the fastest of
--repeat runs, default 2, the slowest in seconds_max; images identical across repeats), relative RMS over
the object pixels, the reference's own noise (√mean variance / RMS), the noise-corrected error
√(rel² − noise²), the ratio of means and nodes visited per pixel; `pareto` marks the rows on the
(seconds, noise-corrected error) front of their view × material. Writes bench/relight_tradeoff.csv and
bench/relight_tradeoff.png. Metrics and material definitions as bench_relight_truth.py (imported).
"""

from __future__ import annotations

import argparse
import csv
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from bench_relight_truth import material_kw  # noqa: E402
from pipeline import io  # noqa: E402
from pipeline.gather import GATHERERS  # noqa: E402
from pipeline.relight import PRESETS, RelightConfig, run_relight  # noqa: E402
from pipeline.runtime import setup_logging  # noqa: E402

BASE = dict(method="hybrid", microbuffer=16, omega_tr=32.0, stop_multiple=4.0)
BSH_DEFAULT = (0.01, 0.98)
BSH_VARIANTS = [(0.0, 0.98), (0.05, 0.98), (0.01, 0.9), (0.05, 0.9)]


def grid() -> list[tuple[str, dict, tuple[float, float]]]:
    """(knob label, relight overrides of BASE, (tc, tn)) — one knob at a time, then combined points."""
    g = [("base", {}, BSH_DEFAULT)]
    g += [(f"method={v}", {"method": v}, BSH_DEFAULT) for v in GATHERERS if v != BASE["method"]]
    g += [(f"m={v}", {"microbuffer": v}, BSH_DEFAULT) for v in (8, 24, 32)]
    g += [(f"omega_tr={v:g}", {"omega_tr": float(v)}, BSH_DEFAULT) for v in (8, 128)]
    g += [(f"stop={v:g}", {"stop_multiple": float(v)}, BSH_DEFAULT) for v in (1, 2, 8)]
    g += [(f"tc={tc:g},tn={tn:g}", {}, (tc, tn)) for tc, tn in BSH_VARIANTS]
    g += [("m=32,stop=2", {"microbuffer": 32, "stop_multiple": 2.0}, BSH_DEFAULT),
          ("m=24,stop=2", {"microbuffer": 24, "stop_multiple": 2.0}, BSH_DEFAULT),
          ("m=8,stop=8", {"microbuffer": 8, "stop_multiple": 8.0}, BSH_DEFAULT)]
    return g


def build_bsh(scene: Path, work: Path, tc: float, tn: float) -> tuple[Path, float]:
    out = work / f"bsh_tc{tc:g}_tn{tn:g}.npz"
    t0 = time.perf_counter()
    newest = max((scene / "cloud_gt.ply").stat().st_mtime, *(f.stat().st_mtime for f in (ROOT / "pipeline").glob("*bsh*.py")))
    if not out.exists() or out.stat().st_mtime < newest:   # rebuilt when the cloud or build-bsh's code is newer
        subprocess.run([sys.executable, str(ROOT / "cli.py"), "build-bsh", str(scene / "cloud_gt.ply"), "--out", str(out),
                        "--tc", str(tc), "--tn", str(tn), "-q"], check=True)
    return out, time.perf_counter() - t0


def measure(scene: Path, bsh: Path, out: Path, view: str, ref_mat: str, cfg: RelightConfig, repeat: int = 1) -> dict:
    """Relight ``repeat`` times (wall time = the minimum: the machine is shared, so the minimum is the
    least disturbed run; the image must be identical every time) and compare with the reference."""
    ref = io.read_image(scene / "truth" / f"gather_{view}_{ref_mat}.exr")
    var = io.read_image(scene / "truth" / f"gather_{view}_{ref_mat}_var.exr")
    cfg.check()
    times, first = [], None
    for _ in range(max(repeat, 1)):
        t0 = time.perf_counter()
        st = run_relight(bsh, out, cfg, scene_path=scene / "scene.json", view=view)
        times.append(time.perf_counter() - t0)
        img = io.read_image(out / "relit.exr")
        if first is None:
            first = img
        elif not np.array_equal(first, img):
            raise RuntimeError(f"{out}: relight is not deterministic across repeats")
    dt = min(times)
    sel = (img[..., 3] > 0.5) & (ref[..., 3] > 0.5)
    d = img[..., :3][sel] - ref[..., :3][sel]
    rms_ref = float(np.sqrt(np.mean(ref[..., :3][sel] ** 2)))
    rel = float(np.sqrt(np.mean(d ** 2))) / rms_ref
    noise = float(np.sqrt(np.mean(var[..., :3][sel]))) / rms_ref
    return {"seconds": round(dt, 2), "seconds_max": round(max(times), 2), "rel_rms": round(rel, 4), "ref_noise": round(noise, 4),
            "rel_rms_noise_corrected": round(float(np.sqrt(max(rel ** 2 - noise ** 2, 0.0))), 4),
            "mean_ratio": round(float(img[..., :3][sel].mean() / ref[..., :3][sel].mean()), 4),
            "nodes_per_pixel": round(st["nodes_visited_per_pixel"], 1), "bsh_nodes": st["nodes"],
            "brdf_used": st["brdf"], "glossy_skipped": st["decisions"]["glossy_work_skipped"],
            "pixels": int(sel.sum()), "renderer": st["gl"]["renderer"]}


def mark_pareto(rows: list[dict]) -> None:
    """pareto = 1 for rows no other row of the same view × material beats in both seconds and error
    (the 'model only' rows, which render a different material, are excluded)."""
    for r in rows:
        r["pareto"] = 0
    groups: dict = {}
    for r in rows:
        if not r["knob"].startswith("model:"):
            groups.setdefault((r["view"], r["material"]), []).append(r)
    for g in groups.values():
        for r in g:
            e, s = r["rel_rms_noise_corrected"], r["seconds"]
            r["pareto"] = int(not any((o["seconds"] <= s and o["rel_rms_noise_corrected"] <= e)
                                      and (o["seconds"] < s or o["rel_rms_noise_corrected"] < e) for o in g))


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = sorted({(r["view"], r["material"]) for r in rows})
    fig, axes = plt.subplots(1, len(keys), figsize=(6.5 * len(keys), 5.5), squeeze=False)
    colors = dict(zip(GATHERERS, ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:olive")))
    for ax, (view, mat) in zip(axes[0], keys):
        g = [r for r in rows if (r["view"], r["material"]) == (view, mat) and not r["knob"].startswith("model:")]
        marks = dict(zip(GATHERERS, "s^oDvP"))
        for r in g:
            ax.scatter(r["seconds"], r["rel_rms_noise_corrected"], c=colors[r["method"]], marker=marks[r["method"]],
                       s=28, zorder=3)
            if r["pareto"] or r["method"] != "hybrid" or r["rel_rms_noise_corrected"] > 1:
                ax.annotate(f"{r['row']}:{r['knob']}", (r["seconds"], r["rel_rms_noise_corrected"]), fontsize=7,
                            xytext=(4, 3), textcoords="offset points")
        for name, v in PRESETS.items():  # the presets' rows (default BSH)
            for r in g:
                if (r["method"], int(r["m"]), float(r["omega_tr"]), float(r["stop_multiple"]), float(r["tc"]),
                        float(r["tn"])) == (v["method"], v["microbuffer"], v["omega_tr"], v["stop_multiple"], *BSH_DEFAULT):
                    ax.scatter(r["seconds"], r["rel_rms_noise_corrected"], marker="*", s=260, c="gold",
                               edgecolors="k", zorder=5)
                    ax.annotate(f"preset {name}", (r["seconds"], r["rel_rms_noise_corrected"]), fontsize=8,
                                xytext=(-10, -14), textcoords="offset points", weight="bold")
        f = sorted((r for r in g if r["pareto"]), key=lambda r: r["seconds"])
        ax.plot([r["seconds"] for r in f], [r["rel_rms_noise_corrected"] for r in f], "k-", lw=1.5, zorder=2,
                label="Pareto front")
        ax.scatter([r["seconds"] for r in f], [r["rel_rms_noise_corrected"] for r in f], s=90, facecolors="none",
                   edgecolors="k", zorder=4)
        for m, c in colors.items():
            ax.scatter([], [], c=c, marker=marks[m], label=m)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("wall time per relight [s] (llvmpipe, shared 2-core CPU)")
        ax.set_ylabel("relative RMS vs path-traced gather, noise-corrected")
        ax.set_title(f"{view} / {mat} ({g[0]['pixels'] if g else 0} px)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    io.save_figure(path, fig)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path, nargs="?", default=ROOT / "data_samples")
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true", help="view1, lambert + ggx0.25 (default)")
    mode.add_argument("--full", action="store_true", help="view1 + view2, all five materials")
    ap.add_argument("--plot-only", action="store_true", help="re-plot the CSV")
    ap.add_argument("--repeat", type=int, default=2, help="runs per row; seconds = the fastest (default 2)")
    ap.add_argument("--views", help="comma list overriding the mode's views")
    ap.add_argument("--materials", help="comma list overriding the mode's materials")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "relight_tradeoff.csv")
    ap.add_argument("--work", type=Path, default=ROOT / "bench" / "_work" / "relight_tradeoff")
    a = ap.parse_args()
    png = a.out.with_suffix(".png")
    if a.plot_only:
        with open(a.out) as f:
            rows = list(csv.DictReader(f))
        for r in rows:
            for k in ("seconds", "rel_rms_noise_corrected"):
                r[k] = float(r[k])
            r["pareto"] = int(r["pareto"])
        plot(rows, png)
        print(f"wrote {png}")
        return
    setup_logging(-1)
    views = ["view1", "view2"] if a.full else ["view1"]
    mats = ["lambert", "ggx0.1", "ggx0.25", "ggx0.5", "ggx1.0"] if a.full else ["lambert", "ggx0.25"]
    views = a.views.split(",") if a.views else views
    mats = a.materials.split(",") if a.materials else mats
    a.work.mkdir(parents=True, exist_ok=True)
    bshs = {}
    for tc, tn in [BSH_DEFAULT] + BSH_VARIANTS:
        p, dt = build_bsh(a.scene, a.work, tc, tn)
        bshs[(tc, tn)] = p
        print(f"bsh tc={tc:g} tn={tn:g}: {p.name} ({dt:.1f} s)", flush=True)
    # warm-up (numba, GL driver, texel tables) so the first timed row is not penalised
    measure(a.scene, bshs[BSH_DEFAULT], a.work / "warmup", views[0], mats[0],
            RelightConfig(**BASE, **material_kw(mats[0])))
    rows: list[dict] = []

    def add(view, mat, knob, over, tcn, ref_mat=None, kw=None):
        kw = dict(material_kw(mat)) if kw is None else kw
        p = {**BASE, **over}
        cfg = RelightConfig(**p, **kw)
        res = measure(a.scene, bshs[tcn], a.work / f"{view}_{mat}_{len(rows)}", view, ref_mat or mat, cfg, a.repeat)
        row = {"row": len(rows), "view": view, "material": mat, "knob": knob, "method": p["method"],
               "m": p["microbuffer"], "omega_tr": p["omega_tr"], "stop_multiple": p["stop_multiple"],
               "tc": tcn[0], "tn": tcn[1], **res}
        rows.append(row)
        print(row, flush=True)

    for view in views:
        for mat in mats:
            for knob, over, tcn in grid():
                add(view, mat, knob, over, tcn)
        if "lambert" in mats:  # model only what the scene requires: same Lambert reference, glossy code path forced
            add(view, "lambert", "model:ggx r1 metallic0 (glossy path)", {}, BSH_DEFAULT,
                kw=dict(brdf="ggx", albedo=(0.8, 0.8, 0.8), metallic=0.0, roughness=1.0, masking="separable"))
            add(view, "lambert", "model:ggx r1 metallic0 m=8", {"microbuffer": 8}, BSH_DEFAULT,
                kw=dict(brdf="ggx", albedo=(0.8, 0.8, 0.8), metallic=0.0, roughness=1.0, masking="separable"))
    mark_pareto(rows)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    fields = list(rows[0])
    with open(a.out, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        w.writerows(rows)
    print(f"wrote {a.out}")
    plot(rows, png)
    print(f"wrote {png}")
    for r in rows:
        if r["pareto"]:
            print("front:", r["row"], r["view"], r["material"], r["knob"], r["seconds"], r["rel_rms_noise_corrected"])


if __name__ == "__main__":
    main()
