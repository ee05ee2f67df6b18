"""Adaptive shading (relight --adaptive ε) at a size above the references': time, node visits and the error
against the full path trace, every pixel vs ε.

    .venv/bin/python -m bench.speed.bench_adaptive [SCENE_DIR] [--bsh bsh.npz] [--view view1] [--scale 4]
        [--eps 0,0.1,0.3] [--out bench/speed/adaptive_small.csv]

The object is rendered at ``scale``× the reference's size (128² → 512²) with relight's defaults (Lambert 0.8,
exact cloud's BSH); its (4·scale)² pixel blocks are the reference's 4×4 blocks, so the error against
``truth/full_<view>_lambert.exr`` is measured at the reference's resolution (blocks entirely on the object in
both). Per ε: wall time of the relight call, walk time, node visits, pixels shaded, R/G/B mean ratio and block
relative RMS against the reference, and the per-pixel relative RMS against the every-pixel image (ε = 0).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]

from bench.benchlib import truth_bsh, write_rows

from pipeline import io  # noqa: E402
from pipeline.relight.relight import RelightConfig, run_relight  # noqa: E402
from pipeline.runtime import setup_logging  # noqa: E402


def block_error(img: np.ndarray, ref: np.ndarray, scale: int, k: int = 4) -> dict:
    """img (s·H, s·W, 4) against ref (H, W, 4) on the reference's k×k blocks."""
    H, W = ref.shape[:2]
    b = k * scale
    A = img[..., :3].reshape(H // k, b, W // k, b, 3).mean((1, 3))
    ma = (img[..., 3] > 0.5).reshape(H // k, b, W // k, b).all((1, 3))
    B = ref[..., :3].reshape(H // k, k, W // k, k, 3).mean((1, 3))
    mb = (ref[..., 3] > 0.5).reshape(H // k, k, W // k, k).all((1, 3))
    sel = ma & mb
    a, r = A[sel], B[sel]
    ratio = a.sum(0) / r.sum(0)
    return {"blocks": int(sel.sum()), "ratio_r": round(float(ratio[0]), 4), "ratio_g": round(float(ratio[1]), 4),
            "ratio_b": round(float(ratio[2]), 4),
            "block_rms": round(float(np.sqrt(((a - r) ** 2).mean()) / np.sqrt((r ** 2).mean())), 4)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path, nargs="?", default=ROOT / "data_samples")
    ap.add_argument("--bsh", type=Path)
    ap.add_argument("--view", default="view1")
    ap.add_argument("--scale", type=int, default=4)
    ap.add_argument("--eps", default="0,0.1,0.3")
    ap.add_argument("--out", type=Path, default=HERE / "adaptive_small.csv")
    ap.add_argument("--work", type=Path, default=ROOT / "bench" / "_work" / "adaptive")
    a = ap.parse_args()
    setup_logging(-1)
    bsh = truth_bsh(a.scene, a.bsh, a.work)
    ref = io.read_image(a.scene / "truth" / f"full_{a.view}_lambert.exr")
    v = io.read_json(a.scene / "scene.json")["views"][a.view]
    size = f"{v['size'][0] * a.scale}x{v['size'][1] * a.scale}"
    rows, base = [], None
    for eps in (float(x) for x in a.eps.split(",")):
        cfg = RelightConfig(adaptive=eps, size=size, brdf="lambert", albedo=(0.8, 0.8, 0.8))
        cfg.check()
        out = a.work / f"{a.view}_{eps:g}"
        t0 = time.perf_counter()
        st = run_relight(bsh, out, cfg, scene_path=a.scene / "scene.json", view=a.view)
        dt = time.perf_counter() - t0
        img = io.read_image(out / "relit.exr")
        row = {"view": a.view, "size": size, "adaptive": eps, "seconds": round(dt, 2),
               "walk_s": round(st["time_s"].get("walk", 0.0), 2), "bounce_s": round(sum(st["object_surfels"].get("bounce_s", [])), 2),
               "node_visits": int(st["nodes_visited"]), "covered": st["covered_pixels"],
               "shaded": (st.get("adaptive") or {}).get("shaded", st["covered_pixels"]), **block_error(img, ref, a.scale)}
        if base is None:
            base = img
            row["pixel_rms_vs_every_pixel"] = 0.0
        else:
            m = (img[..., 3] > 0.5) & (base[..., 3] > 0.5)
            d = img[..., :3][m] - base[..., :3][m]
            row["pixel_rms_vs_every_pixel"] = round(float(np.sqrt((d ** 2).mean()) / np.sqrt((base[..., :3][m] ** 2).mean())), 4)
        rows.append(row)
        print(row, flush=True)
    write_rows(a.out, rows)


if __name__ == "__main__":
    main()
