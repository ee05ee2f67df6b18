"""Classic PBGI against the ground truth's path-traced gather references (relight-core).

    .venv/bin/python -m bench.relight.bench_relight_truth SCENE_DIR [--bsh bsh.npz] [--m 16,32] [--stop 4] [--methods classic,hybrid]
        [--views view1,view2] [--materials lambert,ggx0.1,ggx0.25,ggx0.5,ggx1.0] [--out bench/relight_truth.csv]

SCENE_DIR is a make-scene output (scene.json, cloud_gt.ply, truth/gather_<view>_<material>[_var].exr).
The BSH is built from the exact HDR cloud (cloud_gt.ply) with build-bsh's defaults unless --bsh is given,
so the numbers measure PBGI alone, not the HDR expansion. Materials as scene.json: Lambert 0.8; GGX with
α = roughness², F = 1 (white metal), separable Smith masking (Mitsuba's roughconductor). Per row: relative
RMS over the object pixels, the ratio of mean radiances and its noise (the reference's, 1σ), the reference's
own noise (√mean variance of the pixel mean / RMS), the noise-corrected error √(relRMS² − noise²); the same
on k×k block means (``--block``, default 8; blocks with ≥ k²/4 object pixels): block relative RMS, the
reference's block noise and the noise-corrected block error — all from ``pipeline.metrics.compare_to_reference``
(``min_pixels = k²/4``); time and nodes visited per pixel.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path


HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]

from bench.benchlib import material_kw, truth_bsh, write_rows

from pipeline import io  # noqa: E402
from pipeline.metrics import compare_to_reference  # noqa: E402
from pipeline.gather import GATHERERS  # noqa: E402
from pipeline.relight.relight import RelightConfig, run_relight  # noqa: E402
from pipeline.runtime import setup_logging  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path, nargs="?", default=ROOT / "data_samples")
    ap.add_argument("--bsh", type=Path)
    ap.add_argument("--m", default="16,32")
    ap.add_argument("--methods", default="classic", help="comma-separated, of: " + ", ".join(GATHERERS))
    ap.add_argument("--views", default="view1,view2")
    ap.add_argument("--materials", default="lambert,ggx0.1,ggx0.25,ggx0.5,ggx1.0")
    ap.add_argument("--out", type=Path, default=HERE / "relight_truth_small.csv")
    ap.add_argument("--work", type=Path, default=ROOT / "bench" / "_work" / "relight_truth")
    ap.add_argument("--block", type=int, default=8, help="k of the k×k block means")
    ap.add_argument("--stop", default="4", help="comma-separated stop multiples (§5.3's 4 by default)")
    a = ap.parse_args()
    setup_logging(-1)
    bsh = truth_bsh(a.scene, a.bsh, a.work)
    rows = []
    for view in a.views.split(","):
        for mat in a.materials.split(","):
            ref = io.read_image(a.scene / "truth" / f"gather_{view}_{mat}.exr")
            var = io.read_image(a.scene / "truth" / f"gather_{view}_{mat}_var.exr")
            for method in a.methods.split(","):
                for m, stop in ((int(x), float(y)) for x in a.m.split(",") for y in a.stop.split(",")):
                    cfg = RelightConfig(microbuffer=m, method=method, stop_multiple=stop, **material_kw(mat))
                    cfg.check()
                    out = a.work / f"{view}_{mat}_{method}_{m}_{stop:g}"
                    t0 = time.perf_counter()
                    st = run_relight(bsh, out, cfg, scene_path=a.scene / "scene.json", view=view)
                    dt = time.perf_counter() - t0
                    img = io.read_image(out / "relit.exr")
                    sel = (img[..., 3] > 0.5) & (ref[..., 3] > 0.5)
                    k = a.block
                    c = compare_to_reference(img, ref, sel, ref_var=var, block=k, min_pixels=k * k // 4)
                    row = {"view": view, "material": mat, "method": method, "m": m, "stop": stop, "pixels": c["n_pixels"],
                           "rel_rms": round(c["rms"], 4), "mean_ratio": round(c["mean_ratio"], 4),
                           "mean_ratio_noise": round(c["mean_ratio_noise"], 4), "ref_noise": round(c["ref_noise"], 4),
                           "rel_rms_noise_corrected": round(c["rms_corrected"], 4), f"blocks{k}": c["n_blocks"],
                           f"block{k}_rel_rms": round(c["rms_block"], 4), f"block{k}_ref_noise": round(c["ref_noise_block"], 4),
                           f"block{k}_noise_corrected": round(c["rms_corrected_block"], 4),
                           "mask_mismatch": int(((img[..., 3] > 0.5) != (ref[..., 3] > 0.5)).sum()),
                           "seconds": round(dt, 2), "nodes_per_pixel": round(st["nodes_visited_per_pixel"], 1),
                           "renderer": st["gl"]["renderer"]}
                    rows.append(row)
                    print(row, flush=True)
    write_rows(a.out, rows)


if __name__ == "__main__":
    main()
