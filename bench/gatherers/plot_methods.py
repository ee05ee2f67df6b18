"""The five gatherers' time against error (issue 26's closing measurement): the Pareto plot and the README table
from bench_envmap.py's CSVs.

    .venv/bin/python -m bench.gatherers.plot_methods bench/gatherers/methods_small.csv [bench/gatherers/methods_lamps.csv …]
        [--png bench/gatherers/methods_pareto.png] [--table]

The CSVs are ``bench/gatherers/bench_envmap.py --methods classic,mipmapped,hybrid,importance,envmap --sizes 256,512 …``
outputs (one row per view × material × size × method: the whole relight call's wall ``seconds`` and the 4×4
block error against ``truth/full_*`` and ``truth/gather_*``). The plot: one panel per CSV, seconds against
``full_block_rms`` on log axes, a colour per method, a marker per material, hollow 256², filled 512²; the
dotted line is the references' own block noise. ``--table``: per method and size, the geometric-mean seconds, the
median block RMS over the panel's view × material cases and in how many of them the row is on that case's
Pareto front (no other row of the case, either size, both faster and more accurate), as markdown.
"""

from __future__ import annotations

import argparse
import csv
import math
import statistics
from pathlib import Path

HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]

METHODS = ("classic", "mipmapped", "hybrid", "importance", "envmap")
MARKERS = {"lambert": "o", "ggx0.1": "v", "ggx0.25": "s", "ggx0.5": "D", "ggx1.0": "^"}


def read(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def front(rows: list[dict]) -> list[dict]:
    """The rows no other row beats on both seconds and full_block_rms, by seconds."""
    pts = sorted(rows, key=lambda r: (float(r["seconds"]), float(r["full_block_rms"])))
    out, best = [], math.inf
    for r in pts:
        if float(r["full_block_rms"]) < best:
            out.append(r)
            best = float(r["full_block_rms"])
    return out


def summary(rows: list[dict]) -> list[tuple[str, int, float, float, float, int, int]]:
    """(method, size, geometric-mean seconds, median full block RMS, median gather block RMS, cases, cases where
    it is on the case's Pareto front)."""
    cases = {(r["view"], r["material"]) for r in rows}
    on_front = {id(r) for c in cases for r in front([x for x in rows if (x["view"], x["material"]) == c])}
    out = []
    for m in METHODS:
        for size in sorted({int(r["size"]) for r in rows}):
            sel = [r for r in rows if r["method"] == m and int(r["size"]) == size]
            if sel:
                gm = math.exp(statistics.fmean(math.log(float(r["seconds"])) for r in sel))
                out.append((m, size, gm, statistics.median(float(r["full_block_rms"]) for r in sel),
                            statistics.median(float(r["gather_block_rms"]) for r in sel), len(sel),
                            sum(id(r) in on_front for r in sel)))
    return out


def plot(panels: list[tuple[str, list[dict]]], png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pipeline import io

    fig, axes = plt.subplots(1, len(panels), figsize=(6.5 * len(panels), 5.5), squeeze=False)
    for ax, (name, rows) in zip(axes[0], panels):
        for i, m in enumerate(METHODS):
            for r in (r for r in rows if r["method"] == m):
                filled = int(r["size"]) >= 512
                ax.plot(float(r["seconds"]), float(r["full_block_rms"]), MARKERS.get(r["material"], "x"), color=f"C{i}",
                        ms=7, mfc=f"C{i}" if filled else "none")
            ax.plot([], [], "o", color=f"C{i}", label=m)
        noise = statistics.median(float(r["full_block_noise"]) for r in rows)
        ax.axhline(noise, color="k", ls=":", lw=0.7, label=f"references' block noise ({noise:.3f})")
        for mat, mk in MARKERS.items():
            if any(r["material"] == mat for r in rows):
                ax.plot([], [], mk, color="k", mfc="none", label=mat)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("relight wall time [s] (2 shared CPU cores, llvmpipe)")
        ax.set_ylabel("4×4-block relative RMS against truth/full_*")
        ax.set_title(f"{name}: views {', '.join(sorted({r['view'] for r in rows}))}; hollow 256², filled 512²", fontsize=9)
        ax.grid(True, which="both", lw=0.3)
        ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    io.save_figure(png, fig)
    print(f"wrote {png}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("csvs", type=Path, nargs="+")
    ap.add_argument("--png", type=Path, default=HERE / "methods_pareto.png")
    ap.add_argument("--table", action="store_true", help="print the per-method summary as markdown")
    a = ap.parse_args()
    panels = [(p.stem, read(p)) for p in a.csvs]
    plot(panels, a.png)
    if a.table:
        for name, rows in panels:
            print(f"\n{name}\n\n| method | size | s (geo-mean) | full block RMS (median) | gather block RMS (median) | on the front |\n"
                  "|---|---|---|---|---|---|")
            for m, size, s, e, g, n, k in summary(rows):
                print(f"| {m} | {size}² | {s:.1f} | {100 * e:.1f} % | {100 * g:.1f} % | {k} of {n} |")


if __name__ == "__main__":
    main()
