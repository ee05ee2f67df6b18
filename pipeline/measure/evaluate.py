"""``pcrelight evaluate``: the Table 2 equivalent against the ground truth of ``make-scene``.

Cloud columns (every cloud has the points of ``cloud_ldr.ply`` in the same order as
``cloud_gt.ply``): RMS of the colours in the LDR cloud's units (1.0 = LDR white; the truth is
scaled by the exposure e of ``truth/truth.npz``), the same on the overexposed points only, the
same on the overexposed points whose true luminance is within the photo's peak (what any
photo-based expansion can recover: emitters the photo never sees dominate the plain column), and
the RMS of log10 luminance. α error: the estimate of ``exposure.npz`` against α_true.
Rendering columns: the object relit (same relight options) with each cloud against the object
relit with ``cloud_gt.ply`` scaled by e, at view1 and view2: relative RMS and SSIM (scikit-image,
on the tone-mapped images, as the paper's Table 2 compares what is seen).

Per photo (:func:`run_all_photos`): a truth with several photos (scene.json "photos") is expanded
again with each other photo, and with each photo set of ``--photo-sets`` (photos and the panorama
``pano`` joined by '+'); ``photos.{json,md}`` give per photo (or set) and method the α error and the
cloud columns, plus the RMS on the overexposed points that photo (any photo of the set) sees
(``cloud_rms_over_visible``).
Against Monte-Carlo references, :func:`compare_to_reference` is the one comparison (mean ratio,
relative RMS per pixel and on k×k block means, the reference's own noise, noise-corrected RMS).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..config import StageConfig
from ..gather import GATHERERS, MICROBUFFER_SIDES
from ..metrics import cloud_metrics, image_metrics, precise_metrics
from ..errors import InputError
from ..runtime import get_logger

log = get_logger("evaluate")

# row label of a cloud from its file stem (cloud_<method>.ply), in Table 2's order
ROWS = ["ldr", "landis", "banterle", "rhee", "landis-pc", "banterle-pc", "pmatch-lum", "pmatch-rgb"]


@dataclass
class EvaluateConfig(StageConfig):
    render: bool = field(default=True, metadata={"help": "also relight the object with every cloud (rendering columns)"})
    size: int = field(default=64, metadata={"help": "rendering size for the rendering columns [pixels]"})
    microbuffer: int = field(default=16, metadata={"help": "micro-buffer size for the rendering columns [texels]",
                                                  "choices": MICROBUFFER_SIDES})
    method: str = field(default="hybrid", metadata={"help": "relight method for the rendering columns",
                                                    "choices": tuple(GATHERERS)})
    photos: str = field(default="all", metadata={"help": "--run-all: also expand with every other photo of scene.json "
                                                 "(photo_<name>.exr; cloud columns and α only) and tabulate per photo",
                                                 "choices": ("all", "default")})
    photo_sets: tuple[str, ...] = field(default=(), metadata={"help": "photo sets, each the names of scene.json's photos "
                                                              "(bright, lights, sun) and 'pano' (the panorama) joined by '+', "
                                                              "e.g. bright+lights+sun,pano: with --run-all every method is run "
                                                              "again with each set (cloud columns and α, in photos.{json,md}); "
                                                              "without it, one set: the photos the CLOUDS were expanded with"})

    def check(self) -> None:
        self.check_choices()
        self._require(8 <= self.size <= 4096, "size", "must be in [8, 4096]")
        self._require(all(s and all(n.strip() for n in s.split("+")) for s in self.photo_sets), "photo_sets",
                      "must be photo names joined by '+', sets separated by ','")


def _label(path: Path) -> str:
    stem = path.stem
    if stem == "cloud_ldr":
        return "ldr"
    return stem[len("cloud_"):] if stem.startswith("cloud_") else stem


def run_evaluate(truth_dir: str | os.PathLike, clouds: list[str | os.PathLike], json_out: str | os.PathLike | None,
                 md_out: str | os.PathLike | None, cfg: EvaluateConfig, exposure: str | os.PathLike | None = None,
                 timings: dict[str, Any] | None = None, preview: str | os.PathLike | None = None,
                 photos: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """Compute the table for ``clouds`` against ``truth_dir`` and write JSON/Markdown. ``photos``: the photo set
    the clouds were expanded with (:func:`photo_set`; default: photo.exr with truth/truth.npz) — its peak is the
    brightest photo's, its visible points those any photo sees, its α that of the first (the set's reference)."""
    from .. import io

    t0 = time.perf_counter()
    truth_dir = Path(truth_dir)
    members = photos or [{"file": "photo.exr", "truth": "truth/truth.npz"}]
    trs = [io.read_npz(truth_dir / p["truth"], "pcrelight.truth/1") for p in members]
    tr = trs[0]
    e = float(tr["e"])
    gt = io.read_cloud(truth_dir / "cloud_gt.ply")
    truth = gt.colors * e
    over = tr["overexposed"].astype(bool)
    # the photo's peak in the cloud's units: its radiance is k × the truth's, the LDR cloud e × it
    peak = max(float(io.luminance(io.read_image(truth_dir / p["file"])[..., :3]).max()) / float(t["k"]) * e
               for p, t in zip(members, trs))
    in_range = io.luminance(truth) <= peak
    visible = None
    if all("photo_visible" in t for t in trs):
        visible = np.logical_or.reduce([t["photo_visible"].astype(bool) for t in trs])
    prec_file = truth_dir / "truth" / "cloud_precise.npz"
    precise = io.read_npz(prec_file, "pcrelight.cloud_precise/1") if prec_file.exists() else None
    log.info("truth %s: %d points, e = %.6g, %d overexposed (%d within the photo's peak %.4g)", truth_dir, len(gt), e,
             int(over.sum()), int((over & in_range).sum()), peak)
    if not clouds:
        raise InputError(truth_dir, "no clouds to evaluate (give CLOUD.ply arguments)")
    renderer = _Renderer(truth_dir, cfg, e) if cfg.render else None
    rows = []
    for p in map(Path, clouds):
        c = io.read_cloud(p)
        if len(c) != len(gt):
            raise InputError(p, f"has {len(c)} points, the ground truth has {len(gt)} (same points, same order expected)")
        row: dict[str, Any] = {"method": _label(p), "file": str(p), **cloud_metrics(c.colors, truth, over, in_range, visible)}
        if precise is not None:
            row.update(precise_metrics(c.colors, precise, e, over, in_range))
        if renderer is not None:
            row.update(renderer.columns(p))
        rows.append(row)
        log.info("%s: cloud RMS %.4f (overexposed %.4f), log RMS %.4f", row["method"], row["cloud_rms"],
                 row["cloud_rms_over"], row["log_rms"])
    rows.sort(key=lambda r: (ROWS.index(r["method"]) if r["method"] in ROWS else len(ROWS), r["method"]))
    table: dict[str, Any] = {"truth": str(truth_dir), "e": e, "photo_peak": peak,
                             "photo": str(tr["photo_name"]) if "photo_name" in tr else None, "rows": rows, "timings": timings or {},
                             "alpha": {"true": float(tr["alpha_true"]), "estimated": None}}
    if photos is not None:
        table["photo_set"] = [p["name"] for p in photos]
    if exposure is not None:
        ex = io.read_npz(exposure, "pcrelight.exposure/1")
        a = float(ex["alpha"])
        table["alpha"].update(estimated=a, relative_error=abs(a - float(tr["alpha_true"])) / float(tr["alpha_true"]),
                              source=str(ex["alpha_source"]) if "alpha_source" in ex else "histogram",
                              histogram=float(ex["alpha_histogram"]) if "alpha_histogram" in ex else a,
                              register=float(ex["alpha_register"]) if "alpha_register" in ex else None)
    table["timings"]["evaluate"] = round(time.perf_counter() - t0, 3)
    if json_out:
        io.write_json(json_out, table)
    if preview is not None:
        plot_table(preview, table)
    md = format_markdown(table)
    if md_out:
        with io.atomic_path(md_out) as tmp:
            tmp.write_text(md)
    print(md)
    return table


def plot_table(path: str | os.PathLike, table: dict[str, Any]) -> None:
    """PNG preview: one bar chart per metric (lower is better), one bar per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io import save_figure

    cols = [c for c in ("cloud_rms_over_in_range", "log_rms", "render_rms_view1", "render_rms_view2")
            if any(c in r for r in table["rows"])]
    names = [r["method"].upper() for r in table["rows"]]
    fig, axes = plt.subplots(1, len(cols), figsize=(4 * len(cols), 3.6), squeeze=False)
    for ax, c in zip(axes[0], cols):
        vals = [r.get(c, np.nan) for r in table["rows"]]
        ax.barh(names, vals, color=["#c44" if n.startswith("PMATCH") else "#888" for n in names])
        ax.set_title(c)
        ax.invert_yaxis()
    fig.suptitle(f"Table 2 against {table['truth']} (lower is better)")
    fig.tight_layout()
    save_figure(path, fig)


def format_markdown(table: dict[str, Any]) -> str:
    cols = ["cloud_rms", "cloud_rms_over", "cloud_rms_over_in_range", "precise_rms_over_in_range", "log_rms", "render_rms_view1", "render_ssim_view1",
            "render_rms_view2", "render_ssim_view2"]
    cols = [c for c in cols if any(c in r for r in table["rows"])]
    out = ["| method | " + " | ".join(cols) + " |", "|---|" + "---:|" * len(cols)]
    for r in table["rows"]:
        out.append(f"| {r['method'].upper()} | " + " | ".join(
            "—" if r.get(c) is None or (isinstance(r.get(c), float) and np.isnan(r[c])) else f"{r[c]:.4f}" for c in cols) + " |")
    a = table["alpha"]
    out.append("")
    out.append(f"α true {a['true']:.6g}" + (f", estimated {a['estimated']:.6g} (relative error {a['relative_error']:.2%})"
                                          if a.get("estimated") is not None else ""))
    return "\n".join(out) + "\n"


class _Renderer:
    """Relights the scene's object with a cloud (build-bsh + relight in a temp folder) and
    compares with the object relit by the ground-truth cloud scaled by e."""

    def __init__(self, truth_dir: Path, cfg: EvaluateConfig, e: float):
        self.truth_dir, self.cfg, self.e = truth_dir, cfg, e
        self.ref: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def _render(self, cloud: Path, view: str, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        import tempfile

        from .. import io
        from ..config import resolve
        from ..run.stages import STAGE, call_stage

        with tempfile.TemporaryDirectory(prefix="pcrelight-eval-") as td:
            td = Path(td)
            src = cloud
            if scale != 1.0:
                c = io.read_cloud(cloud)
                c.colors = (c.colors * np.float32(scale)).astype(np.float32)
                src = td / "scaled.ply"
                io.write_cloud(src, c)
            bcfg = resolve(STAGE["build-bsh"].config_class(), None, "build-bsh", {"seed": self.cfg.seed})
            call_stage("build-bsh", bcfg, cloud=src, out=td / "bsh.npz")
            rcfg = resolve(STAGE["relight"].config_class(), None, "relight",
                           {"seed": self.cfg.seed, "size": f"{self.cfg.size}x{self.cfg.size}",
                            "microbuffer": self.cfg.microbuffer, "method": self.cfg.method})
            call_stage("relight", rcfg, bsh=td / "bsh.npz", object_path=(self.truth_dir / "object.glb",),
                       scene=self.truth_dir / "scene.json", view=view, out=td / "r")
            img = io.read_image(td / "r" / "relit.exr")
        return img[..., :3], img[..., 3] > 0.5

    def columns(self, cloud: Path) -> dict[str, float]:
        out = {}
        for view in ("view1", "view2"):
            if view not in self.ref:
                self.ref[view] = self._render(self.truth_dir / "cloud_gt.ply", view, scale=self.e)
            ref, mask = self.ref[view]
            img, _ = self._render(cloud, view)
            m = image_metrics(img, ref, mask)
            out[f"render_rms_{view}"] = m["rms"]
            out[f"render_ssim_{view}"] = m["ssim"]
            out[f"render_ratio_{view}"] = m["mean_ratio"]
            out[f"render_rms_block_{view}"] = m["rms_block"]
        return out


# ----------------------------------------------------------------------------- every method
# (row, patchmatch method or None, reproject overrides); LDR is the input cloud itself
METHODS: list[tuple[str, str | None, dict[str, Any]]] = [
    ("landis", "landis", {}), ("banterle", "banterle", {}), ("rhee", "rhee", {}),
    ("landis-pc", None, {"method": "landis-pc"}), ("banterle-pc", None, {"method": "banterle-pc"}),
    ("pmatch-lum", "pmatch", {"transfer": "lum"}), ("pmatch-rgb", "pmatch", {"transfer": "rgb"}),
]


def run_all(sample: str | os.PathLike, out: str | os.PathLike, config_toml: str | os.PathLike | None,
            cfg: EvaluateConfig, methods: list[str] | None = None,
            preview: str | os.PathLike | None = None, photos: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """Expand the sample's LDR cloud with every method (one expose-match and one render-cubemaps
    shared by all), then evaluate every cloud: ``out/table.json`` and ``out/table.md``.
    The expansion runs the pipeline's own stages (:data:`pipeline.run.stages.STAGES`) in one workspace
    ``out``, each method's artifacts renamed (``faces_<patchmatch method>/``, ``proj_<row>.ply``,
    ``cloud_<row>.ply``). Stage options come from ``config_toml``'s ``[<verb>]`` tables; per-method
    choices override them. ``photos``: a photo set (:func:`photo_set`) the stages are given instead of
    photo.exr (:func:`set_inputs`)."""
    from ..config import TomlFile, resolve
    from ..run.stages import STAGE
    from ..run.runner import Job, execute_all
    from ..io.workspace import Workspace

    sample, out = Path(sample), Path(out)
    ws_kw, em_over = set_inputs(sample, photos) if photos else ({}, {})
    out.mkdir(parents=True, exist_ok=True)
    base = Workspace(sample, out, previews=False, **ws_kw)
    toml = None if config_toml is None else TomlFile(config_toml)   # read once for every job's options

    def job(verb: str, key: str, ws: Workspace, **over: Any) -> Job:
        return Job(verb, resolve(STAGE[verb].config_class(), toml, verb, {"seed": cfg.seed, **over}), ws, key)

    # the plan: one expose-match and one render-cubemaps, one patchmatch per PatchMatch method, one reproject and
    # one poisson per row, each row's artifacts renamed in the one workspace
    jobs = [job("expose-match", "expose-match", base, **em_over)]
    clouds = [base.cloud_ldr]
    chosen = [m for m in METHODS if methods is None or m[0] in methods]
    if any(pm is not None for _, pm, _ in chosen):
        jobs.append(job("render-cubemaps", "render-cubemaps", base))
    faces_done: set[str] = set()
    for row, pm, rover in chosen:
        ws = base.renamed(cloud_proj=f"proj_{row}.ply", cloud_hdr=f"cloud_{row}.ply",
                          **({"hdr_faces": f"faces_{pm}"} if pm is not None else {}))
        if pm is not None and pm not in faces_done:
            faces_done.add(pm)
            jobs.append(job("patchmatch", f"patchmatch[{pm}]", ws, method=pm))
        jobs += [job("reproject", f"reproject[{row}]", ws, **rover), job("poisson", f"poisson[{row}]", ws)]
        clouds.append(ws.cloud_hdr)
    timings: dict[str, Any] = execute_all(jobs)
    return run_evaluate(sample, clouds, out / "table.json", out / "table.md", cfg, exposure=base.exposure,
                        timings=timings, preview=preview if preview is not None else out / "table.png", photos=photos)


# ----------------------------------------------------------------------------- every photo
def photo_truths(truth_dir: str | os.PathLike) -> list[dict[str, Any]]:
    """The photos of a ground truth (scene.json "photos": name, file, truth file), the pipeline's
    ``photo.exr`` first; a truth without that list has the one photo."""
    from .. import io

    sj = io.read_json(Path(truth_dir) / "scene.json")
    return sj.get("photos") or [{"name": "photo", "file": "photo.exr", "truth": "truth/truth.npz"}]


def photo_set(truth_dir: str | os.PathLike, spec: str) -> list[dict[str, Any]]:
    """A photo set ``"bright+lights+sun"`` → the scene.json entries of its photos, in that order (``pano``: the
    panorama, scene.json "panorama", with its ``model`` and ``centre``); an unknown or repeated name is a
    ConfigError naming the known ones."""
    from .. import io
    from ..errors import ConfigError

    sj = io.read_json(Path(truth_dir) / "scene.json")
    known = {p["name"]: p for p in photo_truths(truth_dir)}
    if "panorama" in sj:
        known["pano"] = {**sj["panorama"], "name": "pano"}
    names = [n.strip() for n in spec.split("+")]
    bad = [n for n in names if n not in known]
    if bad or len(set(names)) != len(names):
        what = f"{', '.join(map(repr, bad))} is no photo of" if bad else "names a photo twice; the photos of"
        raise ConfigError(f"--photo-sets {spec!r}: {what} {Path(truth_dir) / 'scene.json'} (known: {', '.join(known)})")
    return [known[n] for n in names]


def set_inputs(sample: Path, photos: list[dict[str, Any]]) -> tuple[dict[str, Any], dict[str, Any]]:
    """What the pipeline is given for a photo set: the Workspace's photo files (the first as ``photo_file``, all of
    them as ``photo_files``) and expose-match's options for a panorama (``photo_model`` equirect, ``photo_at`` its
    centre); a set mixing models gets one model per photo (``pinhole,equirect``) and the placed photos' centres."""
    files = [sample / p["file"] for p in photos]
    ws_kw: dict[str, Any] = {"photo_file": files[0]}
    if len(files) > 1:
        ws_kw["photo_files"] = tuple(files)
    models = [p.get("model", "pinhole") for p in photos]
    em_over: dict[str, Any] = {}
    if set(models) != {"pinhole"}:
        em_over = {"photo_model": models[0] if len(set(models)) == 1 else ",".join(models),
                   "photo_at": tuple(float(x) for p, m in zip(photos, models) if m != "pinhole" for x in p["centre"])}
    return ws_kw, em_over


def photo_view(truth_dir: str | os.PathLike, photo: dict[str, Any], dst: str | os.PathLike) -> Path:
    """A folder that reads like ``truth_dir`` but whose ``photo.exr`` and ``truth/truth.npz`` are
    this photo's (symbolic links, nothing copied)."""
    src, dst = Path(truth_dir).resolve(), Path(dst)
    (dst / "truth").mkdir(parents=True, exist_ok=True)
    links = {dst / f.name: f for f in src.iterdir() if f.name not in ("truth", "photo.exr")}
    links |= {dst / "truth" / f.name: f for f in (src / "truth").iterdir() if f.name != "truth.npz"}
    links |= {dst / "photo.exr": src / photo["file"], dst / "truth" / "truth.npz": src / photo["truth"]}
    for link, target in links.items():
        if link.is_symlink() or link.exists():
            link.unlink()
        link.symlink_to(target)
    return dst


PHOTO_COLUMNS = ("alpha_rel_error", "cloud_rms_over", "cloud_rms_over_in_range", "n_over_in_range",
                 "cloud_rms_over_visible", "n_over_visible", "precise_rms_over", "precise_rms_over_in_range",
                 "precise_noise_over_in_range", "n_precise_over_in_range", "log_rms")


def photo_rows(tables: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per (photo, method) from each photo's table: α error and the cloud columns."""
    rows = []
    for name, t in tables.items():
        for r in t["rows"]:
            rows.append({"photo": name, "method": r["method"], "photo_peak": t["photo_peak"],
                         "alpha_rel_error": t["alpha"].get("relative_error"),
                         **{c: r.get(c) for c in PHOTO_COLUMNS if c != "alpha_rel_error"}})
    return rows


def format_photos_markdown(rows: list[dict[str, Any]]) -> str:
    out = ["| photo | method | photo_peak | " + " | ".join(PHOTO_COLUMNS) + " |", "|---|---|" + "---:|" * (len(PHOTO_COLUMNS) + 1)]
    for r in rows:
        vals = [r["photo_peak"]] + [r.get(c) for c in PHOTO_COLUMNS]
        out.append(f"| {r['photo']} | {r['method'].upper()} | " + " | ".join(
            "—" if v is None or (isinstance(v, float) and np.isnan(v)) else (f"{v:d}" if isinstance(v, int) else f"{v:.4g}")
            for v in vals) + " |")
    return "\n".join(out) + "\n"


def run_all_photos(sample: str | os.PathLike, out: str | os.PathLike, config_toml: str | os.PathLike | None,
                   cfg: EvaluateConfig, methods: list[str] | None = None,
                   preview: str | os.PathLike | None = None) -> dict[str, Any]:
    """:func:`run_all` with the pipeline's photo (``out/table.*``, unchanged), then — ``photos =
    "all"`` and the truth has more photos — every method again with each other photo
    (``out/photo_<name>/``; cloud columns and α, no rendering), then every method with each photo set of
    ``photo_sets`` (``out/set_<names>/``, the same columns; :func:`photo_set`, :func:`set_inputs`), and
    ``out/photos.{json,md}``: per photo (or set) and method the α error and the cloud RMS columns (Table 2 per
    photo)."""
    import dataclasses

    from .. import io

    out = Path(out)
    sets = {spec: photo_set(sample, spec) for spec in cfg.photo_sets}
    for members in sets.values():          # bad names, and sets the pipeline does not take yet: refused before any work
        set_inputs(Path(sample), members)
    table = run_all(sample, out, config_toml, cfg, methods, preview)
    photos = photo_truths(sample)
    if not sets and (cfg.photos == "default" or len(photos) < 2):
        return table
    tables = {photos[0]["name"]: table}
    cloud_cfg = dataclasses.replace(cfg, render=False)
    for ph in photos[1:] if cfg.photos == "all" else []:
        d = out / f"photo_{ph['name']}"
        log.info("photo %s (%s): every method again", ph["name"], ph["file"])
        tables[ph["name"]] = run_all(photo_view(sample, ph, d / "truth_view"), d, config_toml, cloud_cfg, methods)
    for spec, members in sets.items():
        log.info("photo set %s (%s): every method again", spec, ", ".join(p["file"] for p in members))
        tables[spec] = run_all(sample, out / f"set_{spec}", config_toml, cloud_cfg, methods, photos=members)
    rows = photo_rows(tables)
    io.write_json(out / "photos.json", {"truth": str(sample), "photos": photos, "rows": rows})
    md = format_photos_markdown(rows)
    with io.atomic_path(out / "photos.md") as tmp:
        tmp.write_text(md)
    print(md)
    table["photos"] = rows
    return table
