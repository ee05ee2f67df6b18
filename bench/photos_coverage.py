"""What each extra photo buys (issue 25): overexposed-point coverage and end-to-end error against the number of
photos, the photos chosen greedily by the overexposed points they add.

Coverage comes from the ground truth (truth ``photo_visible`` of each photo of scene.json ``photos``: in frame,
facing it, first hit from its eye; counted on the overexposed points). The end-to-end error per photo count is
read from ``bench/end_to_end.py`` CSVs of the greedy prefixes (its ``pipeline`` rows: the pipeline with defaults on
that set; the ``seen exact, rest LDR`` rows: the oracle) — run them first:

    python bench/end_to_end.py --photos none --sets sun+lights+bright --oracle --csv A.csv     # and the prefixes

Run: ``python bench/photos_coverage.py --csv A.csv,B.csv,… [--scene data_samples]`` → bench/photos_coverage.{csv,png}.
"""
from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline import io  # noqa: E402
from pipeline.evaluate import photo_truths  # noqa: E402


def greedy(scene: Path) -> list[tuple[str, int, int]]:
    """[(photo name, overexposed points covered so far, overexposed points in all)] in greedy order."""
    trs = {p["name"]: io.read_npz(scene / p["truth"], "pcrelight.truth/1") for p in photo_truths(scene)}
    over = next(iter(trs.values()))["overexposed"].astype(bool)
    vis = {n: t["photo_visible"].astype(bool) & over for n, t in trs.items()}
    got, order = np.zeros_like(over), []
    while vis:
        n = max(vis, key=lambda k: int((vis[k] & ~got).sum()))
        got |= vis.pop(n)
        order.append((n, int(got.sum()), int(over.sum())))
    return order


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="data_samples")
    ap.add_argument("--csv", default="", help="comma-separated end_to_end.py CSVs holding the greedy prefixes' rows")
    ap.add_argument("--out", default="bench/photos_coverage")
    a = ap.parse_args()
    scene = Path(a.scene)
    order = greedy(scene)
    rows_in = [r for f in a.csv.split(",") if f for r in csv.DictReader(open(f))]
    out = []
    for k, (name, cov, n_over) in enumerate(order, start=1):
        names = [o[0] for o in order[:k]]
        want = frozenset(names)                          # a set's rows in any order of its names
        for view in ("view1", "view2"):
            row = {"photos": k, "set": "+".join(names), "added": name, "overexposed_covered": cov,
                   "overexposed": n_over, "coverage": cov / n_over, "view": view}
            for kind, tag in (("pipeline", ""), ("seen exact, rest LDR", "oracle_")):
                m = [r for r in rows_in if frozenset(r["photo"].split("+")) == want and r["cloud"] == kind
                     and r["view"] == view and r.get("material", "lambert") in ("lambert", "")]
                if m:
                    row.update({f"{tag}{c}": float(m[-1][c]) for c in ("ratio_r", "ratio_g", "ratio_b", "rms_block")})
            out.append(row)
    fields = ["photos", "set", "added", "overexposed_covered", "overexposed", "coverage", "view", "ratio_r", "ratio_g",
              "ratio_b", "rms_block", "oracle_ratio_r", "oracle_ratio_g", "oracle_ratio_b", "oracle_rms_block"]
    with io.atomic_path(a.out + ".csv") as tmp, open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields)
        w.writeheader()
        for r in out:
            w.writerow({k: (f"{v:.4f}" if isinstance(v, float) else v) for k, v in r.items()})
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    ks = [o[0] for o in enumerate(order, start=1)]
    ax[0].plot(ks, [o[1] / o[2] for o in order], "o-")
    for k, (name, cov, n) in zip(ks, order):
        ax[0].annotate(f"+{name}", (k, cov / n), textcoords="offset points", xytext=(4, -12))
    ax[0].set_xlabel("photos (greedy by overexposed points added)"); ax[0].set_ylabel("overexposed points seen")
    ax[0].set_ylim(0, 1); ax[0].set_xticks(ks)
    for view, st in (("view1", "o-"), ("view2", "s-")):
        for tag, lab in (("", "pipeline"), ("oracle_", "oracle")):
            pts = [(r["photos"], r[f"{tag}rms_block"]) for r in out if r["view"] == view and f"{tag}rms_block" in r]
            if pts:
                ax[1].plot(*zip(*pts), st if not tag else st.replace("-", "--"), label=f"{lab} {view}")
    ax[1].set_xlabel("photos"); ax[1].set_ylabel("4×4 block RMS vs path tracer (relit Lambert)")
    ax[1].set_xticks(ks); ax[1].legend()
    fig.tight_layout()
    io.save_figure(a.out + ".png", fig)
    for r in out:
        print(r)


if __name__ == "__main__":
    main()
