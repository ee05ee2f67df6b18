"""bench/photos_coverage.py's greedy order of shots (issue 25's plot) on the shipped sample's truth masks."""

from __future__ import annotations

import sys

import numpy as np

from conftest import ROOT, SAMPLES

sys.path.insert(0, str(ROOT / "bench"))
from photos_coverage import candidates, greedy  # noqa: E402

from pipeline import io  # noqa: E402


def _masks(names: list[str]) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Each shot's overexposed points it shows (truth photo_visible), and the overexposed mask."""
    trs = {p["name"]: io.read_npz(SAMPLES / p["truth"], "pcrelight.truth/1")
           for p in candidates(SAMPLES, ",".join(names))}
    over = trs[names[0]]["overexposed"].astype(bool)
    return {n: t["photo_visible"].astype(bool) & over for n, t in trs.items()}, over


def test_candidates_all_adds_the_panorama():
    assert [p["name"] for p in candidates(SAMPLES)] == ["bright", "lights", "sun"]
    allc = candidates(SAMPLES, "all")
    assert [p["name"] for p in allc] == ["bright", "lights", "sun", "pano"]
    assert allc[-1]["model"] == "equirect" and allc[-1]["truth"] == "truth/truth_pano.npz"


def test_greedy_takes_the_shot_adding_most_overexposed_points():
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
