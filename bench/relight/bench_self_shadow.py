"""The object in its own micro-buffers: relight against the full path trace (``truth/full_*``, the object
in the room) and the gather-only trace (``truth/gather_*``), side by side, for 0/1/2 bounces, auto (-1, the default) and off.

    .venv/bin/python -m bench.relight.bench_self_shadow [SCENE_DIR] [--bsh bsh.npz] [--views view1,view2]
        [--materials lambert,ggx0.1,ggx0.25] [--bounces off,0,1,2,-1] [--method classic] [--m 24]
        [--out bench/relight/self_shadow_small.csv]
    .venv/bin/python -m bench.relight.bench_self_shadow --table bench/relight/self_shadow_small.csv   # the CSV as bench/README's table

The BSH is build-bsh (defaults) of the scene's exact HDR cloud (cloud_gt.ply) unless ``--bsh`` is given, so
the numbers measure relight's model and gatherer, not the expansion. Per row, on 4×4 block means
(``pipeline.metrics.compare_to_reference``, blocks entirely on the object): the mean ratio per channel
(R, G, B) and over all channels, the block relative RMS, the reference's own block noise, against full_* and
against gather_*; the relight wall time and the seconds the bounces took. ``off`` = ``--surfels -1`` (the
paper's gather: the object absent from its own micro-buffers).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]

from bench.benchlib import material_kw, measure, truth_bsh, write_rows

from pipeline import io  # noqa: E402
from pipeline.relight.relight import RelightConfig, run_relight  # noqa: E402
from pipeline.runtime import setup_logging  # noqa: E402


def markdown(csv_path: Path) -> str:
    """The CSV's rows as the markdown table of bench/README.md."""
    import csv

    names = {"off": "paper (`--surfels -1`)", "0": "0 bounces", "1": "1 bounce", "2": "2 bounces", "-1": "auto (default)"}
    out = ["| view | material | model | s (bounces s) | surfels | full: R / G / B | full block RMS (noise) | "
           "gather: mean | gather block RMS |", "|---|---|---|---|---|---|---|---|---|"]
    with open(csv_path, newline="") as f:
        for r in csv.DictReader(f):
            pct = lambda k: f"{100 * float(r[k]):.1f} %"  # noqa: E731
            out.append(f"| {r['view']} | {r['material']} | {names.get(r['bounces'], r['bounces'])} | {float(r['seconds']):.1f} "
                       f"({float(r['bounce_s']):.1f}) | {r['surfels']} | {float(r['full_ratio_r']):.3f} / "
                       f"{float(r['full_ratio_g']):.3f} / {float(r['full_ratio_b']):.3f} | {pct('full_block_rms')} "
                       f"({pct('full_block_noise')}) | {float(r['gather_ratio']):.3f} | {pct('gather_block_rms')} |")
    return "\n".join(out)


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "--table":
        print(markdown(Path(sys.argv[2])))
        return
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path, nargs="?", default=ROOT / "data_samples")
    ap.add_argument("--bsh", type=Path)
    ap.add_argument("--views", default="view1,view2")
    ap.add_argument("--materials", default="lambert,ggx0.1,ggx0.25,ggx0.5,ggx1.0")
    ap.add_argument("--bounces", default="off,0,1,2,-1")
    ap.add_argument("--method", default="classic")
    ap.add_argument("--m", type=int, default=24)
    ap.add_argument("--size", default="")
    ap.add_argument("--surfels", type=int, default=0)
    ap.add_argument("--out", type=Path, default=HERE / "self_shadow_small.csv")
    ap.add_argument("--work", type=Path, default=ROOT / "bench" / "_work" / "self_shadow")
    a = ap.parse_args()
    setup_logging(-1)
    bsh = truth_bsh(a.scene, a.bsh, a.work)
    rows = []
    for view in a.views.split(","):
        for mat in a.materials.split(","):
            for bo in a.bounces.split(","):
                kw = dict(surfels=-1) if bo == "off" else dict(surfels=a.surfels, bounces=int(bo))
                cfg = RelightConfig(microbuffer=a.m, method=a.method, size=a.size, **kw, **material_kw(mat))
                cfg.check()
                out = a.work / f"{view}_{mat}_{bo}"
                t0 = time.perf_counter()
                st = run_relight(bsh, out, cfg, scene_path=a.scene / "scene.json", view=view)
                dt = time.perf_counter() - t0
                img = io.read_image(out / "relit.exr")
                row = {"view": view, "material": mat, "bounces": bo, "method": a.method, "m": a.m,
                       "surfels": st["object_surfels"]["surfels"], "seconds": round(dt, 2),
                       "bounce_s": sum(st["object_surfels"].get("bounce_s", []) or [0]),
                       "nodes_per_pixel": round(st["nodes_visited_per_pixel"], 1)}
                for kind in ("full", "gather"):
                    row.update(measure(img, a.scene, view, mat, kind))
                rows.append(row)
                print(row, flush=True)
    write_rows(a.out, rows)


if __name__ == "__main__":
    main()
