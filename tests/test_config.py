"""Stage options: TOML overlays, CLI precedence, unknown keys and out-of-range values."""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest

from pipeline.config import StageConfig, resolve
from pipeline.errors import ConfigError, InputError


@dataclass
class Demo(StageConfig):
    size: int = field(default=64, metadata={"help": "face size [pixels]"})
    tc: float = field(default=0.01, metadata={"help": "threshold"})
    method: str = field(default="a", metadata={"choices": ("a", "b")})
    albedo: tuple[float, ...] = (0.8, 0.8, 0.8)
    prune: bool = True

    def check(self):
        self._require(self.size >= 1, "size", "must be ≥ 1")
        self._require(self.method in ("a", "b"), "method", "must be a or b")


def test_defaults_file_then_cli(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text('seed = 7\n[demo]\nsize = 32\ntc = 0.5\nalbedo = [0.1, 0.2, 0.3]\n[other]\nfoo = 1\n')
    c = resolve(Demo, f, "demo", {"size": 16, "tc": None})
    assert (c.seed, c.size, c.tc, c.albedo, c.prune) == (7, 16, 0.5, (0.1, 0.2, 0.3), True)
    c = resolve(Demo, None, "demo", {"albedo": "1,0.5,0.25", "prune": False})
    assert c.albedo == (1.0, 0.5, 0.25) and c.prune is False


def test_unknown_key_is_named(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text("[demo]\nsizee = 3\n")
    with pytest.raises(ConfigError, match="unknown key 'sizee' in \\[demo\\]"):
        resolve(Demo, f, "demo", {})


def test_out_of_range_and_bad_type(tmp_path):
    with pytest.raises(ConfigError, match="--size must be ≥ 1, got 0"):
        resolve(Demo, None, "demo", {"size": 0})
    f = tmp_path / "c.toml"
    f.write_text("[demo]\nsize = 'big'\n")
    with pytest.raises(ConfigError, match="'size' must be int"):
        resolve(Demo, f, "demo", {})
    f.write_text("[demo\nsize=1")
    with pytest.raises(InputError, match="not valid TOML"):
        resolve(Demo, f, "demo", {})
    with pytest.raises(InputError, match="no such file"):
        resolve(Demo, tmp_path / "missing.toml", "demo", {})
