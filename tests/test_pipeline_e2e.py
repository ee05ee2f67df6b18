"""End to end: `pcrelight run` chains every stage on the `tiny` ground truth in a temp dir, and
the result is checked against the truth (not only exit codes)."""

from __future__ import annotations

import json

import numpy as np

from pipeline import io
from pipeline.evaluate import cloud_metrics


def _config(tmp_path, scene):
    cfg = tmp_path / "tiny.toml"
    cfg.write_text(f"""seed = 0
[run]
inputs = "{scene}"
workspace = "{tmp_path / 'ws'}"
view = "view1"
[render-cubemaps]
size = 64
[patchmatch]
iterations = 3
[relight]
method = "hybrid"
size = "48x48"
microbuffer = 16
""")
    return cfg


def test_run_every_stage_on_tiny(tiny_scene, tmp_path, cli_run):
    cfg = _config(tmp_path, tiny_scene)
    code, out, err = cli_run("run", cfg, "-q")
    assert code == 0, err
    ws = tmp_path / "ws"
    rep = json.loads((ws / "run.json").read_text())
    assert rep["order"] == ["expose-match", "render-cubemaps", "patchmatch", "reproject", "poisson",
                            "build-bsh", "relight"]
    assert all(rep["stages"][s]["seconds"] > 0 for s in rep["order"])

    # the expanded cloud is closer to the truth than the LDR cloud on the overexposed points
    truth = io.read_npz(tiny_scene / "truth" / "truth.npz", "pcrelight.truth/1")
    gt = io.read_cloud(tiny_scene / "cloud_gt.ply")
    ldr = io.read_cloud(tiny_scene / "cloud_ldr.ply")
    hdr = io.read_cloud(ws / "cloud_hdr.ply")
    over = truth["overexposed"].astype(bool)
    m_ldr = cloud_metrics(ldr.colors, gt.colors * float(truth["e"]), over)
    m_hdr = cloud_metrics(hdr.colors, gt.colors * float(truth["e"]), over)
    assert m_hdr["cloud_rms_over"] < m_ldr["cloud_rms_over"]
    assert np.array_equal(hdr.points, ldr.points)
    # points that were not overexposed keep their LDR colour exactly
    keep = ~over & (hdr.source == 0)
    assert keep.sum() > 0.5 * len(hdr)
    np.testing.assert_array_equal(hdr.colors[keep], ldr.colors[keep])

    # the relit object: finite linear HDR, alpha = the object's mask (the reference's, up to edge pixels)
    relit = io.read_image(ws / "relit.exr")
    assert relit.shape == (48, 48, 4) and np.all(np.isfinite(relit))
    mask = relit[..., 3] > 0.5
    assert mask.sum() > 100 and np.all(relit[~mask, :3] == 0) and np.all(relit[mask, :3].sum(axis=1) > 0)
    stats = json.loads((ws / "stats.json").read_text())
    assert stats["method"] == "hybrid"
    assert (ws / "relit.png").stat().st_size > 0

    # a second run finds every output up to date and skips every stage
    code, _, err = cli_run("run", cfg, "-q")
    assert code == 0, err
    rep = json.loads((ws / "run.json").read_text())
    assert all(s.get("skipped") for s in rep["stages"].values())


def test_run_rejects_unknown_table_and_stage(tiny_scene, tmp_path, cli_run):
    cfg = _config(tmp_path, tiny_scene)
    cfg.write_text(cfg.read_text() + "[relite]\nsize = 1\n")
    code, _, err = cli_run("run", cfg)
    assert code == 2 and "unknown table [relite]" in err and err.count("\n") == 1
    cfg = _config(tmp_path, tiny_scene)
    code, _, err = cli_run("run", cfg, "--from", "nope")
    assert code == 2 and "--from/--to must be one of" in err
