"""What each extra photo buys (issue 25): overexposed-point coverage and end-to-end error against the number of
photos, the photos chosen greedily by the overexposed points they add.

Coverage comes from the ground truth (truth ``photo_visible`` of each candidate: scene.json ``photos``, and with
``--candidates all`` its panorama ``pano`` too — in frame, facing it, first hit from its eye; counted on the
overexposed points), with the share of the overexposed points' flux those points carry (Σ true luminance of
``cloud_gt.ply``: the points are uniform by area) and the points on scene.json's lamps they show (make-scene's
``lamp_points``: facing the eye, unoccluded). The end-to-end error per photo count is read from
``bench/photos/end_to_end.py`` CSVs of the greedy prefixes (Lambert rows; ``pipeline``: the pipeline with defaults on that
set; ``seen exact, rest LDR``: the oracle; both ÷ the path tracer and ÷ relight on the exact cloud) — print the
prefixes with ``--order``, run them, then this again with their CSVs:

    python -m bench.photos.photos_coverage --scene S --order                       # the greedy prefixes, one a line
    python -m bench.photos.end_to_end --scene S --photos none --sets A,A+B,A+B+C --oracle --csv A.csv

Run: ``python -m bench.photos.photos_coverage --csv A.csv,B.csv,… [--scene data_samples] [--candidates all]
[--max-photos 4] [--out bench/photos/photos_coverage]`` → OUT.{csv,png}.
"""
from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np


from pipeline import io  # noqa: E402
from pipeline.color import luminance  # noqa: E402
from pipeline.measure.evaluate import photo_set, photo_truths  # noqa: E402

RATIOS = ("ratio_r", "ratio_g", "ratio_b", "rms_block", "exact_ratio_r", "exact_ratio_g", "exact_ratio_b",
          "exact_rms_block")


def candidates(scene: Path, spec: str = "") -> list[dict]:
    """The shots to choose from: ``""`` = scene.json ``photos``; ``"all"`` = those and the panorama (``pano``) where
    the scene has one; else comma-separated names (:func:`pipeline.measure.evaluate.photo_set`'s, ``pano`` included)."""
    if spec == "all":
        names = [p["name"] for p in photo_truths(scene)]
        names += ["pano"] if "panorama" in io.read_json(scene / "scene.json") else []
    else:
        names = [n for n in spec.split(",") if n] or [p["name"] for p in photo_truths(scene)]
    return photo_set(scene, "+".join(names))


def greedy(scene: Path, spec: str = "") -> list[tuple[str, int, int, float, int, int]]:
    """[(shot name, overexposed points covered so far, overexposed points in all, share of the overexposed points'
    flux covered so far, lamp points covered so far, lamp points in all)] in greedy order (most new overexposed
    points first; ties: the candidates' order)."""
    from pipeline.scene.make_scene import lamp_points

    trs = {p["name"]: io.read_npz(scene / p["truth"], "pcrelight.truth/1") for p in candidates(scene, spec)}
    over = next(iter(trs.values()))["overexposed"].astype(bool)
    gt = io.read_cloud(scene / "cloud_gt.ply")
    y = luminance(gt.colors, np.float64) * over
    lamp = lamp_points(gt.points, io.read_json(scene / "scene.json").get("lamps"))
    seen = {n: t["photo_visible"].astype(bool) for n, t in trs.items()}
    got, lit, order = np.zeros_like(over), np.zeros_like(over), []
    while seen:
        n = max(seen, key=lambda k: int((seen[k] & over & ~got).sum()))
        v = seen.pop(n)
        got |= v & over
        lit |= v & lamp
        order.append((n, int(got.sum()), int(over.sum()), float(y[got].sum() / y.sum()), int(lit.sum()),
                      int(lamp.sum())))
    return order


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="data_samples")
    ap.add_argument("--candidates", default="", help="shots to choose from: empty = scene.json photos; 'all' = "
                    "those and the panorama 'pano'; or comma-separated names")
    ap.add_argument("--max-photos", type=int, default=0, help="rows and plot up to this many shots (0: all)")
    ap.add_argument("--order", action="store_true", help="print the greedy prefixes (end_to_end.py --sets) and stop")
    ap.add_argument("--csv", default="", help="comma-separated end_to_end.py CSVs holding the greedy prefixes' rows")
    ap.add_argument("--out", default="bench/photos/photos_coverage", help="output stem: OUT.csv, OUT.png")
    a = ap.parse_args()
    scene = Path(a.scene)
    order = greedy(scene, a.candidates)
    if a.max_photos:
        order = order[:a.max_photos]
    if a.order:
        print(",".join("+".join(o[0] for o in order[:k]) for k in range(1, len(order) + 1)))
        return
    rows_in = [r for f in a.csv.split(",") if f for r in csv.DictReader(open(f))]
    out = []
    for k, (name, cov, n_over, flux, lamps, n_lamps) in enumerate(order, start=1):
        names = [o[0] for o in order[:k]]
        want = frozenset(names)                          # a set's rows in any order of its names
        for view in ("view1", "view2"):
            row = {"photos": k, "set": "+".join(names), "added": name, "overexposed_covered": cov,
                   "overexposed": n_over, "coverage": cov / n_over, "flux_covered": flux, "lamp_points_covered": lamps,
                   "lamp_points": n_lamps, "view": view}
            for kind, tag in (("pipeline", ""), ("seen exact, rest LDR", "oracle_")):
                m = [r for r in rows_in if frozenset(r["photo"].split("+")) == want and r["cloud"] == kind
                     and r["view"] == view and r.get("material", "lambert") in ("lambert", "")]
                if m:
                    row.update({f"{tag}{c}": float(m[-1][c]) for c in RATIOS if m[-1].get(c)})
                if m and not tag and m[-1].get("alpha_rel_error"):
                    row["alpha_rel_error"] = float(m[-1]["alpha_rel_error"])
            out.append(row)
    fields = ["photos", "set", "added", "overexposed_covered", "overexposed", "coverage", "flux_covered",
              "lamp_points_covered", "lamp_points", "view",
              "alpha_rel_error", *RATIOS, *(f"oracle_{c}" for c in RATIOS)]
    with io.atomic_path(a.out + ".csv") as tmp, open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields)
        w.writeheader()
        for r in out:
            w.writerow({k: (f"{v:.4f}" if isinstance(v, float) else v) for k, v in r.items()})
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(15, 4))
    ks = list(range(1, len(order) + 1))
    ax[0].plot(ks, [o[1] / o[2] for o in order], "o-", label="overexposed points")
    ax[0].plot(ks, [o[3] for o in order], "s--", label="their flux (Σ true luminance)")
    if order[0][5]:
        ax[0].plot(ks, [o[4] / o[5] for o in order], "^:", label=f"the {order[0][5]} lamp points")
    for k, (name, cov, n, *_) in zip(ks, order):
        ax[0].annotate(f"+{name}", (k, cov / n), textcoords="offset points", xytext=(4, -12))
    ax[0].set_xlabel("photos (greedy by overexposed points added)"); ax[0].set_ylabel("share seen by the photos")
    ax[0].set_ylim(0, 1.02); ax[0].set_xlim(0.7, len(ks) + 0.6); ax[0].set_xticks(ks)
    ax[0].legend(loc="best", fontsize="small")
    for i, (pre, what) in enumerate((("", "path tracer (truth/full_*)"), ("exact_", "relight on the exact cloud"))):
        for view, st, col in (("view1", "o", "C0"), ("view2", "s", "C1")):
            for tag, lab in (("", "pipeline"), ("oracle_", "oracle")):
                c = f"{tag}{pre}rms_block"
                pts = [(r["photos"], r[c]) for r in out if r["view"] == view and c in r]
                if pts:
                    ax[1 + i].plot(*zip(*pts), st + ("-" if not tag else "--"), color=col, label=f"{lab} {view}")
            gt = [r for r in rows_in if r["cloud"] == "gt" and r["view"] == view
                  and r.get("material", "lambert") in ("lambert", "")]
            if gt and not pre:
                ax[1].axhline(float(gt[-1]["rms_block"]), color=col, ls=":", label=f"exact cloud {view}")
        ax[1 + i].set_xlabel("photos"); ax[1 + i].set_ylabel(f"4×4 block RMS vs {what}")
        ax[1 + i].set_xticks(ks); ax[1 + i].set_ylim(bottom=0)
        if ax[1 + i].lines:
            ax[1 + i].legend()
    ax[1].set_title("relit Lambert object: error"); ax[2].set_title("the expansion's own error")
    fig.tight_layout()
    io.save_figure(a.out + ".png", fig)
    for r in out:
        print(r)


if __name__ == "__main__":
    main()
