"""evaluate: the Table 2 metrics against hand-computed values, and the CLI on the tiny truth."""

from __future__ import annotations

import json

import numpy as np

from pipeline import io
from pipeline.evaluate import cloud_metrics, image_metrics


def test_cloud_metrics_by_hand():
    truth = np.array([[1, 1, 1], [2, 2, 2], [100, 100, 100]], np.float32)
    got = np.ones((3, 3), np.float32)
    m = cloud_metrics(got, truth, over=np.array([0, 1, 1]), in_range=np.array([1, 1, 0], bool))
    assert np.isclose(m["cloud_rms"], np.sqrt((0 + 1 + 99 ** 2) / 3))
    assert np.isclose(m["cloud_rms_over"], np.sqrt((1 + 99 ** 2) / 2))
    assert np.isclose(m["cloud_rms_over_in_range"], 1.0) and m["n_over_in_range"] == 1
    assert np.isclose(m["log_rms"], np.sqrt((0 + np.log10(2) ** 2 + 2.0 ** 2) / 3), rtol=1e-5)


def test_image_metrics_identical_and_scaled():
    rng = np.random.default_rng(0)
    ref = rng.uniform(0.1, 5, (32, 32, 3)).astype(np.float32)
    mask = np.ones((32, 32), bool)
    m = image_metrics(ref, ref, mask)
    assert m["rms"] == 0 and np.isclose(m["ssim"], 1.0)
    m = image_metrics(ref * 1.1, ref, mask)
    assert np.isclose(m["rms"], 0.1, rtol=1e-5) and m["ssim"] < 1


def test_cli_evaluate_tiny(tiny_scene, tmp_path, cli_run):
    code, out, err = cli_run("evaluate", "--truth", tiny_scene, tiny_scene / "cloud_ldr.ply",
                             "--json", tmp_path / "t.json", "--md", tmp_path / "t.md", "--no-render", "-q",
                             "--preview", tmp_path / "t.png")
    assert code == 0, err
    t = json.loads((tmp_path / "t.json").read_text())
    (row,) = t["rows"]
    tr = io.read_npz(tiny_scene / "truth" / "truth.npz", "pcrelight.truth/1")
    gt = io.read_cloud(tiny_scene / "cloud_gt.ply").colors * float(tr["e"])
    ldr = io.read_cloud(tiny_scene / "cloud_ldr.ply").colors
    assert row["method"] == "ldr" and np.isclose(row["cloud_rms"], np.sqrt(((ldr - gt) ** 2).mean()), rtol=1e-6)
    assert "| LDR |" in (tmp_path / "t.md").read_text()
    assert io.read_image(tmp_path / "t.png").shape[2] >= 3
    # a cloud with other points is refused with one line
    io.write_cloud(tmp_path / "cloud_x.ply", io.read_cloud(tiny_scene / "cloud_ldr.ply").subset(np.arange(10)))
    code, _, err = cli_run("evaluate", "--truth", tiny_scene, tmp_path / "cloud_x.ply", "--no-render", "-q")
    assert code == 1 and "has 10 points, the ground truth has" in err and err.count("\n") == 1


def test_tiny_pmatch_beats_ldr_and_every_operator(tiny_scene, tmp_path):
    """Issue 5 on the tiny ground truth: PatchMatch's cloud RMS on the overexposed points (those
    within the photo's range: the photo never sees the sun, whose few points dominate the plain
    column for every method alike) is below LDR's and below every inverse tone-mapping operator's."""
    from pipeline.evaluate import EvaluateConfig, run_all

    cfg_file = tmp_path / "ev.toml"
    cfg_file.write_text("[render-cubemaps]\nsize = 128\n")
    t = run_all(tiny_scene, tmp_path / "ev", cfg_file, EvaluateConfig(render=False))
    rows = {r["method"]: r["cloud_rms_over_in_range"] for r in t["rows"]}
    assert set(rows) == {"ldr", "landis", "banterle", "rhee", "landis-pc", "banterle-pc", "pmatch-lum", "pmatch-rgb"}
    for pm in ("pmatch-lum", "pmatch-rgb"):
        others = {k: v for k, v in rows.items() if not k.startswith("pmatch")}
        assert all(rows[pm] < v for v in others.values()), (pm, rows)
    assert set(t["timings"]) >= {"expose-match", "render-cubemaps", "patchmatch[pmatch]", "evaluate"}
    assert t["alpha"]["estimated"] > 0 and (tmp_path / "ev" / "table.md").exists()
