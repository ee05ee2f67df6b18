"""relight --preset fast|balanced|exact: the [relight] tables of configs/presets/*.toml, explicit options win
(Python, TOML, CLI), unknown presets are a one-line error. Presets are applied by ``config.resolve`` (the one
preset mechanism, shared with make-scene); that the shipped files are the rule's picks from the measured trade
is tests/test_trade.py's."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from click.testing import CliRunner

from pipeline.config import resolve
from pipeline.errors import ConfigError
from pipeline.relight.relight import RelightConfig
from pipeline.measure.trade import KNOBS as TRADE_KNOBS

ROOT = Path(__file__).resolve().parents[1]
PRESETS = RelightConfig.presets()
KNOBS = tuple(k for v, k in TRADE_KNOBS if v == "relight")  # what `pcrelight trade` writes into [relight]


def relight_config(**values) -> RelightConfig:
    """RelightConfig as the CLI and TOML build it (defaults < preset < given values)."""
    return resolve(RelightConfig, None, "relight", values)


def test_presets_set_their_values_and_pass_check():
    assert set(PRESETS) == {"fast", "balanced", "exact"}
    for name, vals in PRESETS.items():
        cfg = relight_config(preset=name)
        assert set(vals) == set(KNOBS)
        for k, v in vals.items():
            assert getattr(cfg, k) == v, (name, k)
        # fields a preset does not name keep their defaults
        base = RelightConfig()
        for f in dataclasses.fields(RelightConfig):
            if f.name not in vals and f.name != "preset":
                assert getattr(cfg, f.name) == getattr(base, f.name)


def test_presets_are_ordered_by_cost():
    """fast → balanced → exact: the measured seconds (configs/presets/trade.json, written with the files) never
    fall."""
    import json

    rep = json.loads((ROOT / "configs" / "presets" / "trade.json").read_text())["presets"]

    def cost(name):
        return sum(d["seconds"] for d in rep[name]["pairs"].values())

    assert cost("fast") <= cost("balanced") <= cost("exact")


def test_no_preset_keeps_defaults():
    assert dataclasses.asdict(relight_config(preset="")) == dataclasses.asdict(RelightConfig())


def test_explicit_option_overrides_preset():
    cfg = relight_config(preset="fast", microbuffer=32, method="classic")
    assert cfg.microbuffer == 32 and cfg.method == "classic"
    assert cfg.stop_multiple == PRESETS["fast"]["stop_multiple"]
    # an explicit value equal to the dataclass default still wins over the preset (every option a preset sets
    # to something other than the default)
    default = RelightConfig()
    differs = [(name, k) for name, p in PRESETS.items() for k, v in p.items() if getattr(default, k) != v]
    assert differs
    for name, k in differs:
        assert getattr(relight_config(preset=name, **{k: getattr(default, k)}), k) == getattr(default, k), (name, k)


def test_unknown_preset_is_config_error():
    with pytest.raises(ConfigError, match="--preset"):
        relight_config(preset="turbo")


def _capture_cli(monkeypatch, args):
    import cli
    import pipeline.relight.relight as rl

    seen = {}

    def fake_run(bsh, out, cfg, **kw):
        seen["cfg"] = cfg
        return {}

    monkeypatch.setattr(rl, "run_relight", fake_run)
    res = CliRunner().invoke(cli.main, ["relight", *args])
    return res, seen.get("cfg")


def test_cli_preset_and_override(monkeypatch, tmp_path):
    res, cfg = _capture_cli(monkeypatch, ["--preset", "exact", "--bsh", "b.npz", "--out", str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    for k, v in PRESETS["exact"].items():
        assert getattr(cfg, k) == v
    res, cfg = _capture_cli(monkeypatch, ["--preset", "exact", "--microbuffer", "16", "--bsh", "b.npz",
                                          "--out", str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    assert cfg.microbuffer == 16 and cfg.stop_multiple == PRESETS["exact"]["stop_multiple"]
    # TOML: preset and an explicit key in [relight]; the command line wins over both
    toml = tmp_path / "c.toml"
    toml.write_text('[relight]\npreset = "fast"\nmethod = "classic"\n')
    res, cfg = _capture_cli(monkeypatch, ["--config", str(toml), "--stop-multiple", "3", "--bsh", "b.npz",
                                          "--out", str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    assert cfg.preset == "fast" and cfg.method == "classic" and cfg.stop_multiple == 3.0
    assert cfg.microbuffer == PRESETS["fast"]["microbuffer"]


def test_cli_unknown_preset_one_line(monkeypatch, tmp_path):
    res, cfg = _capture_cli(monkeypatch, ["--preset", "turbo", "--bsh", "b.npz", "--out", str(tmp_path / "o")])
    assert cfg is None
    assert res.exit_code == 2
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("pcrelight: --preset") and "turbo" in lines[0]
