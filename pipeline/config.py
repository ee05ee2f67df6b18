"""Stage options: one dataclass per stage, a ``check()``, presets, TOML overlays, unknown keys rejected.

Each stage module defines ``@dataclass class XxxConfig(StageConfig)`` whose fields carry
``metadata={"help": "... [units]", "choices": (...)}``. The CLI builds one ``--field-name``
option per field from that metadata (see :func:`describe`; ``cli.stage`` makes the options), so help,
units, defaults and choices are written once (:meth:`StageConfig.check_choices` enforces the choices
for TOML values too). Precedence (:func:`resolve`): dataclass defaults < preset
(:meth:`StageConfig.presets`, chosen by a ``preset`` field or argument) < TOML file (its top-level
``seed``, then the stage's ``[verb]`` table) < command-line options.

Seeds: a stage with one random stream seeds it with ``seed`` itself; a stage that needs several
derives each with :func:`sub_seed` (``numpy.random.SeedSequence`` of ``[seed, *tags]``; make-scene's
``default_rng([seed, 9])`` is this rule). Exception, kept so that its outputs and recorded bounds stay
as they are: patchmatch hashes ``seed·1000003 + face`` and ``+ 7919·level`` (docs/ARCHITECTURE.md).
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .errors import ConfigError, InputError


@dataclass
class StageConfig:
    """Base of every stage's options. ``seed`` makes a stage deterministic."""

    seed: int = field(default=0, metadata={"help": "random seed; the same seed gives byte-identical outputs"})

    def check(self) -> None:
        """Raise :class:`ConfigError` naming the option when a value is out of range."""

    @classmethod
    def presets(cls) -> Mapping[str, Mapping[str, Any]]:
        """Named sets of option values (``--preset NAME``); none by default."""
        return {}

    def check_choices(self) -> None:
        """Raise :class:`ConfigError` for a field whose value is not one of its metadata ``choices``."""
        for f in dataclasses.fields(self):
            choices = f.metadata.get("choices")
            if choices is not None and getattr(self, f.name) not in choices:
                self._require(False, f.name, "must be one of " + ", ".join(str(c) for c in choices if c != ""))

    # -- helpers for subclasses' check() ---------------------------------------------------
    def _require(self, ok: bool, name: str, rule: str) -> None:
        if not ok:
            value = getattr(self, name)
            err = ConfigError(f"--{name.replace('_', '-')} {rule}, got {value!r}")
            err.field, err.rule, err.value = name, rule, value  # resolve() names the TOML file and key
            raise err

    def check_physical(self) -> None:
        """The rules every stage shares (:data:`PHYSICAL`): every number finite, seeds ≥ 0, colours
        (albedo) in [0, 1], roughness and metallic in [0, 1], fields of view in (0, 180) degrees, a
        non-zero up vector, positive Reinhard keys, non-negative radiances. Called by :func:`resolve`
        after the stage's own :meth:`check`."""
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if v is None:
                continue
            if not all(math.isfinite(x) for x in _numbers(v)):
                self._require(False, f.name, "must be finite (no NaN or Inf)")
            rule = PHYSICAL.get(f.name)
            if rule is not None and not rule[0](v):
                self._require(False, f.name, rule[1])

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def field_names(cls) -> list[str]:
        return [f.name for f in dataclasses.fields(cls)]


def _numbers(v: Any) -> list[float]:
    """Every int/float in a value (nested tuples/lists included; bools and strings skipped)."""
    if isinstance(v, bool) or isinstance(v, str):
        return []
    if isinstance(v, (int, float, np.integer, np.floating)):
        return [float(v)]
    if isinstance(v, (tuple, list)):
        return [x for e in v for x in _numbers(e)]
    return []


def _all_in(lo: float, hi: float) -> Any:
    return lambda v: all(lo <= x <= hi for x in _numbers(v))


# Field name → (rule, what the error says). Applied to every stage that has such a field (after its own
# check()), so a physically impossible value is refused the same way on the command line and in a TOML file.
PHYSICAL: dict[str, tuple[Any, str]] = {
    "seed": (lambda v: 0 <= int(v) < 2 ** 63, "must be an integer in [0, 2^63)"),
    "albedo": (_all_in(0.0, 1.0), "must be in [0, 1] per channel (a surface reflects at most the light it receives)"),
    "base_color": (_all_in(0.0, 1.0), "must be in [0, 1] per channel (a surface reflects at most the light it receives)"),
    "roughness": (_all_in(0.0, 1.0), "must be in [0, 1]"),
    "metallic": (_all_in(0.0, 1.0), "must be in [0, 1]"),
    "fov": (lambda v: all(0 < x < 180 for x in _numbers(v)), "must be in (0, 180) degrees"),
    "photo_fov": (lambda v: all(x == 0 or 0 < x < 180 for x in _numbers(v)), "must be 0 (unknown) or in (0, 180) degrees"),
    "up": (lambda v: len(_numbers(v)) != 3 or any(x != 0 for x in _numbers(v)), "must be a non-zero vector"),
    "key": (lambda v: all(x > 0 for x in _numbers(v)), "must be > 0"),
    "sky_radiance": (_all_in(0.0, math.inf), "must be ≥ 0"),
    "sun_radiance": (_all_in(0.0, math.inf), "must be ≥ 0"),
    "lamp_radiance": (_all_in(0.0, math.inf), "must be ≥ 0"),
}


def _coerce(cls: type, name: str, value: Any, where: str) -> Any:
    """Convert a TOML/CLI value to the field's annotated type, or raise ConfigError."""
    hints = typing.get_type_hints(cls)
    tp = hints[name]
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    try:
        if tp is bool:
            if isinstance(value, str):
                if value.lower() in ("1", "true", "yes", "on"):
                    return True
                if value.lower() in ("0", "false", "no", "off"):
                    return False
                raise ValueError(value)
            return bool(value)
        if tp in (int, float, str):
            if tp is int and isinstance(value, float) and not value.is_integer():
                raise ValueError(value)
            return tp(value)
        if origin in (tuple, list):
            inner = args[0] if args else float
            if inner is Ellipsis or inner is typing.Any:
                inner = float
            if isinstance(value, str):
                if typing.get_origin(inner) in (tuple, list):  # "x,y,z;x,y,z" → [[x,y,z],[x,y,z]]
                    value = [[w for w in part.split(",") if w.strip()] for part in value.split(";") if part.strip()]
                else:
                    value = [v for v in value.replace(";", ",").split(",") if v.strip()]
            if typing.get_origin(inner) in (tuple, list):  # list of vectors, e.g. viewpoints
                sub = typing.get_args(inner)[0]
                out = [tuple(sub(x) for x in v) for v in value]
            else:
                out = [inner(v) for v in value]
            return tuple(out) if origin is tuple else out
        if origin is typing.Union or str(origin) == "types.UnionType":  # Optional[X]
            if value is None or value == "":
                return None
            for a in args:
                if a is type(None):
                    continue
                return a(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: '{name}' must be {getattr(tp, '__name__', str(tp))}, got {value!r}") from None
    return value


def resolve(cls: type[StageConfig], toml_path: str | os.PathLike | None, section: str,
            overrides: Mapping[str, Any], preset: str | None = None) -> StageConfig:
    """Build a checked config: defaults, then the preset, then ``[section]`` of the TOML file, then CLI
    overrides.

    The TOML file may hold several sections (one per stage verb, e.g. ``[build-bsh]``) and a
    top-level ``seed``; keys of this stage's section that are not fields are an error naming the key.
    Overrides whose value is ``None`` (option not given) are ignored. The preset is ``preset`` if given,
    else the resolved value of a ``preset`` field (empty: none); its values (:meth:`StageConfig.presets`)
    fill only the fields the TOML file and the overrides leave unset.
    """
    values: dict[str, Any] = {}
    names = set(cls.field_names())
    from_file: dict[str, str] = {}  # field → where in the TOML file it was set ("[section] key")
    if toml_path is not None:
        data = load_toml(toml_path)
        check_file(data, toml_path, section)
        if "seed" in data and not isinstance(data["seed"], dict):
            values["seed"] = _coerce(cls, "seed", data["seed"], f"{toml_path} (top level)")
            from_file["seed"] = "seed (top level)"
        sec = data.get(section, {})
        if not isinstance(sec, dict):
            raise ConfigError(f"{toml_path}: [{section}] must be a table")
        for k, v in sec.items():
            key = k.replace("-", "_")
            if key not in names:
                raise ConfigError(f"{toml_path}: unknown key '{k}' in [{section}]"
                                  f" (known: {', '.join(sorted(names))})")
            values[key] = _coerce(cls, key, v, f"{toml_path} [{section}]")
            from_file[key] = f"[{section}] {k}"
    for k, v in overrides.items():
        if v is None:
            continue
        if k not in names:
            raise ConfigError(f"unknown option '{k}' for {section}")
        values[k] = _coerce(cls, k, v, f"--{k.replace('_', '-')}")
        from_file.pop(k, None)
    if preset is None:
        preset = values.get("preset", "") if "preset" in names else ""
    if preset:
        table = cls.presets()
        if preset not in table:
            raise ConfigError(f"--preset must be one of {', '.join(table)}, got {preset!r}")
        base = {k.replace("-", "_"): v for k, v in table[preset].items()}
        bad = sorted(set(base) - names)
        if bad:
            raise ConfigError(f"preset {preset!r}: unknown key '{bad[0]}' (known: {', '.join(sorted(names))})")
        values = {**{k: _coerce(cls, k, v, f"preset {preset!r}") for k, v in base.items()}, **values}
    cfg = cls(**values)
    try:
        cfg.check_physical()  # first: "must be finite" says more about a NaN than a stage's range does
        cfg.check()
    except ConfigError as e:  # a value from the TOML file: name the file and the key
        name = getattr(e, "field", None)
        if toml_path is not None and name in from_file:
            raise ConfigError(f"{toml_path}: {from_file[name]} {e.rule}, got {e.value!r}") from None
        raise
    return cfg


# The speed/accuracy presets (fast, balanced, exact): one TOML file each, written by `pcrelight trade` from
# its measured front (pipeline/measure/trade.py: the rule; configs/presets/trade.csv: the rows they were picked from).
PRESET_DIR = Path(__file__).resolve().parent.parent / "configs" / "presets"
PRESET_NAMES = ("fast", "balanced", "exact")
# the preset rule (pcrelight trade picks them by it; the planner bounds a run's error by it): exact = the lowest
# error, balanced = the cheapest row within BALANCED_FACTOR × exact's error, fast = within FAST_FACTOR ×
BALANCED_FACTOR, FAST_FACTOR = 1.15, 2.0


def preset_tables(section: str, folder: str | os.PathLike | None = None) -> dict[str, dict[str, Any]]:
    """``{name: the [section] table of <folder>/<name>.toml}`` for the presets (:data:`PRESET_NAMES`) of
    ``folder`` (default :data:`PRESET_DIR`) that have that table: the one place presets are read from."""
    d = Path(folder) if folder is not None else PRESET_DIR
    out = {}
    for name in PRESET_NAMES:
        f = d / f"{name}.toml"
        if f.exists():
            t = load_toml(f).get(section)
            if isinstance(t, dict):
                out[name] = t
    return out


def config_class(verb: str) -> type[StageConfig]:
    """The options dataclass of ``verb`` (:data:`pipeline.verbs.VERBS`' ``config``, imported now)."""
    import importlib

    from .verbs import VERB

    mod, _, name = VERB[verb].config.partition(":")
    return getattr(importlib.import_module(mod), name)


def check_file(data: Mapping[str, Any], path: str | os.PathLike, section: str | None = None) -> None:
    """The one check of a pcrelight config file, the same for every verb and ``run``: only ``seed`` stands above
    the tables, every table is a verb's (:data:`pipeline.verbs.VERB`) and every key of every table is a field of
    that verb's options. Raises :class:`ConfigError` naming the file and the table or key. ``section``: the table
    a caller reads; when it is no verb's (a library's own TOML, a test's) only the top level is checked."""
    from .verbs import TABLES, VERB

    tables = {name for name, verb in VERB.items() if verb.table}     # (VERB: also a test's own verb)
    for k, v in data.items():
        if isinstance(v, dict):
            if section is not None and section not in tables:
                continue
            if k not in tables:
                raise ConfigError(f"{path}: unknown table [{k}] (known: {', '.join(sorted(TABLES))})")
            names = set(config_class(k).field_names())
            for key in v:
                if key.replace("-", "_") not in names:
                    raise ConfigError(f"{path}: unknown key '{key}' in [{k}] (known: {', '.join(sorted(names))})")
        elif k != "seed":
            raise ConfigError(f"{path}: key '{k}' belongs to no table (only 'seed' may stand above the "
                              f"tables; put it under its verb's [table])")


def sub_seed(seed: int, *tags: int) -> np.random.SeedSequence:
    """The one rule for derived random streams: ``SeedSequence([seed, *tags])`` (integer tags ≥ 0,
    e.g. a face or level index). ``np.random.default_rng(sub_seed(s, 9))`` is the stream of
    ``default_rng([s, 9])`` (make-scene's), and ``sub_seed(s)`` that of ``default_rng(s)``."""
    if int(seed) < 0 or any(int(t) < 0 for t in tags):
        raise ConfigError(f"--seed must be ≥ 0, got {seed}")
    return np.random.SeedSequence([int(seed), *(int(t) for t in tags)] if tags else int(seed))


def sub_seed_u64(seed: int, *tags: int) -> int:
    """:func:`sub_seed` as one unsigned 64-bit integer, for kernels that hash their own counters."""
    return int(sub_seed(seed, *tags).generate_state(1, np.uint64)[0])


class TomlFile(os.PathLike):
    """A TOML file read once: :func:`load_toml` (and so :func:`resolve`) returns the parsed tables instead of
    reading the file again; ``str()`` and ``os.fspath()`` are its path, so messages still name the file.
    :func:`pipeline.run.runner.plan` parses a run's config this way (one read for every stage's options)."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = os.fspath(path)
        self.data = load_toml(self.path)

    def __fspath__(self) -> str:
        return self.path

    def __str__(self) -> str:
        return self.path

    def __repr__(self) -> str:
        return f"TomlFile({self.path!r})"


def load_toml(path: str | os.PathLike) -> dict[str, Any]:
    """Read a TOML file (a :class:`TomlFile`: its tables, read once); a missing or malformed file is an InputError
    naming it."""
    if isinstance(path, TomlFile):
        return path.data
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise InputError(path, "no such file") from None
    except tomllib.TOMLDecodeError as e:
        raise InputError(path, f"not valid TOML ({e})") from None
    except UnicodeDecodeError as e:  # (found by atheris: tomllib decodes the bytes first)
        raise InputError(path, f"not valid TOML (not UTF-8 text: byte {e.object[e.start]:#04x} at {e.start})") from None
    except IsADirectoryError:
        raise InputError(path, "is a directory, expected a TOML file") from None
    except OSError as e:
        raise InputError(path, f"cannot read ({e.strerror or e})") from None


def describe(cls: type[StageConfig]) -> list[tuple[str, Any, str, tuple | None, type]]:
    """(name, default, help, choices, type) for every field, for building CLI options and docs."""
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        default = f.default if f.default is not dataclasses.MISSING else (
            f.default_factory() if f.default_factory is not dataclasses.MISSING else None)  # type: ignore[misc]
        out.append((f.name, default, f.metadata.get("help", ""), f.metadata.get("choices"), hints[f.name]))
    return out
