"""The run report: one self-contained HTML page of a pipeline workspace (``pcrelight report``; ``pcrelight run``
ends by writing it).

The page shows what is in the workspace, nothing more: the inputs (the photo tone-mapped, make-scene's cloud
panorama and path-traced reference when the inputs folder has them), the plan's decisions (``run.json``), every
stage's status, options, report (``<stage>.json`` / ``report.json`` / ``stats.json``: its decisions and numbers)
and PNG previews, the timings, the relit image and ``composite.png`` when there is one, the renders of several gatherers side by side when
the workspace holds more than one relight output (:func:`relight_renders`), Table 2 (``table.json``,
``table.png`` from ``evaluate``) and the speed/accuracy trade (``trade.csv`` and its Pareto PNG from ``trade``)
when present. Which files a stage writes comes from :data:`pipeline.run.stages.STAGES`, their names from
:mod:`pipeline.io.workspace`.

Self-contained: every image is embedded as a ``data:`` URI (PNG; previews wider or taller than ``max_px`` are
downscaled), CSS and script are inline, and the page's Content-Security-Policy forbids any network load. A small
inline script checks that every ``<img>`` decoded (``naturalWidth`` > 0) and colours the band at the top of the
page: green when all did, red (and the broken images outlined) when one did not, grey without JavaScript.

A missing optional piece is left out of the page; a workspace that is not one (no ``run.json`` and no stage
output) or holds a broken file (bad JSON, a PNG that does not decode) is an :class:`~pipeline.errors.InputError`.
The page is a function of the files: the same workspace gives the same bytes (no clock in it).
"""

from __future__ import annotations

import base64
import csv
import json
import math
import os
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from .. import __version__
from ..errors import InputError
from ..runtime import get_logger

log = get_logger("report")

MAX_PX = 1600                      # embedded images: longest side [px]; larger previews are downscaled
TIMING_KEYS = ("timings", "timings_s", "time_s")       # a stage report's breakdown of its time [s]
TOTAL_KEYS = ("seconds", "total_s")                    # a stage report's own total time [s]
NOT_NUMBERS = {"config", "decisions", "inputs", "input", "outputs", "output", "stage", "preview", *TIMING_KEYS}
# Marker colours of the band at the top of the page (RGB; the test reads them from a screenshot).
MARK_PENDING = (128, 128, 128)
MARK_OK = (0, 160, 64)
MARK_BROKEN = (208, 16, 16)


@dataclass
class Figure:
    """One embedded image: title, ``data:`` URI, where it came from, its size in the page [px]."""

    title: str
    src: str
    source: str
    width: int
    height: int
    note: str = ""


@dataclass
class StageView:
    """What the page shows of one stage."""

    verb: str
    status: str                     # ran | kept | skipped | earlier | present | absent
    detail: str                     # one sentence: how long, why skipped, …
    seconds: float | None = None
    from_plan: dict[str, Any] = field(default_factory=dict)
    config: list[tuple[str, str]] = field(default_factory=list)
    reports: list[dict[str, Any]] = field(default_factory=list)   # name, decisions, numbers, timings, text
    figures: list[Figure] = field(default_factory=list)


# ----------------------------------------------------------------------------- formatting (pure)
def fmt(v: Any, width: int = 96) -> str:
    """A value for a table cell: floats to 4 significant digits, None as —, short lists inline, long ones
    cut with their length."""
    if v is None:
        return "—"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return "NaN" if math.isnan(v) else f"{v:.4g}"
    if isinstance(v, (int, str)):
        return str(v)
    if isinstance(v, (list, tuple)):
        if len(v) > 8 and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
            return "[" + ", ".join(fmt(x) for x in v[:4]) + f", … {len(v)} values]"
        text = "[" + ", ".join(fmt(x, width) for x in v) + "]"
    elif isinstance(v, dict):
        text = "{" + ", ".join(f"{k}: {fmt(x, width)}" for k, x in v.items()) + "}"
    else:
        text = str(v)
    return text if len(text) <= width else text[:width - 1] + "…"


def rows_of(d: dict[str, Any], skip: Iterable[str] = (), prefix: str = "") -> list[tuple[str, str]]:
    """A report's entries as (key, text) rows: nested tables one level deep as ``key.sub``, deeper ones
    inline (cut by :func:`fmt`)."""
    out: list[tuple[str, str]] = []
    for k, v in d.items():
        if k in skip:
            continue
        if isinstance(v, dict) and not prefix and v:
            out += rows_of(v, (), f"{k}.")
        else:
            out.append((prefix + str(k), fmt(v)))
    return out


def bar_rows(seconds: dict[str, float | None]) -> list[dict[str, Any]]:
    """Timing rows with a bar width in % of the largest (None: no time known)."""
    known = [s for s in seconds.values() if s is not None]
    top = max(known, default=0.0)
    return [{"name": k, "seconds": s, "text": "—" if s is None else f"{s:.2f} s",
             "pct": 0.0 if not s or top <= 0 else round(100.0 * s / top, 1)} for k, s in seconds.items()]


# ----------------------------------------------------------------------------- images
def _data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def png_figure(path: Path, title: str, max_px: int = MAX_PX, note: str = "") -> Figure:
    """Embed a PNG file (decoded first: a file that does not decode is an InputError; longer than ``max_px``
    on a side: downscaled)."""
    from PIL import Image, UnidentifiedImageError

    data = path.read_bytes()
    try:
        with Image.open(BytesIO(data)) as im:
            im.load()
            if im.format != "PNG":
                raise InputError(path, f"not a PNG ({im.format})")
            w, h = im.size
            if max(w, h) > max_px:
                im.thumbnail((max_px, max_px), Image.Resampling.LANCZOS)
                buf = BytesIO()
                im.save(buf, format="PNG")
                data = buf.getvalue()
                note = (note + "; " if note else "") + f"downscaled from {w}×{h}"
                w, h = im.size
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        raise InputError(path, f"not a readable PNG ({str(e).splitlines()[0] if str(e) else type(e).__name__})") from None
    return Figure(title, _data_uri(data), str(path), w, h, note)


def array_figure(rgb: np.ndarray, title: str, source: str, max_px: int = MAX_PX, note: str = "") -> Figure:
    """Embed display-encoded RGB in [0, 1] (H, W, 3) as a PNG."""
    from PIL import Image

    im = Image.fromarray(np.round(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.uint8), "RGB")
    if max(im.size) > max_px:
        im.thumbnail((max_px, max_px), Image.Resampling.LANCZOS)
    buf = BytesIO()
    im.save(buf, format="PNG")
    return Figure(title, _data_uri(buf.getvalue()), source, im.size[0], im.size[1], note)


def photo_figure(path: Path, max_px: int = MAX_PX) -> Figure:
    """The HDR photo tone-mapped as the previews are (:func:`pipeline.display.tonemap`), with its peak."""
    from .. import io
    from ..color import luminance
    from ..display import tonemap

    img = io.read_image(path)
    rgb = np.nan_to_num(img[..., :3] if img.ndim == 3 else np.repeat(img[..., None], 3, axis=2))
    peak = float(luminance(rgb).max()) if rgb.size else 0.0
    return array_figure(tonemap(rgb), f"photo ({path.name}, tone-mapped)", str(path), max_px,
                        f"{img.shape[1]}×{img.shape[0]}, peak luminance {peak:.4g}")


# ----------------------------------------------------------------------------- reading the workspace
def _read_dict(path: Path) -> dict[str, Any]:
    from .. import io

    obj = io.read_json(path)
    if not isinstance(obj, dict):
        raise InputError(path, f"expected a JSON object, got {type(obj).__name__}")
    return obj


def stage_report(path: Path, label: str) -> dict[str, Any]:
    """One stage report JSON, split for the page: its decisions, its numbers, its timing breakdown, its own
    total time, its options and the pretty text."""
    d = _read_dict(path)
    timing = next((d[k] for k in TIMING_KEYS if isinstance(d.get(k), dict)), {})
    total = next((float(d[k]) for k in TOTAL_KEYS if isinstance(d.get(k), (int, float)) and not isinstance(d.get(k), bool)), None)
    return {"name": label, "path": str(path),
            "decisions": rows_of(d["decisions"]) if isinstance(d.get("decisions"), dict) else [],
            "numbers": rows_of(d, NOT_NUMBERS | set(TOTAL_KEYS)),
            "timings": bar_rows({k: float(v) for k, v in timing.items() if isinstance(v, (int, float))}),
            "total": total,
            "config": d.get("config") if isinstance(d.get("config"), dict) else None,
            "text": json.dumps(d, indent=1, sort_keys=True, default=str)}


def _label(path: Path, root: Path) -> str:
    try:
        return str(path.relative_to(root))
    except ValueError:
        return str(path)


def _stage_view(st: Any, ws: Any, entry: dict[str, Any] | None, have_run: bool, max_px: int) -> StageView:
    """The page's view of one stage: its status from run.json's entry (None: not in this run), its files."""
    shown = [p for p in st.all_outputs(ws) if p.exists() and p.is_file()]
    if entry is not None and entry.get("skipped") and entry.get("plan"):
        return StageView(st.verb, "skipped", f"skipped by the plan: {entry['plan']}",
                         config=rows_of(entry.get("config", {})))
    if entry is not None and entry.get("skipped"):
        status, detail = "kept", "outputs up to date: kept from an earlier run (--force reruns)"
    elif entry is not None:
        status, detail = "ran", f"ran in {float(entry.get('seconds', 0.0)):.2f} s"
    elif not shown:
        return StageView(st.verb, "absent", "not in this run: no outputs in the workspace")
    elif have_run:
        status, detail = "earlier", "not in this run (run.json): outputs from an earlier run"
    else:
        status, detail = "present", "outputs present (no run.json: the stage was run on its own)"
    v = StageView(st.verb, status, detail, seconds=entry.get("seconds") if entry else None,
                  from_plan=dict(entry.get("from_plan", {})) if entry else {})
    for p in shown:
        if p.suffix == ".json":
            v.reports.append(stage_report(p, _label(p, ws.root)))
    cfg = entry.get("config") if entry else next((r["config"] for r in v.reports if r["config"]), None)
    v.config = rows_of(cfg or {})
    if v.seconds is None:
        v.seconds = next((r["total"] for r in v.reports if r["total"] is not None), None)
    preview = st.preview_path(ws)
    for p in sorted((p for p in shown if p.suffix == ".png" and p != ws.relit), key=lambda p: p != preview):
        v.figures.append(png_figure(p, "preview" if p == preview else p.name, max_px))
    return v


def _table2(table_json: Path, max_px: int) -> dict[str, Any] | None:
    """Table 2 from evaluate's table.json (and table.png beside it), or None when absent."""
    if not table_json.is_file():
        return None
    t = _read_dict(table_json)
    rows = t.get("rows")
    if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
        raise InputError(table_json, "no 'rows' list of objects (not evaluate's table.json)")
    cols: list[str] = []
    for r in rows:
        cols += [k for k in r if k not in cols and k not in ("method", "file")]
    png = table_json.with_suffix(".png")
    return {"path": str(table_json), "columns": cols,
            "rows": [[str(r.get("method", "?")).upper()] + [fmt(r.get(c)) for c in cols] for r in rows],
            "facts": rows_of({k: t.get(k) for k in ("truth", "photo", "e", "photo_peak", "alpha") if k in t}),
            "figure": png_figure(png, png.name, max_px) if png.is_file() else None}


def _trade(trade_csv: Path, max_px: int, max_rows: int = 60) -> dict[str, Any] | None:
    """The speed/accuracy trade: trade.csv (and the Pareto PNG beside it), or None when absent."""
    if not trade_csv.is_file():
        return None
    try:
        with open(trade_csv, newline="") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise InputError(trade_csv, f"not a readable CSV ({e})") from None
    if not rows:
        raise InputError(trade_csv, "empty (no header row)")
    pngs = sorted(p for p in trade_csv.parent.glob("*.png") if "pareto" in p.name.lower() or "trade" in p.name.lower())
    return {"path": str(trade_csv), "header": rows[0], "rows": rows[1:max_rows + 1], "total": len(rows) - 1,
            "figures": [png_figure(p, p.name, max_px) for p in pngs]}


def _inputs(ws: Any, max_px: int) -> dict[str, Any] | None:
    """The inputs folder: the files the run read (with sizes), the photo and make-scene's cloud panorama
    (when present)."""
    if ws.inputs is None or not Path(ws.inputs).is_dir():
        return None
    files = [(str(p), f"{p.stat().st_size / 1e6:.2f} MB") for p in (ws.photo, ws.cloud_ldr, ws.scene, ws.object)
             if p.is_file()]
    figs = []
    if ws.photo.is_file():
        figs.append(photo_figure(ws.photo, max_px))
    pano = ws.inputs / "previews" / "cloud_ldr_panorama.png"
    if pano.is_file():
        figs.append(png_figure(pano, "LDR cloud (make-scene's panorama)", max_px))
    return {"folder": str(ws.inputs), "files": files, "figures": figs}


def relight_renders(root: Path) -> list[tuple[Path, dict[str, Any]]]:
    """The relight outputs of a workspace: its own (``relit.exr`` + ``stats.json`` at the root) and those of
    relight runs into its sub-folders (``pcrelight relight --method X --out <workspace>/relit_X``), as
    ``(folder, stats.json)``; a folder counts when it holds both files and the stats name the relight stage."""
    out = []
    for d in [root] + sorted(p for p in root.iterdir() if p.is_dir()):
        if (d / "relit.exr").is_file() and (d / "stats.json").is_file():
            st = _read_dict(d / "stats.json")
            if st.get("stage") == "relight":
                out.append((d, st))
    return out


def _methods(root: Path, max_px: int) -> dict[str, Any] | None:
    """Several gatherers' renders side by side (when the workspace holds at least two relight outputs, see
    :func:`relight_renders`): one row at one exposure (the first render's automatic one,
    :func:`pipeline.display.side_by_side`) of those with the first one's size, and a table of every render's
    method, BRDF, size and time; None with fewer than two."""
    from .. import io
    from ..display import side_by_side

    found = relight_renders(root)
    if len(found) < 2:
        return None
    imgs = [io.read_image(d / "relit.exr") for d, _ in found]
    shape = imgs[0].shape[:2]
    rows, shown = [], []
    for (d, st), img in zip(found, imgs):
        same = img.shape[:2] == shape and img.shape[2] >= 3
        if same:
            shown.append((d, st, img))
        rows.append({"method": str(st.get("method", "?")), "folder": _label(d, root) if d != root else ".",
                     "brdf": str(st.get("brdf", "?")), "size": f"{img.shape[1]}×{img.shape[0]}",
                     "microbuffer": fmt(st.get("microbuffer")), "seconds": fmt(st.get("total_s")),
                     "shown": same})
    fig = None
    if len(shown) >= 2:
        names = [f"{st.get('method', '?')} ({_label(d, root) if d != root else '.'})" for d, st, _ in shown]
        fig = array_figure(side_by_side([img for _, _, img in shown]), "left to right: " + ", ".join(names),
                           ", ".join(str(d / "relit.exr") for d, _, _ in shown), max_px,
                           "one exposure: the first render's automatic one")
    return {"rows": rows, "figure": fig}


# ----------------------------------------------------------------------------- the page
def collect(workspace: str | os.PathLike, inputs: str | os.PathLike | None = None,
            table: str | os.PathLike | None = None, trade: str | os.PathLike | None = None,
            max_px: int = MAX_PX) -> dict[str, Any]:
    """Everything the page shows, read from the workspace (see the module docstring). ``inputs``: the inputs
    folder (default: run.json's); ``table``: evaluate's table.json (default ``<workspace>/table.json``);
    ``trade``: trade.csv (default ``<workspace>/trade.csv``)."""
    from .stages import STAGES, VERBS
    from ..io.workspace import NAMES, Workspace

    root = Path(workspace)
    if not root.is_dir():
        raise InputError(root, "no such folder (give the workspace of a pcrelight run)")
    run_json = root / NAMES["run_report"]
    run = _read_dict(run_json) if run_json.exists() else None
    if run is not None and not (isinstance(run.get("stages"), dict) and isinstance(run.get("run", {}), dict)):
        raise InputError(run_json, "not a pcrelight run.json (no 'stages' table)")
    opts = (run or {}).get("run", {})
    plan = (run or {}).get("plan") if isinstance((run or {}).get("plan"), dict) else None
    inp = Path(inputs) if inputs is not None else (Path(opts["inputs"]) if opts.get("inputs") else None)
    hdr_cloud = plan.get("hdr_cloud", "cloud_hdr") if plan else "cloud_hdr"
    ws = Workspace(inp if inp is not None else root, root, Path(opts["object"]) if opts.get("object") else None,
                   True, str(opts.get("view", "view1")),
                   hdr_cloud=hdr_cloud if hdr_cloud in ("cloud_ldr", "cloud_proj", "cloud_hdr") else "cloud_hdr")
    entries = (run or {}).get("stages", {})
    views = [_stage_view(st, ws, entries.get(st.verb) if isinstance(entries.get(st.verb), dict) else None,
                         run is not None, max_px) for st in STAGES]
    if run is None and all(v.status == "absent" for v in views):
        raise InputError(root, f"not a pcrelight workspace: no {NAMES['run_report']} and no stage output")
    stats = next((r for v in views if v.verb == VERBS[-1] for r in v.reports), None)
    brdf = None
    if ws.relit_stats.is_file():
        b = _read_dict(ws.relit_stats).get("brdf")
        brdf = b if isinstance(b, str) else None
    result = []   # the composite first: the object in the photo (make demo's photo/), else over the room
    for composite, what in ((ws.root / "photo" / "composite.png", "the object in the photo (photo/composite.png)"),
                            (ws.relit_dir / "composite.png", "composite (composite.png)")):
        if composite.is_file():
            result.append(png_figure(composite, what, max_px))
    if ws.relit.is_file() and views[-1].status != "skipped":
        result.append(png_figure(ws.relit, "relit object (relit.png)", max_px))
    ref = ws.inputs / "previews" / f"full_{ws.view}_{brdf}.png" if inp is not None and brdf else None
    if result and ref is not None and ref.is_file():  # make-scene's path trace of the same view and BRDF
        result.append(png_figure(ref, f"path-traced reference ({ref.name}, make-scene)", max_px))
    decisions = []
    for d in (plan or {}).get("decisions", []):
        if isinstance(d, dict):
            needed = d.get("needed")
            decisions.append({"name": d.get("name", "?"), "state": {True: "needed", False: "not needed"}.get(needed, "pending"),
                              "why": str(d.get("why", "")), "when": str(d.get("when", "")),
                              "stages": ", ".join(map(str, d.get("stages", []))),
                              "value": fmt(d.get("value")), "threshold": fmt(d.get("threshold"))})
    seconds = {v.verb: v.seconds for v in views if v.status in ("ran", "present", "kept", "earlier")}
    ran = [v.seconds for v in views if v.status == "ran" and v.seconds is not None]
    page = {
        "title": f"pcrelight report — {root}",
        "workspace": str(root), "version": __version__,
        "run": {"config": (run or {}).get("config"), "options": rows_of(opts)} if run is not None else None,
        "view": ws.view,
        "inputs": _inputs(ws, max_px) if inp is not None else None,
        "decisions": decisions, "follow": plan.get("follow", True) if plan else None,
        "stages": views, "timings": bar_rows(seconds), "total": round(sum(ran), 3) if ran else None,
        "result": result, "stats": stats, "methods": _methods(root, max_px),
        "table": _table2(Path(table) if table is not None else root / "table.json", max_px),
        "trade": _trade(Path(trade) if trade is not None else root / "trade.csv", max_px),
        "marks": {"pending": MARK_PENDING, "ok": MARK_OK, "broken": MARK_BROKEN},
    }
    return page


def render(page: dict[str, Any]) -> str:
    """The HTML of a collected page (the Jinja2 template ``templates/report.html.j2``, autoescaped)."""
    import jinja2

    env = jinja2.Environment(loader=jinja2.PackageLoader("pipeline.run", "templates"),
                             autoescape=jinja2.select_autoescape(["html", "j2"]), undefined=jinja2.StrictUndefined,
                             trim_blocks=True, lstrip_blocks=True, keep_trailing_newline=True)
    env.filters["fmt"] = fmt
    env.filters["rgb"] = lambda c: "#%02x%02x%02x" % tuple(c)
    return env.get_template("report.html.j2").render(**page)


def write_report(workspace: str | os.PathLike, out: str | os.PathLike | None = None,
                 inputs: str | os.PathLike | None = None, table: str | os.PathLike | None = None,
                 trade: str | os.PathLike | None = None, max_px: int = MAX_PX) -> Path:
    """Collect, render and write the report of ``workspace`` atomically to ``out`` (default
    ``<workspace>/report.html``); returns the path."""
    import time

    from .. import io
    from ..io.workspace import NAMES

    t0 = time.perf_counter()
    out = Path(out) if out is not None else Path(workspace) / NAMES["report"]
    page = collect(workspace, inputs, table, trade, max_px)
    html = render(page)
    with io.atomic_path(out) as tmp:
        tmp.write_text(html, encoding="utf-8")
    n_img = html.count("<img ")
    log.info("report: %s (%d images, %.1f MB, %d stages shown%s%s) in %.1f s", out, n_img, len(html) / 1e6,
             sum(v.status != "absent" for v in page["stages"]), ", Table 2" if page["table"] else "",
             ", trade" if page["trade"] else "", time.perf_counter() - t0)
    return out
