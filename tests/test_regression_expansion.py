"""CI regression of the HDR expansion on the shipped `small` scene (data_samples/), CI-sized:
expose-match → render-cubemaps (128² faces) → patchmatch (2 iterations, lum and rgb transfer) →
reproject → poisson, measured against cloud_gt.ply like `pcrelight evaluate` (Table 2).

Recorded values (llvmpipe-free CPU stages, seed 0, 2026-11-25) with a fixed headroom of 2 % of the
value (numba float reductions may differ across CPUs). The α error is a property of the ground
truth (the photo looks at the brightest region, brighter than the cloud as a whole) and of the
paper's histogram matching; it is recorded, not claimed good. Changing a bound is a deliberate,
explained commit.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from conftest import SAMPLES

RECORDED: dict[str, float] = {
    "alpha_rel_error": 0.46988,
    "ldr_rms_over_in_range": 2.00995,          # the input: a fixed number (guards the metric itself)
    "ldr_log_rms": 0.142868,
    "pmatch_lum_rms_over_in_range": 1.78928,
    "pmatch_lum_log_rms": 0.138811,
    "pmatch_rgb_rms_over_in_range": 1.76731,
    "pmatch_rgb_log_rms": 0.138705,
}
HEADROOM = 0.02

pytestmark = pytest.mark.skipif(not (SAMPLES / "truth").exists(), reason="data_samples/ not present")


def run_chain(out: Path) -> dict[str, float]:
    """Run the CI-sized expansion and return the metrics."""
    from pipeline import expose_match, io, patchmatch, poisson, render_cubemaps, reproject
    from pipeline.config import resolve
    from pipeline.evaluate import cloud_metrics

    photo, ldr = SAMPLES / "photo.exr", SAMPLES / "cloud_ldr.ply"
    seed = {"seed": 0}
    expose_match.run_expose_match(photo, ldr, out / "exposure.npz", out / "photo_ldr.exr",
                                  resolve(expose_match.ExposeMatchConfig, None, "expose-match", seed))
    render_cubemaps.run_render_cubemaps(ldr, out / "cubemaps",
                                        resolve(render_cubemaps.RenderCubemapsConfig, None, "render-cubemaps",
                                                {**seed, "size": 128}))
    patchmatch.run_patchmatch(out / "cubemaps", photo, out / "photo_ldr.exr", out / "exposure.npz", out / "faces",
                              resolve(patchmatch.PatchmatchConfig, None, "patchmatch", {**seed, "iterations": 2}))
    tr = io.read_npz(SAMPLES / "truth" / "truth.npz", "pcrelight.truth/1")
    e, k = float(tr["e"]), float(tr["k"])
    truth = io.read_cloud(SAMPLES / "cloud_gt.ply").colors * e
    over = tr["overexposed"].astype(bool)
    peak = float(io.luminance(io.read_image(photo)[..., :3]).max()) / k * e
    in_range = io.luminance(truth) <= peak
    alpha = float(io.read_npz(out / "exposure.npz", "pcrelight.exposure/1")["alpha"])
    res = {"alpha_rel_error": abs(alpha - float(tr["alpha_true"])) / float(tr["alpha_true"])}
    m = cloud_metrics(io.read_cloud(ldr).colors, truth, over, in_range)
    res.update(ldr_rms_over_in_range=m["cloud_rms_over_in_range"], ldr_log_rms=m["log_rms"])
    for transfer in ("lum", "rgb"):
        reproject.run_reproject(ldr, out / "cubemaps", out / "faces", out / f"proj_{transfer}.ply",
                                resolve(reproject.ReprojectConfig, None, "reproject", {**seed, "transfer": transfer}))
        poisson.run_poisson(out / f"proj_{transfer}.ply", out / f"hdr_{transfer}.ply",
                            resolve(poisson.PoissonConfig, None, "poisson", seed), ldr=ldr)
        m = cloud_metrics(io.read_cloud(out / f"hdr_{transfer}.ply").colors, truth, over, in_range)
        res[f"pmatch_{transfer}_rms_over_in_range"] = m["cloud_rms_over_in_range"]
        res[f"pmatch_{transfer}_log_rms"] = m["log_rms"]
    return res


@pytest.fixture(scope="module")
def metrics(tmp_path_factory):
    return run_chain(tmp_path_factory.mktemp("expansion"))


@pytest.mark.parametrize("key", sorted(RECORDED))
def test_metric_within_recorded_bound(metrics, key):
    assert metrics[key] <= RECORDED[key] * (1 + HEADROOM), f"{key} = {metrics[key]:.5g} (recorded {RECORDED[key]:.5g})"


def test_pmatch_beats_ldr_within_the_photos_range(metrics):
    """PatchMatch's HDR values are closer to the truth than the clipped LDR ones, on the
    overexposed points whose truth the photo can show, and in log luminance."""
    for t in ("lum", "rgb"):
        assert metrics[f"pmatch_{t}_rms_over_in_range"] < metrics["ldr_rms_over_in_range"]
        assert metrics[f"pmatch_{t}_log_rms"] < metrics["ldr_log_rms"]
