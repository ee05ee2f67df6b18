"""trade: what each second buys on the user's own scene (issue 27), and the presets chosen from it.

``pcrelight trade --scene DIR`` sweeps the knobs that cost time across the pipeline (:func:`grid`): the
expansion's (cube-face size, views, PatchMatch iterations and patch size, the Poisson solver), build-bsh's
pruning threshold t_c and relight's (every gatherer of :data:`pipeline.gather.GATHERERS`, the micro-buffer
side, the stop multiple, Ω_tr, adaptive shading's ε, bounces, the lobe buffer, the object's surfels), one
knob at a time around the base configuration (the defaults overlaid by ``--config``), plus a few combined
points. Each point runs the pipeline as ``pcrelight run`` does (:func:`pipeline.run.runner.run_pipeline`, the
planner included) up to build-bsh, then relights the scene's object from each view with each reference
material, and compares the image with the path-traced references by
:func:`pipeline.metrics.compare_to_reference` on 4×4 block means: ``err`` = the noise-corrected block RMS
against ``truth/full_<view>_<material>.exr`` (the object in the room: what a camera sees; the reference's own
noise removed), ``gather_*`` the same against ``truth/gather_*`` (the object absent from its own light:
what PBGI computes). Time: ``seconds`` = the wall time of the expansion stages + build-bsh + relight of that
row (what one ``pcrelight run`` of that configuration costs on this machine); the parts are in their columns.
``cpu_s`` (and its parts ``*_cpu_s``) = the CPU seconds of this process over the same work (every thread:
numba's, llvmpipe's), the figure to compare on a shared machine; ``load1`` = the 1-minute load average when the
row started.

Rows are keyed by their configuration, view and material: a rerun skips the rows already in ``trade.csv``
(rewritten atomically after every row, so an interrupted sweep resumes where it stopped); ``budget_min``
stops the sweep cleanly between rows once that many minutes have passed (after at least one row, so that
every rerun makes progress).

**The preset rule** (:func:`pick_presets`). A configuration is a candidate when it was measured on every
(view, material) pair of the CSV. ``exact`` = the candidate whose largest ratio err / (the pair's lowest err)
over the pairs is the smallest; ``balanced`` = the cheapest candidate (mean ``seconds`` over the pairs) whose
err is within 1.15× exact's on every pair; ``fast`` = the cheapest within 2×. Ties go to the earlier row.
The front (:func:`pareto`) is per pair: the rows no other row of the pair beats on both seconds and err.

Outputs in ``--out``: ``trade.csv``, ``trade.png`` (err vs seconds, log axes, every point labelled, the front
and the presets marked), ``trade.json`` (the presets with their err, seconds and distance from the front),
``trade.md`` (the same as tables, and each front) and
``fast.toml``, ``balanced.toml``, ``exact.toml`` — the preset files ``configs/presets/`` ships
(:func:`pipeline.config.preset_tables` reads them; ``relight --preset NAME`` applies their ``[relight]``
table, the other tables are the expansion options the trade measured with, for a ``pcrelight run`` config).
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..config import BALANCED_FACTOR, FAST_FACTOR, PRESET_NAMES, StageConfig, load_toml, resolve
from ..errors import ConfigError, InputError
from ..runtime import check_interrupt, get_logger
from ..io.workspace import Workspace

log = get_logger("trade")

# The knobs the sweep writes into trade.csv (stage verb, field): every row holds their resolved values.
KNOBS: tuple[tuple[str, str], ...] = (
    ("render-cubemaps", "size"), ("render-cubemaps", "max_views"),
    ("patchmatch", "iterations"), ("patchmatch", "patch_size"), ("poisson", "solver"),
    ("build-bsh", "tc"),
    ("relight", "method"), ("relight", "microbuffer"), ("relight", "stop_multiple"), ("relight", "omega_tr"),
    ("relight", "adaptive"), ("relight", "bounces"), ("relight", "lobe_buffer"), ("relight", "surfels"),
)
EXPANSION = ("expose-match", "render-cubemaps", "patchmatch", "reproject", "poisson")
RESULT_FIELDS = ("view", "material", "seconds", "expansion_s", "bsh_s", "relight_s", "cpu_s", "expansion_cpu_s",
                 "bsh_cpu_s", "relight_cpu_s", "load1", "err", "rms_block",
                 "mean_ratio_block", "ref_noise_block", "gather_err", "gather_mean_ratio_block", "n_blocks",
                 "nodes_per_pixel", "bsh_nodes", "renderer")
CPU_FIELDS = ("cpu_s", "expansion_cpu_s", "bsh_cpu_s", "relight_cpu_s", "load1")   # absent from older CSVs


@dataclass
class TradeConfig(StageConfig):
    """Options of ``pcrelight trade`` (units in brackets)."""

    views: str = field(default="view1", metadata={"help": "comma-separated scene.json views to relight from"})
    materials: str = field(default="lambert,ggx0.25", metadata={
        "help": "comma-separated reference materials (scene.json materials; truth/full_<view>_<material>.exr)"})
    grid: str = field(default="pipeline", metadata={
        "help": "pipeline: relight and build-bsh knobs on the base expansion, then expansion points (~35 rows a "
                "view × material); relight: the relight and build-bsh knobs only; quick: 4 points (a first look, CI)",
        "choices": ("pipeline", "relight", "quick")})
    budget_min: float = field(default=0.0, metadata={
        "help": "stop cleanly between rows after this many minutes (a rerun resumes) [min]; 0 = no bound"})
    repeat: int = field(default=1, metadata={"help": "relight runs per row; seconds = the fastest (the image must "
                                                      "be identical each time)"})

    def check(self) -> None:
        self.check_choices()
        self._require(self.budget_min >= 0, "budget_min", "must be ≥ 0 (0 = no bound)")
        self._require(1 <= self.repeat <= 10, "repeat", "must be in [1, 10]")
        self._require(bool(_names(self.views)), "views", "must name at least one view")
        self._require(bool(_names(self.materials)), "materials", "must name at least one material")


def _names(s: str) -> list[str]:
    return [x.strip() for x in s.split(",") if x.strip()]


# --------------------------------------------------------------------------- the grid
@dataclass(frozen=True)
class Point:
    """One configuration: a label and its overrides per stage verb (of the base configuration)."""

    label: str
    over: tuple[tuple[str, tuple[tuple[str, Any], ...]], ...] = ()

    @staticmethod
    def of(label: str, **stages: dict[str, Any]) -> "Point":
        return Point(label, tuple(sorted((v.replace("_", "-"), tuple(sorted(d.items()))) for v, d in stages.items())))

    def stage(self, verb: str) -> dict[str, Any]:
        return dict(next((d for v, d in self.over if v == verb), ()))


def grid(kind: str, gatherers: list[str]) -> list[Point]:
    """The sweep's points in the order they run: the base, relight's and build-bsh's knobs on the base
    expansion (cheap: one relight each), then the expansion's (each a new expansion), then combined points."""
    P = Point.of
    pts = [P("base")]
    if kind == "quick":
        return pts + [P("m=8", relight={"microbuffer": 8}), P("stop=8", relight={"stop_multiple": 8.0}),
                      P("cube/2", render_cubemaps={"size": "half"})]
    pts += [P(f"method={g}", relight={"method": g}) for g in gatherers]
    pts += [P(f"m={m}", relight={"microbuffer": m}) for m in (8, 16, 24, 32)]
    pts += [P(f"stop={s:g}", relight={"stop_multiple": float(s)}) for s in (2, 8)]
    pts += [P(f"omega_tr={w:g}", relight={"omega_tr": float(w)}) for w in (8, 128)]
    pts += [P(f"adaptive={a:g}", relight={"adaptive": float(a)}) for a in (0, 1)]
    pts += [P(f"bounces={b}", relight={"bounces": b}) for b in (0, 1)]
    pts += [P(f"lobe_buffer={n}", relight={"lobe_buffer": n}) for n in (0, 32)]
    pts += [P("surfels=off", relight={"surfels": -1})]
    pts += [P(f"tc={t:g}", build_bsh={"tc": float(t)}) for t in (0.02, 0.2)]
    pts += [P("m=16,stop=8", relight={"microbuffer": 16, "stop_multiple": 8.0}),
            P("m=32,stop=8", relight={"microbuffer": 32, "stop_multiple": 8.0}),
            P("m=16,adaptive=1", relight={"microbuffer": 16, "adaptive": 1.0})]
    if kind == "relight":
        return pts
    # the expansion's knobs, the cheapest to run first (a later stage's knob reuses the earlier stages' outputs)
    pts += [P("poisson=amg", poisson={"solver": "amg"}), P("pm_iterations=2", patchmatch={"iterations": 2}),
            P("patch=5", patchmatch={"patch_size": 5}), P("cube/2", render_cubemaps={"size": "half"}),
            P("cube/2,m=16,stop=8", render_cubemaps={"size": "half"}, relight={"microbuffer": 16, "stop_multiple": 8.0}),
            P("views=1", render_cubemaps={"max_views": 1}), P("views=3", render_cubemaps={"max_views": 3}),
            P("cube*2", render_cubemaps={"size": "double"})]
    return pts


# --------------------------------------------------------------------------- configurations
class Base:
    """The base configuration: each stage's resolved options (defaults < ``config_toml``'s table)."""

    def __init__(self, config_toml: str | Path | None, seed: int):
        from ..run.stages import STAGE

        self.toml = config_toml
        self.data = load_toml(config_toml) if config_toml else {}
        self.seed = seed
        self.classes = {v: STAGE[v].config_class() for v in (*EXPANSION, "build-bsh", "relight")}

    def tables(self, p: Point) -> dict[str, dict[str, Any]]:
        """Each stage's table for point ``p``: the base file's, then the point's overrides ("half"/"double"
        cube sizes are relative to the base's)."""
        out: dict[str, dict[str, Any]] = {}
        for verb in self.classes:
            t = dict(self.data.get(verb, {}))
            for k, v in p.stage(verb).items():
                if verb == "render-cubemaps" and k == "size" and isinstance(v, str):
                    base = self.resolved(verb, {}).size
                    v = max(16, base // 2) if v == "half" else base * 2
                t[k] = v
            out[verb] = t
        return out

    def resolved(self, verb: str, table: dict[str, Any]) -> StageConfig:
        return resolve(self.classes[verb], None, verb, {"seed": self.seed, **{k.replace("-", "_"): v for k, v in
                                                                              {**self.data.get(verb, {}), **table}.items()}})

    def knobs(self, tables: dict[str, dict[str, Any]]) -> dict[str, Any]:
        """The resolved value of every :data:`KNOBS` column."""
        cfgs = {v: self.resolved(v, tables[v]) for v in {v for v, _ in KNOBS}}
        return {f"{v}.{k}": getattr(cfgs[v], k) for v, k in KNOBS}


def _digest(obj: Any) -> str:
    return hashlib.sha1(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:10]


def expansion_key(tables: dict[str, dict[str, Any]]) -> str:
    return _digest({v: tables[v] for v in EXPANSION})


def bsh_key(tables: dict[str, dict[str, Any]]) -> str:
    return _digest({"exp": expansion_key(tables), "bsh": tables["build-bsh"]})


def row_key(knobs: dict[str, Any], view: str, material: str) -> str:
    """A row's identity in trade.csv: its knob values (as the CSV writes them), view and material."""
    return _digest({"knobs": {k: _fmt(v) for k, v in knobs.items()}, "view": view, "material": material})


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


# --------------------------------------------------------------------------- the scene
def material_overrides(scene: dict[str, Any], name: str) -> dict[str, Any]:
    """relight options that render the reference material ``name`` of scene.json's ``materials``
    (lambert: albedo; ggx: Mitsuba's roughconductor, F = 1, separable Smith masking)."""
    mats = scene.get("materials", {})
    if name not in mats:
        raise InputError("scene.json", f"no material '{name}' (have: {', '.join(mats) or 'none'})")
    m = mats[name]
    if m.get("type") == "lambert":
        a = float(m.get("albedo", 0.8))
        return {"brdf": "lambert", "albedo": (a, a, a)}
    if m.get("type") == "ggx":
        return {"brdf": "ggx", "albedo": (1.0, 1.0, 1.0), "metallic": 1.0, "roughness": float(m["roughness"]),
                "masking": "separable" if "separable" in str(m.get("masking", "separable")) else "height-correlated"}
    raise InputError("scene.json", f"material '{name}': type {m.get('type')!r} is neither lambert nor ggx")


def check_scene(scene_dir: Path, views: list[str], materials: list[str]) -> tuple[dict[str, Any], float]:
    """scene.json, and the exposure e that brings relit.exr (the LDR cloud's units) to scene radiance; every
    reference the sweep compares with must exist (one line naming the first missing file otherwise)."""
    from .. import io

    for f in ("scene.json", "cloud_ldr.ply"):
        if not (scene_dir / f).exists():
            raise InputError(scene_dir / f, "no such file (trade --scene needs a make-scene folder: scene.json, "
                                            "cloud_ldr.ply, photo.exr, object, truth/full_<view>_<material>.exr)")
    scene = io.read_json(scene_dir / "scene.json")
    for v in views:
        if v not in scene.get("views", {}):
            raise InputError(scene_dir / "scene.json", f"no view '{v}' (have: {', '.join(scene.get('views', {}))})")
    for mat in materials:
        material_overrides(scene, mat)
        for v in views:
            for kind in ("full",):
                for suf in ("", "_var"):
                    f = scene_dir / "truth" / f"{kind}_{v}_{mat}{suf}.exr"
                    if not f.exists():
                        raise InputError(f, "no such file (the path-traced reference the trade compares with)")
    e = scene.get("exposure_e")
    if e is None and (scene_dir / "truth" / "truth.npz").exists():
        e = float(io.read_npz(scene_dir / "truth" / "truth.npz", "pcrelight.truth/1")["e"])
    if e is None or not (float(e) > 0):
        raise InputError(scene_dir / "scene.json", "no exposure_e (the LDR cloud's scale e of the scene radiance)")
    return scene, float(e)


def compare(scene_dir: Path, relit: np.ndarray, e: float, view: str, material: str) -> dict[str, Any]:
    """relit.exr (÷ e) against truth/full_* (``err`` …) and, when present, truth/gather_* (``gather_*``)."""
    from .. import io
    from ..metrics import compare_to_reference

    est = relit[..., :3].astype(np.float64) / e
    out: dict[str, Any] = {}
    for kind in ("full", "gather"):
        ref_f = scene_dir / "truth" / f"{kind}_{view}_{material}.exr"
        if not ref_f.exists():
            out.update(gather_err=float("nan"), gather_mean_ratio_block=float("nan"))
            continue
        ref = io.read_image(ref_f)
        var = io.read_image(ref_f.with_name(ref_f.stem + "_var.exr"))
        m = (relit[..., 3] > 0.5) & (ref[..., 3] > 0.5)
        r = compare_to_reference(est, ref[..., :3].astype(np.float64), m, var[..., :3].astype(np.float64), block=4)
        if kind == "full":
            out.update(err=r["rms_corrected_block"], rms_block=r["rms_block"], mean_ratio_block=r["mean_ratio_block"],
                       ref_noise_block=r["ref_noise_block"], n_blocks=r["n_blocks"])
        else:
            out.update(gather_err=r["rms_corrected_block"], gather_mean_ratio_block=r["mean_ratio_block"])
    return out


# --------------------------------------------------------------------------- the CSV
def columns() -> list[str]:
    return ["key", "point", *(f"{v}.{k}" for v, k in KNOBS), *RESULT_FIELDS]


def read_rows(path: Path) -> list[dict[str, str]]:
    """trade.csv's rows (none if absent). A CSV written with other columns is an error naming the file."""
    if not path.exists():
        return []
    with open(path, newline="") as f:
        r = csv.DictReader(f)
        if r.fieldnames and list(r.fieldnames) not in (columns(), [c for c in columns() if c not in CPU_FIELDS]):
            raise InputError(path, "columns differ from this version's trade.csv (move it aside to start afresh)")
        return [{**{c: "" for c in CPU_FIELDS}, **row} for row in r]   # a CSV from before the CPU columns: blank


def write_rows(path: Path, rows: list[dict[str, Any]]) -> None:
    """All rows, atomically (temp + rename: a kill leaves the previous complete file)."""
    from .. import io

    with io.atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=columns(), extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})


# --------------------------------------------------------------------------- the rule
Row = dict[str, Any]


def config_of(r: Row) -> tuple[str, ...]:
    """A row's configuration (its knob values), independent of view and material."""
    return tuple(str(r[f"{v}.{k}"]) for v, k in KNOBS)


def pareto(rows: list[Row]) -> list[Row]:
    """The rows no other row beats on both ``seconds`` and ``err`` (equal on both: the first kept), by seconds."""
    good = [r for r in rows if math.isfinite(float(r["err"]))]
    front = []
    for i, r in enumerate(good):
        s, e = float(r["seconds"]), float(r["err"])
        dominated = any((float(o["seconds"]) <= s and float(o["err"]) <= e)
                        and (float(o["seconds"]) < s or float(o["err"]) < e or j < i) for j, o in enumerate(good) if j != i)
        if not dominated:
            front.append(r)
    return sorted(front, key=lambda r: float(r["seconds"]))


def pairs_of(rows: list[Row]) -> list[tuple[str, str]]:
    return sorted({(r["view"], r["material"]) for r in rows})


def pick_presets(rows: list[Row], balanced: float = BALANCED_FACTOR, fast: float = FAST_FACTOR) -> dict[str, Row]:
    """The documented rule (module docstring): name → a representative row (the configuration's first row).
    Raises ConfigError when no configuration was measured on every pair."""
    pairs = pairs_of(rows)
    err: dict[tuple, dict[tuple[str, str], float]] = {}
    secs: dict[tuple, list[float]] = {}
    first: dict[tuple, Row] = {}
    for r in rows:
        c = config_of(r)
        e = float(r["err"])
        if not math.isfinite(e):
            continue
        err.setdefault(c, {})[(r["view"], r["material"])] = e
        secs.setdefault(c, []).append(float(r["seconds"]))
        first.setdefault(c, r)
    cand = [c for c in first if set(err[c]) >= set(pairs)]          # in first-row order
    if not cand:
        raise ConfigError("trade: no configuration was measured on every view × material; nothing to pick from")
    best = {p: min(err[c][p] for c in cand) for p in pairs}

    def worst_ratio(c: tuple) -> float:
        return max(err[c][p] / best[p] if best[p] > 0 else (1.0 if err[c][p] == 0 else math.inf) for p in pairs)

    cost = {c: float(np.mean(secs[c])) for c in cand}
    exact = min(cand, key=worst_ratio)

    def cheapest_within(f: float) -> tuple:
        return min((c for c in cand if all(err[c][p] <= f * err[exact][p] for p in pairs)), key=lambda c: cost[c])

    return {"fast": first[cheapest_within(fast)], "balanced": first[cheapest_within(balanced)], "exact": first[exact]}


def preset_report(rows: list[Row], picks: dict[str, Row]) -> dict[str, Any]:
    """Per preset and pair: its err and seconds, and its distance from the pair's front: ``err_over_front`` =
    err ÷ the lowest err of a front point no slower − 1, ``time_over_front`` = seconds ÷ the least seconds of a
    front point no worse − 1 (both 0 on the front)."""
    out: dict[str, Any] = {}
    for name, pick in picks.items():
        c = config_of(pick)
        per = {}
        for view, mat in pairs_of(rows):
            g = [r for r in rows if (r["view"], r["material"]) == (view, mat)]
            mine = next(r for r in g if config_of(r) == c)
            f = pareto(g)
            s, e = float(mine["seconds"]), float(mine["err"])
            e_front = min((float(r["err"]) for r in f if float(r["seconds"]) <= s), default=e)
            s_front = min((float(r["seconds"]) for r in f if float(r["err"]) <= e), default=s)
            per[f"{view}/{mat}"] = {"err": e, "seconds": s, "cpu_s": _num(mine.get("cpu_s")),
                                    "load1": _num(mine.get("load1")), "on_front": any(config_of(r) == c for r in f),
                                    "err_over_front": e / e_front - 1 if e_front > 0 else 0.0,
                                    "time_over_front": s / s_front - 1 if s_front > 0 else 0.0,
                                    "gather_err": float(mine["gather_err"])}
        out[name] = {"point": pick["point"], "knobs": {f"{v}.{k}": pick[f"{v}.{k}"] for v, k in KNOBS}, "pairs": per}
    return out


def preset_toml(name: str, pick: Row, report: dict[str, Any], source: str) -> str:
    """A preset file: one table per stage with the knobs' values of the picked row (TOML)."""
    lines = [f"# preset '{name}': written by `pcrelight trade` from {source} by the rule of pipeline/measure/trade.py",
             f"# (row '{pick['point']}'; fast = cheapest within {FAST_FACTOR:g}× exact's error, balanced = within "
             f"{BALANCED_FACTOR:g}×, exact = the lowest error over every view × material).",
             "# Measured: " + "; ".join(f"{p}: err {d['err']:.4f}, {d['seconds']:.1f} s"
                                          for p, d in report["pairs"].items()),
             "# `relight --preset NAME` applies [relight]; the other tables are the expansion options it was measured",
             "# with (copy them into a `pcrelight run` config).  Do not edit: rerun `pcrelight trade`."]
    for verb in dict.fromkeys(v for v, _ in KNOBS):
        lines += ["", f"[{verb}]"]
        for v, k in KNOBS:
            if v == verb:
                lines.append(f"{k} = {_toml_value(pick[f'{v}.{k}'])}")
    return "\n".join(lines) + "\n"


def format_markdown(rows: list[Row], report: dict[str, Any], complete: bool) -> str:
    """trade.md: the presets (error, seconds, distance from the front per view × material) and each front."""
    pairs = [f"{v}/{m}" for v, m in pairs_of(rows)]
    out = [f"# trade: {len(rows)} rows{'' if complete else ' (sweep incomplete: rerun to resume)'}", "",
           "| preset | point | " + " | ".join(f"{p} err · s · over the front (err / time)" for p in pairs) + " |",
           "|---|---|" + "---|" * len(pairs)]
    for name in PRESET_NAMES:
        d = report[name]
        cells = []
        for p in pairs:
            q = d["pairs"][p]
            cpu = q.get("cpu_s", math.nan)
            cells.append(f"{q['err']:.4f} · {q['seconds']:.1f} s" + (f" (CPU {cpu:.1f} s)" if math.isfinite(cpu) else "")
                         + " · " + ("on the front" if q["on_front"] else
                         f"+{100 * q['err_over_front']:.0f} % / +{100 * q['time_over_front']:.0f} %"))
        out.append(f"| {name} | {d['point']} | " + " | ".join(cells) + " |")
    for (view, mat) in pairs_of(rows):
        g = [r for r in rows if (r["view"], r["material"]) == (view, mat)]
        out += ["", f"Front {view}/{mat}: " + " → ".join(
            f"{r['point']} ({float(r['seconds']):.1f} s, {float(r['err']):.4f})" for r in pareto(g))]
    return "\n".join(out) + "\n"


def _num(v: Any) -> float:
    """A CSV cell as a float (NaN when blank: a row from before the CPU columns)."""
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def _toml_value(s: Any) -> str:
    s = str(s)
    try:
        int(s)
        return s
    except ValueError:
        pass
    try:
        x = float(s)
        return repr(x) if math.isfinite(x) else f'"{s}"'
    except ValueError:
        return json.dumps(s)


# --------------------------------------------------------------------------- the plot
ERR_FLOOR = 1e-4  # the plot's lowest err (a noise-corrected error can be 0: within the reference's noise)


def plot(rows: list[Row], picks: dict[str, Row] | None, path: Path) -> None:
    """err vs seconds per view × material (log axes), every point labelled, the front and presets marked; an
    err below :data:`ERR_FLOOR` is drawn at it."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    from .. import io

    keys = pairs_of(rows)
    fig, axes = plt.subplots(1, max(len(keys), 1), figsize=(7.5 * max(len(keys), 1), 6.5), squeeze=False)
    colour = {"expansion": "tab:red", "build-bsh": "tab:green", "relight": "tab:blue", "base": "k"}
    for ax, (view, mat) in zip(axes[0], keys):
        g = [r for r in rows if (r["view"], r["material"]) == (view, mat) and math.isfinite(float(r["err"]))]
        for r in g:
            kind = _kind(r["point"])
            ax.scatter(float(r["seconds"]), _y(r), c=colour[kind], s=22, zorder=3)
            ax.annotate(r["point"], (float(r["seconds"]), _y(r)), fontsize=6.5, xytext=(3, 2),
                        textcoords="offset points")
        f = pareto(g)
        ax.plot([float(r["seconds"]) for r in f], [_y(r) for r in f], "k-", lw=1.2, zorder=2,
                label="Pareto front")
        names: dict[tuple, list[str]] = {}
        for name, pick in (picks or {}).items():
            names.setdefault(config_of(pick), []).append(name)
        for c, ns in names.items():
            mine = [r for r in g if config_of(r) == c]
            if mine:
                ax.scatter(float(mine[0]["seconds"]), _y(mine[0]), marker="*", s=240, c="gold",
                           edgecolors="k", zorder=5)
                ax.annotate(" = ".join(ns), (float(mine[0]["seconds"]), _y(mine[0])), fontsize=9, weight="bold",
                            xytext=(-12, -15), textcoords="offset points")
        for kind, c in colour.items():
            ax.scatter([], [], c=c, s=22, label=f"{kind} knob" if kind != "base" else "base")
        ax.set_xscale("log")
        ax.set_yscale("log")
        fmt = FuncFormatter(lambda x, _: f"{x:.3g}")
        for axis in (ax.xaxis, ax.yaxis):
            axis.set_major_formatter(fmt)
            axis.set_minor_formatter(fmt)
        ax.tick_params(axis="both", which="both", labelsize=7)
        ax.tick_params(axis="x", which="both", labelrotation=45)
        ax.set_xlabel("wall time of the run: expansion + build-bsh + relight [s]")
        ax.set_ylabel("block RMS vs path-traced full_*, noise-corrected")
        ax.set_title(f"{view} / {mat}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    io.save_figure(path, fig)


def _y(r: Row) -> float:
    return max(float(r["err"]), ERR_FLOOR)


def _front_words(d: dict[str, Any]) -> str:
    if d["on_front"]:
        return "on the front"
    return f"+{100 * d['err_over_front']:.0f} % err, +{100 * d['time_over_front']:.0f} % time over the front"


def _kind(label: str) -> str:
    if label == "base":
        return "base"
    first = label.split(",")[0].split("=")[0].split("/")[0].split("*")[0]
    if first in ("cube", "views", "pm_iterations", "patch", "poisson"):
        return "expansion"
    return "build-bsh" if first == "tc" else "relight"


# --------------------------------------------------------------------------- the sweep
class Sweep:
    """Runs the points: expansions and BSHs cached in ``work`` (with their measured seconds), rows appended to
    ``csv_path`` as they complete."""

    def __init__(self, scene_dir: Path, work: Path, base: Base, cfg: TradeConfig):
        self.scene_dir, self.work, self.base, self.cfg = scene_dir, work, base, cfg
        self.cpu: dict[str, float] = {}   # the last row's CPU seconds: expansion, bsh, relight (NaN: not measured)

    def expansion(self, tables: dict[str, dict[str, Any]], root: Path | None = None) -> tuple[Path, dict[str, float], Path]:
        """(workspace, seconds per stage of the expansion and build-bsh (the base's build-bsh options), the cloud
        build-bsh reads) — once per expansion key, through :func:`pipeline.run.runner.run_pipeline` (the planner
        included, every stage forced so the seconds are measured). The stages before the first one whose options
        differ from an expansion already run are not run again: their outputs are linked from that workspace and
        their seconds taken from its record (deterministic stages: same options and seed, same outputs).
        ``root``: run every stage in that folder, sharing nothing (the warm-up)."""
        from .. import io
        from ..run.stages import STAGE
        from ..run.runner import run_pipeline

        ws = root if root is not None else self.work / f"exp_{expansion_key(tables)}"
        done = ws / "trade_expansion.json"
        if done.exists() and root is None:
            d = io.read_json(done)
            c = d.get("cpu", {})
            self.cpu.update(expansion=sum(float(c.get(v, float("nan"))) for v in EXPANSION),
                            bsh=float(c.get("build-bsh", float("nan"))))
            return ws, d["seconds"], Path(d["bsh_input"])
        order = (*EXPANSION, "build-bsh")
        mine = {v: tables[v] for v in EXPANSION}
        mine["build-bsh"] = dict(self.base.data.get("build-bsh", {}))
        src, shared = None, 0
        if root is None:
            for rec in sorted(self.work.glob("exp_*/trade_expansion.json")):
                other = io.read_json(rec).get("tables", {})
                k = 0
                while k < len(order) - 1 and _same(other.get(order[k]), mine[order[k]]):
                    k += 1
                if k > shared:
                    src, shared = rec.parent, k
        ws.mkdir(parents=True, exist_ok=True)
        secs: dict[str, float] = {}
        cpu: dict[str, float] = {}
        if src is not None:
            src_rec = io.read_json(src / "trade_expansion.json")
            src_secs, src_cpu = src_rec["seconds"], src_rec.get("cpu", {})
            a, b = Workspace(self.scene_dir, src), Workspace(self.scene_dir, ws)
            for v in order[:shared]:
                for f_src, f_dst in zip(STAGE[v].outputs(a), STAGE[v].outputs(b)):
                    _link(f_src, f_dst)
                secs[v] = float(src_secs.get(v, 0.0))
                cpu[v] = float(src_cpu.get(v, float("nan")))
            log.info("expansion %s: %s shared with %s (outputs linked, seconds from its record)", ws.name,
                     ", ".join(order[:shared]), src.name)
        toml = ws / "config.toml"
        body = [f"seed = {self.base.seed}", "", "[run]", f"inputs = {json.dumps(str(self.scene_dir))}",
                f"workspace = {json.dumps(str(ws))}", "previews = false",
                f"view = {json.dumps(_names(self.cfg.views)[0])}"]
        for verb in order:
            body += ["", f"[{verb}]"] + [f"{k} = {_toml_literal(v)}" for k, v in mine[verb].items()]
        with io.atomic_path(toml) as tmp:
            tmp.write_text("\n".join(body) + "\n")
        log.info("expansion %s: %s", ws.name, {v: tables[v] for v in EXPANSION if tables[v]})
        rep = run_pipeline(str(toml), from_stage=order[shared], to_stage="build-bsh", force=True)
        for v in order[shared:]:
            secs[v] = float(rep["stages"].get(v, {}).get("seconds", 0.0))
            cpu[v] = float(rep["stages"].get(v, {}).get("cpu_s", 0.0))
        bsh_in = rep["stages"]["build-bsh"]["input"]
        if root is None:
            io.write_json(done, {"seconds": secs, "cpu": cpu, "bsh_input": bsh_in, "tables": mine,
                                 "shared_from": str(src), "plan": rep.get("plan")})
        self.cpu.update(expansion=sum(cpu.get(v, 0.0) for v in EXPANSION), bsh=cpu.get("build-bsh", float("nan")))
        return ws, secs, Path(bsh_in)

    def bsh(self, tables: dict[str, dict[str, Any]]) -> tuple[Path, float, float]:
        """(bsh.npz, expansion seconds, build-bsh seconds) of a point."""
        from .. import io

        ws, secs, bsh_in = self.expansion(tables)
        exp_s = sum(secs[v] for v in EXPANSION)
        if tables["build-bsh"] == dict(self.base.data.get("build-bsh", {})):
            return Workspace(self.scene_dir, ws).bsh, exp_s, secs["build-bsh"]
        key = bsh_key(tables)
        out, done = ws / f"bsh_{key}.npz", ws / f"trade_bsh_{key}.json"
        if done.exists() and out.exists():
            d = io.read_json(done)
            self.cpu["bsh"] = float(d.get("cpu", float("nan")))
            return out, exp_s, float(d["seconds"])
        from ..run.stages import call_stage

        t0, c0 = time.perf_counter(), time.process_time()
        call_stage("build-bsh", self.base.resolved("build-bsh", tables["build-bsh"]), cloud=bsh_in, out=out)
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
        io.write_json(done, {"seconds": dt, "cpu": dc})
        self.cpu["bsh"] = dc
        return out, exp_s, dt

    def warm_up(self, tables: dict[str, dict[str, Any]], view: str, material: str, scene: dict[str, Any]) -> None:
        """Compile what the first row would otherwise pay for (numba kernels on a fresh install, GL shaders):
        the expansion with 64² faces and one view, build-bsh and an m = 8 relight, untimed, in ``work/warmup``.
        The photo is not registered here (``photo_fov`` 0: 4–9 min on a loaded machine); expose-match runs once
        for every row, so whatever it compiles weighs on every row alike."""
        t = {v: dict(d) for v, d in tables.items()}
        t["expose-match"]["photo_fov"] = 0.0
        t["render-cubemaps"].update(size=64, max_views=1)
        t["relight"].update(microbuffer=8, bounces=0)
        t0 = time.perf_counter()
        ws, _, _ = self.expansion(t, root=self.work / "warmup")
        self.relight(Workspace(self.scene_dir, ws).bsh, t, view, material, scene, repeat=1)
        log.info("warm-up (compiles numba kernels and GL shaders once; not in any row): %.1f s", time.perf_counter() - t0)

    def relight(self, bsh: Path, tables: dict[str, dict[str, Any]], view: str, material: str,
                scene: dict[str, Any], repeat: int | None = None) -> tuple[np.ndarray, dict[str, Any], float]:
        """(relit.exr, stats, fastest wall seconds of ``repeat`` runs, default ``--repeat``)."""
        from .. import io
        from ..run.stages import call_stage

        rcfg = self.base.resolved("relight", {**tables["relight"], **material_overrides(scene, material)})
        out = self.work / "relit"
        times, cpus, first = [], [], None
        for _ in range(repeat or self.cfg.repeat):
            t0, c0 = time.perf_counter(), time.process_time()
            st = call_stage("relight", rcfg, bsh=bsh, object_path=(), scene=self.scene_dir / "scene.json", view=view,
                            out=out)
            times.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
            img = io.read_image(out / "relit.exr")
            if first is not None and not np.array_equal(first, img):
                raise RuntimeError("relight is not deterministic across repeats")
            first = img
        assert first is not None
        self.cpu["relight"] = min(cpus)
        return first, st, min(times)


def _cpu_columns(cpu: dict[str, float]) -> dict[str, float]:
    """A row's CPU columns from :attr:`Sweep.cpu` (NaN where a part was not measured)."""
    nan = float("nan")
    e, b, r = (float(cpu.get(k, nan)) for k in ("expansion", "bsh", "relight"))
    return {"cpu_s": e + b + r, "expansion_cpu_s": e, "bsh_cpu_s": b, "relight_cpu_s": r}


def _same(a: Any, b: Any) -> bool:
    """Two option tables equal once written as JSON (a record's tuples come back as lists)."""
    return json.dumps(a, sort_keys=True, default=list) == json.dumps(b, sort_keys=True, default=list)


def _link(src: Path, dst: Path) -> None:
    """``dst`` holds what ``src`` holds (a file hard-linked, else copied; a folder file by file); nothing when
    ``src`` is absent (a stage the plan skipped). The stages replace their outputs by rename, so a later
    stage writing ``dst`` leaves ``src`` as it was."""
    import os
    import shutil

    if src.is_dir():
        for f in src.rglob("*"):
            if f.is_file():
                _link(f, dst / f.relative_to(src))
        return
    if not src.exists():
        return
    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.exists():
        dst.unlink()
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def _toml_literal(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_literal(x) for x in v) + "]"
    return json.dumps(str(v))


def plan_rows(base: Base, cfg: TradeConfig) -> Iterator[tuple[Point, dict[str, dict[str, Any]], dict[str, Any], str, str]]:
    """(point, tables, knobs, view, material) of every row of the sweep, in order; points whose knobs equal an
    earlier point's (a variation equal to the base value) are left out."""
    from ..gather import GATHERERS

    seen: set[tuple] = set()
    for p in grid(cfg.grid, list(GATHERERS)):
        tables = base.tables(p)
        knobs = base.knobs(tables)
        sig = tuple(_fmt(knobs[k]) for k in sorted(knobs))
        if sig in seen:
            continue
        seen.add(sig)
        for view in _names(cfg.views):
            for mat in _names(cfg.materials):
                yield p, tables, knobs, view, mat


def run_trade(scene_dir: str | Path, out: str | Path, work: str | Path, cfg: TradeConfig,
              config_toml: str | Path | None = None, preview: str | Path | None = None) -> dict[str, Any]:
    """Sweep, resume, write ``out``/trade.csv, trade.png (also to ``preview`` when given), trade.json and the
    three preset files. Returns trade.json's content (``complete`` False when the budget stopped the sweep)."""
    t_start = time.perf_counter()
    scene_dir, out, work = Path(scene_dir).resolve(), Path(out), Path(work)
    views, mats = _names(cfg.views), _names(cfg.materials)
    scene, e = check_scene(scene_dir, views, mats)
    base = Base(config_toml, cfg.seed)
    csv_path = out / "trade.csv"
    rows: list[Row] = read_rows(csv_path)
    done = {r["key"] for r in rows}
    todo = list(plan_rows(base, cfg))
    log.info("trade on %s: %d rows in the grid '%s' (%d views × %d materials), %d already in %s; e = %.4g; "
             "budget %s", scene_dir, len(todo), cfg.grid, len(views), len(mats),
             sum(row_key(k, v, m) in done for _, _, k, v, m in todo), csv_path, e,
             f"{cfg.budget_min:g} min" if cfg.budget_min else "none")
    sweep = Sweep(scene_dir, work, base, cfg)
    complete, measured, warm = True, 0, False
    for p, tables, knobs, view, mat in todo:
        key = row_key(knobs, view, mat)
        if key in done:
            continue
        if not warm:
            sweep.warm_up(tables, view, mat, scene)
            warm = True
        if cfg.budget_min and measured and time.perf_counter() - t_start > 60 * cfg.budget_min:
            complete = False
            log.warning("budget of %g min reached: stopped before row '%s' %s/%s; rerun the same command to resume",
                        cfg.budget_min, p.label, view, mat)
            break
        check_interrupt()
        load1 = os.getloadavg()[0]
        sweep.cpu = {}
        bsh, exp_s, bsh_s = sweep.bsh(tables)
        img, st, rel_s = sweep.relight(bsh, tables, view, mat, scene)
        res = compare(scene_dir, img, e, view, mat)
        row = {"key": key, "point": p.label, **{k: _fmt(v) for k, v in knobs.items()}, "view": view, "material": mat,
               "seconds": exp_s + bsh_s + rel_s, "expansion_s": exp_s, "bsh_s": bsh_s, "relight_s": rel_s,
               **_cpu_columns(sweep.cpu), "load1": load1, **res,
               "nodes_per_pixel": st.get("nodes_visited_per_pixel", 0.0), "bsh_nodes": st.get("nodes", 0),
               "renderer": st.get("gl", {}).get("renderer", "")}
        rows.append(row)
        done.add(key)
        measured += 1
        write_rows(csv_path, rows)
        log.info("row %-22s %s/%-8s %7.1f s (relight %5.2f s, CPU %.1f s, load %.1f)  err %.4f  gather err %.4f",
                 p.label, view, mat, row["seconds"], rel_s, row["relight_cpu_s"], load1, row["err"], row["gather_err"])
    summary = finish(rows, out, complete, source=str(csv_path), measured=measured, todo=len(todo))
    if preview is not None and (out / "trade.png").exists():
        from .. import io

        with io.atomic_path(preview) as tmp:
            tmp.write_bytes((out / "trade.png").read_bytes())
    return summary


def finish(rows: list[Row], out: Path, complete: bool = True, source: str = "trade.csv", measured: int = 0,
           todo: int = 0) -> dict[str, Any]:
    """The front plot, the presets picked by the rule and trade.json from ``rows``."""
    from .. import io

    if not rows:
        log.warning("no row measured yet (the budget ran out first): nothing written; rerun to resume")
        return {"complete": False, "rows": 0, "measured_now": 0, "grid_rows": todo}
    rows = [dict(r) for r in rows]
    picks = pick_presets(rows)
    report = preset_report(rows, picks)
    plot(rows, picks, out / "trade.png")
    for name in PRESET_NAMES:
        with io.atomic_path(out / f"{name}.toml") as tmp:
            tmp.write_text(preset_toml(name, picks[name], report[name], Path(source).name))
    summary = {"complete": complete, "rows": len(rows), "measured_now": measured, "grid_rows": todo,
               "rule": {"balanced_factor": BALANCED_FACTOR, "fast_factor": FAST_FACTOR}, "presets": report}
    io.write_json(out / "trade.json", summary)
    with io.atomic_path(out / "trade.md") as tmp:
        tmp.write_text(format_markdown(rows, report, complete))
    for name in PRESET_NAMES:
        log.info("preset %-8s = %-20s %s", name, report[name]["point"], "; ".join(
            f"{p}: err {d['err']:.4f} {d['seconds']:.1f} s ({_front_words(d)})" for p, d in report[name]["pairs"].items()))
    log.info("wrote %s, %s, %s and %s%s", out / "trade.csv", out / "trade.png", out / "trade.json",
             ", ".join(f"{n}.toml" for n in PRESET_NAMES), "" if complete else " (sweep incomplete: rerun to resume)")
    return summary
