"""pcrelight trade (pipeline/measure/trade.py): the preset rule on a synthetic CSV, the front, resume and budget (a
sweep whose pipeline runs are replaced by fakes: no GL), the shipped presets are the rule's picks from the
shipped trade.csv, one-line errors, and a real quick sweep on the tiny scene end to end."""

from __future__ import annotations

import time
import tomllib
from pathlib import Path

import pytest

from pipeline import io
from pipeline.measure import trade
from pipeline.config import PRESET_DIR, preset_tables, resolve
from pipeline.relight.relight import RelightConfig

ROOT = Path(__file__).resolve().parents[1]


def _row(point: str, mat: str, seconds: float, err: float, **knobs) -> dict:
    base = {f"{v}.{k}": "0" for v, k in trade.KNOBS}
    base.update({f"relight.{k}": str(v) for k, v in knobs.items()})
    base["relight.method"] = point  # one configuration per point name
    return {"key": f"{point}/{mat}", "point": point, **base, "view": "view1", "material": mat,
            "seconds": seconds, "err": err, "gather_err": err}


def test_rule_on_a_synthetic_csv():
    """exact = smallest worst ratio to each pair's best; balanced / fast = cheapest within 1.15× / 2× of exact's
    error on every pair (mean seconds); a configuration missing a pair is no candidate."""
    rows = []
    table = {  # point: (seconds, err lambert, err ggx)
        "A": (10.0, 0.100, 0.100),   # the most accurate on both
        "B": (5.0, 0.110, 0.112),    # within 15 % on both: balanced
        "C": (4.0, 0.110, 0.120),    # cheaper, but ggx 20 % over exact: not balanced
        "D": (1.0, 0.190, 0.150),    # within 2×: fast
        "E": (0.5, 0.300, 0.100),    # cheapest, lambert 3×: neither
        "F": (0.1, 0.050, None),     # best lambert, but never measured on ggx: no candidate
    }
    for p, (s, el, eg) in table.items():
        rows.append(_row(p, "lambert", s, el))
        if eg is not None:
            rows.append(_row(p, "ggx0.25", s, eg))
    picks = trade.pick_presets(rows)
    assert {k: v["point"] for k, v in picks.items()} == {"exact": "A", "balanced": "B", "fast": "D"}
    # the front of one pair: F (fastest, best lambert) dominates everything on lambert; on ggx: E, D, A …
    assert [r["point"] for r in trade.pareto([r for r in rows if r["material"] == "lambert"])] == ["F"]
    assert [r["point"] for r in trade.pareto([r for r in rows if r["material"] == "ggx0.25"])] == ["E"]
    rep = trade.preset_report(rows, picks)
    assert rep["exact"]["pairs"]["view1/ggx0.25"]["on_front"] is False
    assert rep["exact"]["pairs"]["view1/ggx0.25"]["err_over_front"] == pytest.approx(0.0)  # E is as good, faster
    assert rep["exact"]["pairs"]["view1/ggx0.25"]["time_over_front"] == pytest.approx(10.0 / 0.5 - 1)
    with pytest.raises(Exception, match="every view"):
        trade.pick_presets([_row("F", "lambert", 1, 0.1), _row("G", "ggx0.25", 1, 0.1)])


def test_preset_files_round_trip():
    """preset_toml writes one table per stage with the knobs of the picked row; config reads them back."""
    rows = [_row("A", "lambert", 1.0, 0.1, microbuffer=16)]
    rows[0].update({"relight.method": "hybrid", "relight.stop_multiple": "4", "relight.omega_tr": "32",
                    "render-cubemaps.size": "256", "poisson.solver": "auto"})
    rep = trade.preset_report(rows, {"fast": rows[0]})
    text = trade.preset_toml("fast", rows[0], rep["fast"], "trade.csv")
    data = tomllib.loads(text)
    assert data["relight"]["method"] == "hybrid" and data["relight"]["microbuffer"] == 16
    assert data["render-cubemaps"]["size"] == 256 and data["poisson"]["solver"] == "auto"
    assert isinstance(data["relight"]["stop_multiple"], int | float)


# ----------------------------------------------------------------------------- resume and budget (fakes)
def _fake_sweep(monkeypatch, scene: Path, calls: list, sleep: float = 0.0):
    """Replace the pipeline runs: no expansion, the reference itself as the relit image."""
    ref = io.read_image(scene / "truth" / "full_view1_lambert.exr")
    e = float(io.read_json(scene / "scene.json")["exposure_e"])
    img = ref.copy()
    img[..., :3] *= e

    def bsh(self, tables):
        return scene / "none.npz", 10.0, 1.0

    def relight(self, bsh, tables, view, material, scene_json, repeat=None):
        calls.append((tables["relight"].get("microbuffer"), material))
        time.sleep(sleep)
        return img, {"nodes_visited_per_pixel": 1.0, "nodes": 1, "gl": {"renderer": "fake"}}, 0.5 + len(calls) * 0.01

    monkeypatch.setattr(trade.Sweep, "bsh", bsh)
    monkeypatch.setattr(trade.Sweep, "relight", relight)
    monkeypatch.setattr(trade.Sweep, "warm_up", lambda self, *a: None)


def test_resume_skips_done_rows_and_budget_stops_cleanly(monkeypatch, tiny_scene, tmp_path):
    calls: list = []
    _fake_sweep(monkeypatch, tiny_scene, calls, sleep=0.3)
    out = tmp_path / "out"
    cfg = resolve(trade.TradeConfig, None, "trade", {"grid": "quick", "materials": "lambert", "budget_min": 0.3 / 60})
    s1 = trade.run_trade(tiny_scene, out, tmp_path / "work", cfg)
    n1 = len(calls)
    assert not s1["complete"] and n1 == 1 and s1["grid_rows"] == 4  # at least one row a run, then the budget
    rows1 = trade.read_rows(out / "trade.csv")
    assert len(rows1) == n1
    cfg = resolve(trade.TradeConfig, None, "trade", {"grid": "quick", "materials": "lambert"})
    s2 = trade.run_trade(tiny_scene, out, tmp_path / "work", cfg)
    assert s2["complete"] and s2["measured_now"] == 4 - n1 and len(calls) == 4
    rows2 = trade.read_rows(out / "trade.csv")
    assert rows2[:n1] == rows1 and len({r["key"] for r in rows2}) == 4
    s3 = trade.run_trade(tiny_scene, out, tmp_path / "work", cfg)
    assert s3["measured_now"] == 0 and len(calls) == 4 and trade.read_rows(out / "trade.csv") == rows2
    for name in trade.PRESET_NAMES:
        assert "relight" in tomllib.loads((out / f"{name}.toml").read_text())
    assert (out / "trade.png").stat().st_size > 0
    # the relit image is the reference × e: no error beyond the reference's own noise
    assert all(float(r["err"]) < 1e-6 and abs(float(r["mean_ratio_block"]) - 1) < 1e-6 for r in rows2)


def test_missing_reference_is_one_line(cli_run, tmp_path, tiny_scene):
    import shutil

    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    (scene / "truth" / "full_view1_ggx0.25.exr").unlink()
    code, out, err = cli_run("trade", "--scene", scene, "--out", tmp_path / "o", "--grid", "quick")
    lines = [ln for ln in err.splitlines() if ln.startswith("pcrelight:")]
    assert code == 1 and len(lines) == 1 and "full_view1_ggx0.25.exr" in lines[0], err
    assert not (tmp_path / "o").exists()
    code, out, err = cli_run("trade", "--scene", scene, "--budget-min", "-1")
    assert code == 2 and "--budget-min" in err


# ----------------------------------------------------------------------------- the shipped presets
def test_shipped_presets_are_the_rules_picks_from_the_shipped_csv():
    """configs/presets/{fast,balanced,exact}.toml are what the rule picks from configs/presets/trade.csv (a
    re-measured CSV that moves the front fails here until `pcrelight trade` rewrites the files), and
    relight --preset reads exactly their [relight] tables."""
    rows = trade.read_rows(PRESET_DIR / "trade.csv")
    assert rows, "configs/presets/trade.csv is empty"
    picks = trade.pick_presets(rows)
    rep = trade.preset_report(rows, picks)
    for name in trade.PRESET_NAMES:
        want = tomllib.loads(trade.preset_toml(name, picks[name], rep[name], "trade.csv"))
        have = tomllib.loads((PRESET_DIR / f"{name}.toml").read_text())
        assert have == want, name
        assert RelightConfig.presets()[name] == have["relight"]
    assert set(preset_tables("relight")) == set(trade.PRESET_NAMES)


# ----------------------------------------------------------------------------- a real sweep
def test_tiny_quick_sweep_end_to_end(tiny_scene, tmp_path):
    """The quick grid on the tiny scene (small faces, one material): 4 rows measured, the CSV's numbers
    are the compare_to_reference of relit.exr ÷ e, m 8 visits fewer nodes than m 16, and the half-size
    cube maps cost less expansion time than the base's."""
    pytest.importorskip("moderngl")
    from pipeline import gl
    from pipeline.errors import GLUnavailable

    try:
        gl.create_context().release()
    except GLUnavailable as e:
        pytest.skip(f"no headless GL: {e}")
    toml = tmp_path / "base.toml"
    toml.write_text("[render-cubemaps]\nsize = 64\nmax_views = 1\n[patchmatch]\niterations = 1\nlevels = 1\n"
                    "[relight]\nmethod = \"hybrid\"\nmicrobuffer = 16\nbounces = 0\n")
    cfg = resolve(trade.TradeConfig, None, "trade", {"grid": "quick", "materials": "lambert"})
    s = trade.run_trade(tiny_scene, tmp_path / "out", tmp_path / "work", cfg, config_toml=toml)
    assert s["complete"] and s["rows"] == 4
    rows = {r["point"]: r for r in trade.read_rows(tmp_path / "out" / "trade.csv")}
    assert set(rows) == {"base", "m=8", "stop=8", "cube/2"}
    assert rows["cube/2"]["render-cubemaps.size"] == "32" and rows["base"]["render-cubemaps.size"] == "64"
    assert float(rows["m=8"]["nodes_per_pixel"]) < float(rows["base"]["nodes_per_pixel"])
    for r in rows.values():
        assert 0 < float(r["err"]) < 1 and 0.5 < float(r["mean_ratio_block"]) < 1.5
        assert float(r["seconds"]) == pytest.approx(float(r["expansion_s"]) + float(r["bsh_s"]) + float(r["relight_s"]),
                                                    rel=1e-4)
    assert rows["base"]["expansion_s"] == rows["m=8"]["expansion_s"]  # one expansion, measured once
    assert (tmp_path / "out" / "trade.png").exists() and (tmp_path / "out" / "trade.json").exists()
