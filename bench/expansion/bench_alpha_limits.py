"""What α a ground truth's photos can give at all (issue 14: "α within 2 % on every photo of the tiny
and small presets").

    .venv/bin/python -m bench.expansion.bench_alpha_limits SCENE_DIR [SCENE_DIR ...] [--out bench/expansion/alpha_limits.csv]

For every photo of each make-scene folder, at the photo's TRUE pose (truth/*.npz), with
:func:`pipeline.expansion.register_photo.exposure_from_pose` (expose-match's exposure step, its defaults):

* ``ldr``: the LDR cloud (what expose-match sees) — the error that remains with a perfect registration;
* ``boot_sd``: the bootstrap standard deviation of the ``ldr`` estimate over its photo blocks (300
  resamples): the noise of the estimate itself;
* ``reg_from_truth_deg/_m``: the pose the point refinement (:func:`refine_points`, σ 8, 4 then 2, 1 px)
  ends at when STARTED at the true pose — where the registration's objective has its optimum on these
  data (0 when the data pin the pose).

Rows: scene, photo, spp of cloud / photo, photo size, blocks, α errors (relative), boot_sd, pose drift.
"""
from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]

from pipeline import io  # noqa: E402
from pipeline.expansion import register_photo as rp  # noqa: E402
from pipeline.measure.evaluate import photo_truths  # noqa: E402
from pipeline.expansion.splats import knn_splat_radii  # noqa: E402

FIELDS = ("scene", "photo", "points", "cloud_rel_se", "cloud_spp", "photo_spp", "photo_size", "blocks", "alpha_err_ldr", "boot_sd", "reg_from_truth_deg", "reg_from_truth_m")


def block_bootstrap(ex: dict, n: int = 300, seed: int = 0) -> float:
    """Bootstrap SD of α_sum = Σ cloud / Σ photo over the counted blocks, relative to α_sum."""
    cy, py = np.asarray(ex["block_cloud"]), np.asarray(ex["block_photo"])
    if len(cy) < 2:
        return float("nan")
    rng = np.random.default_rng(seed)
    j = rng.integers(0, len(cy), (n, len(cy)))
    return float(np.std(cy[j].sum(1) / py[j].sum(1)) / (cy.sum() / py.sum()))


def run(scene: Path) -> list[dict]:
    cl = io.read_cloud(scene / "cloud_ldr.ply")
    P, C, N = cl.points, cl.colors, cl.normals
    radii = knn_splat_radii(P)
    sj = io.read_json(scene / "scene.json")
    rows = []
    for ph in photo_truths(scene):
        t = io.read_npz(scene / ph["truth"], "pcrelight.truth/1")
        img = io.read_image(scene / ph["file"])[..., :3].astype(np.float64)
        w2c = np.asarray(t["photo_world_to_camera"], float)
        R, eye, K = w2c[:3, :3], -w2c[:3, :3].T @ w2c[:3, 3], np.asarray(t["photo_K"], float)
        at = float(t["alpha_true"])
        ldr = rp.exposure_from_pose(P, C, img, K, R, eye, normals=N)
        f = rp.refine_points(P, C, img, K, R, eye, sigmas_px=(8.0, 4.0, 2.0, 1.0), normals=N, radii=radii)
        deg, m = rp.pose_error(f.R, f.eye, R, eye)
        rows.append(dict(scene=scene.name, photo=ph["name"], points=len(P),
                         cloud_rel_se=float(sj["cloud"]["precision"]["rel_se_median"]), cloud_spp=round(sj["cloud"]["precision"]["spp_mean"]),
                         photo_spp=sj["photo"]["spp"], photo_size="x".join(map(str, img.shape[1::-1])),
                         blocks=ldr["blocks"], alpha_err_ldr=ldr["alpha_sum"] / at - 1,
                         boot_sd=block_bootstrap(ldr), reg_from_truth_deg=deg, reg_from_truth_m=m))
        print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in rows[-1].items()}, flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="+", type=Path)
    ap.add_argument("--out", default="bench/expansion/alpha_limits.csv")
    a = ap.parse_args()
    rows = [r for s in a.scenes for r in run(s)]
    with open(a.out, "w", newline="") as fh:
        w = csv.DictWriter(fh, FIELDS)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.5g}" if isinstance(v, float) else v) for k, v in r.items()})
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
