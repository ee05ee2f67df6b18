"""photos_coverage.py's greedy order of shots (issue 25's plot) checked on the shipped sample's truth masks.

    .venv/bin/python -m bench.photos.check_photos_coverage [SCENE_DIR]

Was tests/test_photos_coverage.py: it checks bench code, and tests never import benches, so it runs with the bench
(the manifest's quick subset); exits non-zero on a failed check, writes nothing.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from bench.photos.photos_coverage import candidates, greedy
from pipeline import io

SAMPLES = Path(__file__).resolve().parents[2] / "data_samples"


def _masks(names: list[str]) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Each shot's overexposed points it shows (truth photo_visible), and the overexposed mask."""
    trs = {p["name"]: io.read_npz(SAMPLES / p["truth"], "pcrelight.truth/1")
           for p in candidates(SAMPLES, ",".join(names))}
    over = trs[names[0]]["overexposed"].astype(bool)
    return {n: t["photo_visible"].astype(bool) & over for n, t in trs.items()}, over


def check_candidates_all_adds_the_panorama():
    assert [p["name"] for p in candidates(SAMPLES)] == ["bright", "lights", "sun"]
    allc = candidates(SAMPLES, "all")
    assert [p["name"] for p in allc] == ["bright", "lights", "sun", "pano"]
    assert allc[-1]["model"] == "equirect" and allc[-1]["truth"] == "truth/truth_pano.npz"


def check_greedy_takes_the_shot_adding_most_overexposed_points():
    order = greedy(SAMPLES, "all")
    vis, over = _masks(["bright", "lights", "sun", "pano"])
    assert sorted(o[0] for o in order) == sorted(vis)
    got = np.zeros_like(over)
    for name, cov, n_over, flux, lamps, n_lamps in order:
        gains = {n: int((m & ~got).sum()) for n, m in vis.items()}
        assert gains[name] == max(gains.values())        # no remaining shot adds more
        got |= vis.pop(name)
        assert cov == int(got.sum()) and n_over == int(over.sum())
        assert 0.0 <= flux <= 1.0 and 0 <= lamps <= n_lamps
    assert order[0][0] == "pano" and order[0][1] > 0.9 * order[0][2]     # the panorama shows 95 % of them
    covs, fluxes, lamps = [o[1] for o in order], [o[3] for o in order], [o[4] for o in order]
    assert covs == sorted(covs) and fluxes == sorted(fluxes) and lamps == sorted(lamps)
    assert order[-1][5] > 0 and order[-1][4] > 0       # the shipped room's gallery lamps, some of them shown


if __name__ == "__main__":
    if len(sys.argv) > 1:
        SAMPLES = Path(sys.argv[1])
    for check in (check_candidates_all_adds_the_panorama, check_greedy_takes_the_shot_adding_most_overexposed_points):
        check()
        print(f"ok {check.__name__}")
