"""End to end: `pcrelight run` chains every stage on the `tiny` ground truth in a temp dir, and
the result is checked against the truth (not only exit codes)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline import io
from pipeline.run import runner, stages
from pipeline.metrics import cloud_metrics
from pipeline.io.workspace import Workspace

READERS = ("read_cloud", "read_image", "image_channels", "read_npz", "read_json", "read_mesh", "read_object")


def _files(root: Path) -> dict[Path, int]:
    return {p.resolve(): p.stat().st_mtime_ns for p in root.rglob("*") if p.is_file() and not p.name.startswith(".")}


def _record(monkeypatch) -> tuple[dict[str, set[Path]], dict[str, set[Path]], dict[str, Path]]:
    """Record, per stage, the files it reads (through pipeline.io's readers) and the files it writes
    (new or changed in the workspace), and the workspace root."""
    reads: dict[str, set[Path]] = {}
    writes: dict[str, set[Path]] = {}
    current: list[str] = []
    seen: dict[str, Path] = {}
    run = stages.Stage.run

    def recording_run(self, ws, cfg):
        seen["root"] = ws.root
        before = _files(ws.root)
        current.append(self.verb)
        try:
            return run(self, ws, cfg)
        finally:
            current.pop()
            writes[self.verb] = {p for p, m in _files(ws.root).items() if before.get(p) != m}

    monkeypatch.setattr(stages.Stage, "run", recording_run)
    for name in READERS:
        def reader(path, *a, _read=getattr(io, name), **k):
            if current:
                reads.setdefault(current[-1], set()).add(Path(path).resolve())
            return _read(path, *a, **k)
        monkeypatch.setattr(io, name, reader)
    return reads, writes, seen


def _check_declarations(reads, writes, ws) -> None:
    """Each stage wrote its declared outputs, nothing undeclared (its preview is declared too), and
    read only its declared inputs."""
    for st in stages.STAGES:
        assert all(p.exists() for p in st.outputs(ws)), st.verb
        outs = {p.resolve() for p in runner.files_of(st.outputs(ws))}
        may = {p.resolve() for p in runner.files_of(st.all_outputs(ws))}
        assert outs <= writes[st.verb] <= may, (st.verb, sorted(writes[st.verb] ^ may))
        assert st.preview is None or st.preview_path(ws).resolve() in writes[st.verb]  # the tiny scene has something to show
        declared = [p.resolve() for p in st.inputs(ws)]
        stray = [p for p in reads.get(st.verb, ()) if not any(p == d or d in p.parents for d in declared)]
        assert reads.get(st.verb) and not stray, (st.verb, stray)


def _config(tmp_path, scene):
    cfg = tmp_path / "tiny.toml"
    cfg.write_text(f"""seed = 0
[run]
inputs = "{scene}"
workspace = "{tmp_path / 'ws'}"
view = "view1"
hdr_out = true
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


def test_run_every_stage_on_tiny(tiny_scene, tmp_path, cli_run, monkeypatch):
    cfg = _config(tmp_path, tiny_scene)
    with monkeypatch.context() as mp:
        reads, writes, seen = _record(mp)
        code, out, err = cli_run("run", cfg, "-q")
    assert code == 0, err
    ws = tmp_path / "ws"
    # the registry's declarations are what the stages really read and write (what an executor ships)
    _check_declarations(reads, writes, Workspace(tiny_scene, seen["root"]))
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
    # [run] hdr_out: relit.hdr and composite.hdr (Radiance RGBE) beside their EXRs, within 2⁻⁷ of a pixel's largest channel
    for name in ("relit", "composite"):
        exr, hdr = io.read_image(ws / f"{name}.exr")[..., :3], io.read_image(ws / f"{name}.hdr")
        assert hdr.shape == exr.shape and np.all(np.abs(hdr - exr) <= 2.0 ** -7 * exr.max(axis=2, keepdims=True) * 1.001)

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
