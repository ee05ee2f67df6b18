"""Benchmark of the HDR expansion (issue 5 "Measure"): time per stage, and the PatchMatch speed /
accuracy trade (iterations, patch size, cube-map size, view count) as a Pareto plot.

    .venv/bin/python -m bench.expansion.bench_expansion [--scene DIR] [--quick]

DIR is a make-scene ground truth (photo.exr, cloud_ldr.ply, cloud_gt.ply, truth/truth.npz);
default data_samples/ (the shipped `small`), else bench/_work/tiny (made with
`pcrelight make-scene --preset tiny` when missing).  Writes
  bench/expansion/expansion.csv         one row per (scene, run, stage): seconds
  bench/expansion/expansion_pareto.csv  one row per sweep point: parameter, value, PatchMatch seconds,
                              expansion seconds, cloud RMS (all / overexposed), log RMS
  bench/expansion/expansion_pareto.png  cloud RMS on the overexposed points against expansion time, Pareto
                              front marked; the LDR and operator rows as horizontal references
  bench/expansion/expansion_stages.png  seconds per stage of the default run
Timings are wall-clock on this machine (2 cores, shared): compare rows of the same run only.
The sweep varies one parameter at a time around the default (iterations 5, patch 7, cube 256²,
automatic views ≤ 6); cube size and view count re-render the cube maps.
"""
from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]

import numpy as np  # noqa: E402

from pipeline import io  # noqa: E402
from pipeline.metrics import cloud_metrics  # noqa: E402
from pipeline.expansion.expose_match import ExposeMatchConfig, run_expose_match  # noqa: E402
from pipeline.expansion.patchmatch import PatchmatchConfig, run_patchmatch  # noqa: E402
from pipeline.expansion.poisson import PoissonConfig, run_poisson  # noqa: E402
from pipeline.expansion.render_cubemaps import RenderCubemapsConfig, run_render_cubemaps  # noqa: E402
from pipeline.expansion.reproject import ReprojectConfig, run_reproject  # noqa: E402

BENCH = HERE                   # the outputs (--out)
WORK = ROOT / "bench" / "_work"


def _scene(arg: str | None) -> Path:
    if arg:
        return Path(arg)
    if (ROOT / "data_samples" / "truth" / "truth.npz").exists():
        return ROOT / "data_samples"
    tiny = WORK / "tiny"
    if not (tiny / "truth" / "truth.npz").exists():
        from pipeline.scene.make_scene import apply_preset, run_make_scene

        run_make_scene(tiny, apply_preset("tiny", {}), preview=False)
    return tiny


class Run:
    """One expansion of the scene's LDR cloud with given options; records seconds per stage."""

    def __init__(self, scene: Path, work: Path, truth: np.ndarray, over: np.ndarray):
        self.scene, self.work, self.truth, self.over = scene, work, truth, over
        self.photo, self.ldr = scene / "photo.exr", scene / "cloud_ldr.ply"

    def exposure(self) -> float:
        t0 = time.perf_counter()
        run_expose_match(self.photo, self.ldr, self.work / "exposure.npz", self.work / "photo_ldr.exr",
                         ExposeMatchConfig())
        return time.perf_counter() - t0

    def cubemaps(self, size: int, max_views: int) -> tuple[Path, float]:
        d = self.work / f"cub_{size}_{max_views}"
        t0 = time.perf_counter()
        if not (d / "cameras.npz").exists():
            run_render_cubemaps(self.ldr, d, RenderCubemapsConfig(size=size, max_views=max_views))
        return d, time.perf_counter() - t0

    def expand(self, tag: str, cub: Path, pm: PatchmatchConfig, transfer: str = "rgb") -> dict:
        w = self.work / tag
        times = {}
        t0 = time.perf_counter()
        run_patchmatch(cub, self.photo, self.work / "photo_ldr.exr", self.work / "exposure.npz", w / "faces", pm)
        times["patchmatch"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        run_reproject(self.ldr, cub, w / "faces", w / "proj.ply", ReprojectConfig(transfer=transfer),
                      photo=self.photo, exposure=self.work / "exposure.npz")
        times["reproject"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        run_poisson(w / "proj.ply", w / "cloud.ply", PoissonConfig())
        times["poisson"] = time.perf_counter() - t0
        return {**times, **self.metrics(io.read_cloud(w / "cloud.ply").colors)}

    def metrics(self, colors: np.ndarray) -> dict:
        """evaluate's cloud metrics + log10-luminance RMS on the overexposed points + RMS on the
        overexposed points whose truth the photo can explain (Y ≤ α_true · max Y(photo))."""
        m = cloud_metrics(colors, self.truth, self.over)
        y = np.maximum(io.luminance(colors), 1e-4).astype(np.float64)
        yt = np.maximum(io.luminance(self.truth), 1e-4).astype(np.float64)
        m["log_rms_over"] = float(np.sqrt(np.mean(np.log10(y[self.over] / yt[self.over]) ** 2)))
        sel = self.over & (yt <= self.peak)
        d = colors[sel].astype(np.float64) - self.truth[sel]
        m["rms_over_in_range"] = float(np.sqrt(np.mean(d ** 2))) if sel.any() else float("nan")
        m["n_over_in_range"] = int(sel.sum())
        return m


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default=None)
    ap.add_argument("--quick", action="store_true", help="fewer sweep points")
    ap.add_argument("--out", type=Path, default=HERE, help="the folder of the CSVs and PNGs (default bench/expansion/)")
    args = ap.parse_args()
    global BENCH
    BENCH = args.out
    scene = _scene(args.scene)
    work = WORK / f"expansion_{scene.name}"
    if work.exists():  # cube maps are reused within one run only: every timing is measured here
        import shutil

        shutil.rmtree(work)
    work.mkdir(parents=True, exist_ok=True)
    tr = io.read_npz(scene / "truth" / "truth.npz", "pcrelight.truth/1")
    e = float(tr["e"])
    truth = io.read_cloud(scene / "cloud_gt.ply").colors * e
    over = tr["overexposed"].astype(bool)
    run = Run(scene, work, truth, over)
    run.peak = float(tr["alpha_true"]) * float(io.luminance(io.read_image(scene / "photo.exr")[..., :3]).max())
    ldr_m = run.metrics(io.read_cloud(scene / "cloud_ldr.ply").colors)
    print(f"photo peak in cloud units (α_true · max Y): {run.peak:.4g}; overexposed points within it: "
          f"{ldr_m['n_over_in_range']} of {int(over.sum())}")
    # warm up numba (JIT or cache load) so that no timed run pays for compilation
    from pipeline.expansion.patchmatch import pyramid_patchmatch, vote

    _w = np.random.default_rng(0).random((40, 40, 3))
    _n, _ = pyramid_patchmatch(_w, _w, levels=2, iterations=1, patch_size=5, min_side=8)
    vote(_w, _n, np.ones((40, 40), np.uint8), 5)
    stage_rows = []
    t_exp = run.exposure()
    stage_rows.append(("default", "expose-match", t_exp))
    cub, t_cub = run.cubemaps(256, 6)
    stage_rows.append(("default", "render-cubemaps", t_cub))
    base = dict(iterations=5, patch_size=7)
    d = run.expand("default", cub, PatchmatchConfig(**base))
    for k in ("patchmatch", "reproject", "poisson"):
        stage_rows.append(("default", k, d[k]))
    stage_rows.append(("default", "total", t_exp + t_cub + d["patchmatch"] + d["reproject"] + d["poisson"]))

    sweeps = {"iterations": [1, 2, 5, 8], "patch_size": [5, 7, 11], "size": [128, 256, 512], "max_views": [1, 3, 6]}
    if args.quick:
        sweeps = {"iterations": [1, 5], "patch_size": [5, 7], "size": [128, 256], "max_views": [1, 6]}
    pareto = [dict(param="default", value="", seconds=d["patchmatch"] + d["reproject"] + d["poisson"] + t_cub,
                   patchmatch_s=d["patchmatch"], **{k: d[k] for k in ("cloud_rms", "cloud_rms_over", "log_rms", "log_rms_over", "rms_over_in_range")})]
    for param, values in sweeps.items():
        for v in values:
            pm = dict(base)
            size, views = 256, 6
            if param in pm:
                if pm[param] == v:
                    continue
                pm[param] = v
            elif param == "size":
                if v == 256:
                    continue
                size = v
            else:
                if v == 6:
                    continue
                views = v
            c, tc = run.cubemaps(size, views)
            r = run.expand(f"{param}_{v}", c, PatchmatchConfig(**pm))
            pareto.append(dict(param=param, value=v, seconds=r["patchmatch"] + r["reproject"] + r["poisson"] + tc,
                               patchmatch_s=r["patchmatch"],
                               **{k: r[k] for k in ("cloud_rms", "cloud_rms_over", "log_rms", "log_rms_over", "rms_over_in_range")}))
            print(pareto[-1], flush=True)

    BENCH.mkdir(parents=True, exist_ok=True)
    with open(BENCH / "expansion.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["scene", "run", "stage", "seconds"])
        for r in stage_rows:
            w.writerow([scene.name, r[0], r[1], f"{r[2]:.3f}"])
    with open(BENCH / "expansion_pareto.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["scene", "param", "value", "seconds", "patchmatch_s", "cloud_rms",
                                          "cloud_rms_over", "log_rms", "log_rms_over", "rms_over_in_range"])
        w.writeheader()
        w.writerow(dict(scene=scene.name, param="ldr", value="", seconds=0, patchmatch_s=0,
                        **{k: ldr_m[k] for k in ("cloud_rms", "cloud_rms_over", "log_rms", "log_rms_over", "rms_over_in_range")}))
        for r in pareto:
            w.writerow(dict(scene=scene.name, **r))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(18, 5))
    xs = np.array([r["seconds"] for r in pareto])
    for ax, key, label in zip(axes, ("cloud_rms_over", "rms_over_in_range", "log_rms_over"),
                              ("cloud RMS, overexposed points [LDR units]",
                               "RMS, overexposed points with truth ≤ the photo's peak [LDR units]",
                               "log10-luminance RMS, overexposed points")):
        ys = np.array([r[key] for r in pareto])
        for r, x, y in zip(pareto, xs, ys):
            ax.scatter(x, y, s=18)
            ax.annotate(f"{r['param']}={r['value']}" if r["value"] != "" else "default", (x, y), fontsize=7)
        front, best = [], np.inf
        for i in np.argsort(xs):
            if ys[i] < best:
                best = ys[i]
                front.append(i)
        ax.plot(xs[front], ys[front], "k--", lw=0.8, label="Pareto front")
        ax.axhline(ldr_m[key], color="r", lw=0.8, label=f"LDR {ldr_m[key]:.4g}")
        ax.set_xlabel("expansion time (cube maps + patchmatch + reproject + poisson) [s]")
        ax.set_ylabel(label)
        ax.legend()
    axes[0].set_title(f"PatchMatch speed/accuracy on '{scene.name}'")
    fig.tight_layout()
    io.save_figure(BENCH / "expansion_pareto.png", fig)
    fig, ax = plt.subplots(figsize=(6, 3.5))
    names = [r[1] for r in stage_rows if r[1] != "total"]
    ax.barh(names, [r[2] for r in stage_rows if r[1] != "total"])
    ax.set_xlabel("seconds")
    ax.set_title(f"expansion stages on '{scene.name}' (total {stage_rows[-1][2]:.1f} s)")
    fig.tight_layout()
    io.save_figure(BENCH / "expansion_stages.png", fig)
    print(f"LDR: {ldr_m}")
    for r in stage_rows:
        print(f"{r[1]:>16s}: {r[2]:8.2f} s")


if __name__ == "__main__":
    main()
