"""The planner's decisions on the shipped scene (issue 27): what each one saves and what it would cost to decide
otherwise, every decision run both ways.

Base: ``configs/demo.toml`` (the registered photo, 256² cube faces, hybrid) on ``data_samples`` up to build-bsh
through :func:`pipeline.run.runner.run_pipeline` (the plan followed; every stage forced, so each is timed), then relight
from view1 at ``--size`` with the reference material (Lambert, albedo 0.8: ``pipeline.measure.trade.material_overrides``)
and the error against ``truth/full_view1_lambert.exr`` by :func:`pipeline.measure.trade.compare` (the 4×4-block RMS with the
reference's noise removed, ``err``; ``mean_ratio`` its 4×4-block mean ratio), as ``pcrelight trade`` measures it.

Rows (``way`` = planned: what the planner does; forced: the other way):

- **faces** — planned: render-cubemaps and patchmatch skipped (the photo is registered, ``--unseen poisson``),
  reproject on the photo alone; forced: ``[run] plan = false`` from render-cubemaps on the same expose-match
  outputs. ``same_bytes``: cloud_proj.ply, cloud_hdr.ply, bsh.npz and relit.exr byte-identical.
- **expansion** (needed here: overexposed points) — forced: skipped, build-bsh on cloud_ldr.ply (the error a
  wrong skip adds). And on the shipped scene dimmed to nothing overexposed (every LDR colour brighter than Y 0.85
  scaled down to it, as tests/test_plan.py does): planned skip vs ``plan = false`` (same bytes; its ``err`` is of
  the dimmed room against the shipped references, so only the difference between the two ways means anything).
- **poisson** (needed here: invalid points) — forced: skipped, build-bsh on cloud_proj.ply. And ``--unseen ldr``
  (nothing invalid): planned skip vs the copy poisson writes (seconds; cloud_proj = cloud_hdr colours).
- **glossy** — planned: the object is Lambert, no glossy work; forced: ``--brdf disney`` (metallic 0, roughness 1:
  the glossy path's BRDF evaluation and lobe micro-buffer on the same material).
- **emitters** — planned: build-bsh's ``--emitters compact`` (the default; the emitters it finds); forced: none.

Run: ``nice -n 10 python -m bench.plan.bench_plan [--out bench/_work/plan] [--csv bench/plan/plan_decisions.csv]``.
Seconds are wall seconds on this machine, in one run (compare them within the CSV, not across runs).

``--table``: the measured table the planner's relight decisions read (``configs/presets/relight_plan.csv``,
:data:`pipeline.run.plan.RELIGHT_TABLE`): for each scene (``--table-scenes``: the shipped one and the lamp room), BSH by
build-bsh's defaults on its exact ``cloud_gt.ply`` (relight's error alone, not the expansion's), each view, the
object's footprint and gap (:func:`pipeline.run.plan.object_geometry`), relight (``--config``'s [relight], Lambert 0.8)
at m = 8, 16, 24, 32 with its error (``knob`` microbuffer), and hybrid at Ω_tr = 8, 32, 128 at the view's size
and twice it (``knob`` omega_tr; CPU seconds of this process, and whether the image equals Ω_tr 32's).

``--rows WS``: the relight decisions and poisson on view2 on a pipeline workspace WS of the shipped scene (the
planned run's cloud_proj.ply, cloud_hdr.ply and bsh.npz, e.g. ``pcrelight trade``'s base expansion), rows
``microbuffer``, ``cut`` and ``poisson`` (view2) replacing those of ``--csv`` and keeping its others.
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import hashlib
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]

from pipeline import io  # noqa: E402
from pipeline.bsh.build_bsh import BuildBshConfig, run_build_bsh  # noqa: E402
from pipeline.color import luminance  # noqa: E402
from pipeline.config import load_toml, resolve  # noqa: E402
from pipeline.relight.relight import RelightConfig, run_relight  # noqa: E402
from pipeline.run.stages import STAGE
from pipeline.run.runner import run_pipeline  # noqa: E402
from pipeline.measure.trade import compare, material_overrides  # noqa: E402
from pipeline.io.workspace import Workspace  # noqa: E402

FIELDS = ("decision", "scene", "way", "planner", "stages", "seconds", "err", "mean_ratio", "d_err", "same_bytes", "note")
TABLE_M = (8, 16, 24, 32)
TABLE_OMEGA = (8.0, 32.0, 128.0)
EXPANSION = ("expose-match", "render-cubemaps", "patchmatch", "reproject", "poisson")


def md5(p: Path) -> str:
    return hashlib.md5(Path(p).read_bytes()).hexdigest()


def write_toml(path: Path, base: Path, inputs: Path, ws: Path, plan: bool = True, extra: dict[str, dict] | None = None) -> Path:
    """``base``'s tables with [run] inputs/workspace/plan set and ``extra`` tables' keys added."""
    data = load_toml(base)
    data.setdefault("run", {}).update(inputs=str(inputs), workspace=str(ws), plan=plan, previews=False, report=False)
    for k, v in (extra or {}).items():
        data.setdefault(k, {}).update(v)
    lines = [f"seed = {int(data.pop('seed', 0))}"]
    for table, kv in data.items():
        lines += ["", f"[{table}]"] + [f"{k} = {toml_value(v)}" for k, v in kv.items()]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path


def toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    return '"' + str(v).replace("\\", "\\\\").replace('"', '\\"') + '"'


def stage_seconds(rep: dict[str, Any], verbs: tuple[str, ...]) -> float:
    return sum(float(rep["stages"].get(v, {}).get("seconds", 0.0)) for v in verbs)


class Relighter:
    """relight from ``view`` with the reference material, timed, compared with truth/full_*."""

    def __init__(self, scene: Path, toml: Path, view: str, size: str, out: Path):
        self.scene, self.view, self.out = scene, view, out
        sj = io.read_json(scene / "scene.json")
        self.e = float(sj["exposure_e"]) if "exposure_e" in sj else \
            float(io.read_npz(scene / "truth" / "truth.npz", "pcrelight.truth/1")["e"])
        self.base = {**material_overrides(sj, "lambert"), "size": size}
        self.toml = toml

    def __call__(self, bsh: Path, **over: Any) -> tuple[dict[str, Any], float, str]:
        cfg = resolve(RelightConfig, self.toml, "relight", {**self.base, **over})
        t0 = time.perf_counter()
        run_relight(bsh, self.out, cfg, scene_path=self.scene / "scene.json", view=self.view)
        dt = time.perf_counter() - t0
        img = io.read_image(self.out / "relit.exr")
        return compare(self.scene, img, self.e, self.view, "lambert"), dt, md5(self.out / "relit.exr")


def build(cloud: Path, out: Path, toml: Path, **over: Any) -> float:
    cfg = resolve(BuildBshConfig, toml, "build-bsh", over)
    t0 = time.perf_counter()
    run_build_bsh(cloud, out, cfg)
    return time.perf_counter() - t0


def dim_inputs(src: Path, folder: Path, target: float = 0.85) -> int:
    """``src`` with its LDR cloud's colours brighter than luminance ``target`` scaled down to it (chromaticity
    kept), stored as 8-bit sRGB like the sample's; photo, scene and object as they are (tests/test_plan.py has its own copy)."""
    folder.mkdir(parents=True, exist_ok=True)
    c = io.read_cloud(src / "cloud_ldr.ply")
    y = luminance(c.colors, np.float64)
    k = np.where(y > target, target / np.maximum(y, 1e-12), 1.0)
    io.write_cloud(folder / "cloud_ldr.ply", io.Cloud(c.points, c.normals, (c.colors * k[:, None]).astype(np.float32)),
                   uchar_colors=True)
    for f in ("photo.exr", "scene.json", "object.glb"):
        shutil.copy(src / f, folder / f)
    return int((k < 1).sum())


def _cpu_relight(scene: Path, bsh: Path, out: Path, cfg: RelightConfig, view: str) -> tuple[dict, float, float, str]:
    """(stats, wall s, CPU s of this process, md5 of relit.exr) of one relight."""
    t0, c0 = time.perf_counter(), time.process_time()
    st = run_relight(bsh, out, cfg, scene_path=scene / "scene.json", view=view)
    return st, time.perf_counter() - t0, time.process_time() - c0, md5(out / "relit.exr")


def geometry(scene: Path, cfg: RelightConfig, view: str) -> dict[str, float]:
    """:func:`pipeline.run.plan.object_geometry` of the scene's object from ``view`` at ``cfg.size``."""
    from pipeline.relight.gbuffer import place_parts
    from pipeline.run.plan import object_geometry
    from pipeline.relight.inputs import camera_for, objects_for

    sj = io.read_json(scene / "scene.json")
    cam = camera_for(cfg, sj, scene / "scene.json", view)
    pts = np.concatenate([q["positions"] for p, w in objects_for(None, sj, scene / "scene.json")
                          for q in place_parts(io.read_object(p), w)])
    return object_geometry(pts, io.read_cloud(scene / "cloud_ldr.ply", estimate_missing_normals=False).points, cam)


def table(scenes: list[tuple[str, Path]], config: Path, out: Path, path: Path) -> None:
    """The planner's measured relight table (module docstring, ``--table``), written to ``path`` row by row
    (rows already there for the same scene/view/size/knob/value are kept, not measured again)."""
    import os

    from pipeline.run.plan import TABLE_FIELDS, read_table

    rows = read_table(path) if path.exists() else []
    have = {(r["scene"], r["view"], r["size"], r["knob"], r["value"]) for r in rows}

    def save() -> None:
        with io.atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=TABLE_FIELDS)
            w.writeheader()
            w.writerows(rows)

    warm = False
    for name, scene in scenes:
        sj = io.read_json(scene / "scene.json")
        e = 1.0                  # cloud_gt.ply holds scene radiance (the LDR cloud's units are e × it)
        bsh = out / name / "bsh.npz"
        if not bsh.exists():
            build(scene / "cloud_gt.ply", bsh, config)
        for view in sj["views"]:
            w0, h0 = (int(x) for x in sj["views"][view]["size"])
            jobs = [("microbuffer", m, f"{w0}x{h0}") for m in TABLE_M]
            jobs += [("omega_tr", om, f"{k * w0}x{k * h0}") for k in (1, 2) for om in TABLE_OMEGA]
            ref32: dict[str, str] = {}
            for knob, val, size in jobs:
                key = (name, view, size, knob, f"{val:g}")
                over = {**material_overrides(sj, "lambert"), "size": size, "method": "hybrid"}
                over[knob] = val
                cfg = resolve(RelightConfig, config, "relight", over)
                if key in have:
                    if knob == "omega_tr" and val == 32.0:
                        ref32[size] = next(r["relit_md5"] for r in rows if (r["scene"], r["view"], r["size"], r["knob"],
                                                                             r["value"]) == key)
                    continue
                if not warm:          # the first relight of a process compiles the GL shaders: untimed
                    run_relight(bsh, out / "relit", cfg, scene_path=scene / "scene.json", view=view)
                    warm = True
                geo = geometry(scene, cfg, view)
                load1 = os.getloadavg()[0]
                st, wall, cpu, h = _cpu_relight(scene, bsh, out / "relit", cfg, view)
                r: dict[str, Any] = {"err": "", "mean_ratio": ""}
                if size == f"{w0}x{h0}":
                    c = compare(scene, io.read_image(out / "relit" / "relit.exr"), e, view, "lambert")
                    r = {"err": f"{c['err']:.5f}", "mean_ratio": f"{c['mean_ratio_block']:.4f}"}
                if knob == "omega_tr" and val == 32.0:
                    ref32[size] = h
                rows.append({"scene": name, "view": view, "size": size, "footprint_px": f"{geo['footprint_px']:.1f}",
                             "gap_ratio": f"{geo['gap_ratio']:.4f}", "knob": knob, "value": f"{val:g}", **r,
                             "relight_s": f"{wall:.2f}", "relight_cpu_s": f"{cpu:.2f}", "load1": f"{load1:.1f}",
                             "nodes_per_pixel": f"{st.get('nodes_visited_per_pixel', 0.0):.1f}", "relit_md5": h})
                have.add(key)
                save()
                print(rows[-1], flush=True)
    for r in rows:               # whether each Ω_tr's image is Ω_tr 32's (the exactness the cut decision leans on)
        if r["knob"] == "omega_tr":
            same = [q["relit_md5"] for q in rows if q["knob"] == "omega_tr" and q["value"] == "32"
                    and (q["scene"], q["view"], q["size"]) == (r["scene"], r["view"], r["size"])]
            if same and same[0] != r["relit_md5"]:
                print(f"note: {r['scene']}/{r['view']}/{r['size']} Ω_tr {r['value']}: relit.exr differs from Ω_tr 32's")
    save()
    print(f"wrote {path} ({len(rows)} rows)")


def relight_rows(scene: Path, config: Path, ws: Path, out: Path, csv_path: Path, size: str) -> None:
    """The ``--rows`` mode (module docstring): for view1 and view2 the planner's microbuffer and cut decisions
    (:func:`pipeline.run.plan.make_plan` on ``ws`` with ``config``, the shipped table) planned vs forced — the configured
    value when the plan changed it, else the alternative it turned down (the next coarser m; the Ω_tr of the lowest
    measured CPU ratio after the configured one) — and poisson on view2 (planned: bsh.npz of cloud_hdr.ply; forced:
    build-bsh on cloud_proj.ply). Seconds: relight's wall seconds; its CPU seconds and the load in ``note``."""
    import os

    from pipeline.run import plan as planner
    from pipeline.run.stages import STAGES

    sj = io.read_json(scene / "scene.json")
    e = float(sj["exposure_e"])
    given = {k: set(v) for k, v in load_toml(config).items() if isinstance(v, dict)}
    rows: list[dict[str, Any]] = []
    b_hdr = ws / "bsh.npz"
    b_proj = out / "proj" / "bsh.npz"
    if not b_proj.exists():
        build(ws / "cloud_proj.ply", b_proj, config)
    mat = {**material_overrides(sj, "lambert"), "size": size}
    warm = False

    def one(bsh: Path, view: str, **over: Any) -> tuple[dict, float, float, str]:
        nonlocal warm
        cfg = resolve(RelightConfig, config, "relight", {**mat, **over})
        if not warm:
            run_relight(bsh, out / "relit", cfg, scene_path=scene / "scene.json", view=view)
            warm = True
        st, wall, cpu, h = _cpu_relight(scene, bsh, out / "relit", cfg, view)
        return compare(scene, io.read_image(out / "relit" / "relit.exr"), e, view, "lambert"), wall, cpu, h

    def add(decision: str, sc: str, way: str, planner_: str, stages: str, wall: float, cpu: float, r: dict | None,
            ref: float | None, same: str = "", note: str = "") -> None:
        err = None if r is None else float(r["err"])
        rows.append({"decision": decision, "scene": sc, "way": way, "planner": planner_, "stages": stages,
                     "seconds": f"{wall:.1f}", "err": "" if err is None else f"{err:.4f}",
                     "mean_ratio": "" if r is None else f"{float(r['mean_ratio_block']):.4f}",
                     "d_err": "" if err is None or ref is None else f"{err - ref:+.4f}", "same_bytes": same,
                     "note": f"CPU {cpu:.1f} s, load {os.getloadavg()[0]:.1f}" + (f"; {note}" if note else "")})
        print(rows[-1], flush=True)

    for view in ("view1", "view2"):
        w = Workspace(scene, ws, view=view)
        cfgs = {st.verb: resolve(st.config_class(), config, st.verb, {}) for st in STAGES}
        cfgs["relight"] = resolve(RelightConfig, config, "relight", mat)
        pl = planner.make_plan(w, cfgs, ["relight"], given=given)
        mb, cut = pl.get("microbuffer"), pl.get("cut")
        m_cfg, om_cfg = int(mb.value["configured"]), float(cut.value["configured"])
        m_pl, om_pl = int(mb.value["m"]), float(cut.value["omega_tr"])
        sc = f"shipped {view}"
        # the other way: the configured value when the plan changed it, else the alternative it turned down (the
        # next coarser m; the Ω_tr with the lowest measured CPU ratio after the configured one)
        m_alt = m_cfg if m_pl != m_cfg else max((m for m in TABLE_M if m < m_cfg), default=m_cfg)
        ratios = cut.value.get("cpu_ratio", {})
        om_alt = om_cfg if om_pl != om_cfg else float(min((k for k in ratios if float(k) != om_cfg),
                                                          key=lambda k: ratios[k], default=f"{om_cfg:g}"))
        r_p, s_p, c_p, h_p = one(b_hdr, view, microbuffer=m_pl, omega_tr=om_pl)        # the planned run
        r_m, s_m, c_m, h_m = one(b_hdr, view, microbuffer=m_alt, omega_tr=om_pl)
        add("microbuffer", sc, "planned", f"m {m_pl}", "relight", s_p, c_p, r_p, r_p["err"], "", mb.why)
        add("microbuffer", sc, "forced", f"m {m_alt}", "relight", s_m, c_m, r_m, r_p["err"],
            "relit " + ("yes" if h_m == h_p else "no"))
        r_c, s_c, c_c, h_c = one(b_hdr, view, microbuffer=m_pl, omega_tr=om_alt)
        add("cut", sc, "planned", f"Ω_tr {om_pl:g}", "relight (hybrid)", s_p, c_p, r_p, r_p["err"], "", cut.why)
        add("cut", sc, "forced", f"Ω_tr {om_alt:g}", "relight (hybrid)", s_c, c_c, r_c, r_p["err"],
            "relit " + ("yes" if h_c == h_p else "no"))
        r_f = r_p
        s_f = s_p
        if view == "view2":
            r_q, s_q, c_q, _ = one(b_proj, view, microbuffer=m_pl, omega_tr=om_pl)
            inv = planner.decide_poisson(io.read_cloud(ws / "cloud_proj.ply", estimate_missing_normals=False).valid)
            po = io.read_json(ws / "run.json")["stages"]["poisson"]
            po_s, po_c = float(po.get("seconds", 0.0)), float(po.get("cpu_s", float("nan")))
            add("poisson", sc, "planned", "run", "poisson", po_s, po_c, r_f, r_f["err"], "",
                f"{inv.value['invalid']} invalid points; poisson {po_s:.1f} s in the expansion; relight {s_f:.1f} s")
            add("poisson", sc, "forced", "", "none (build-bsh on cloud_proj.ply)", 0.0, 0.0, r_q, r_f["err"], "",
                f"relight {s_q:.1f} s (CPU {c_q:.1f} s)")
    old = []
    if csv_path.exists():
        with open(csv_path, newline="") as f:
            old = [r for r in csv.DictReader(f) if not (r["decision"] in ("microbuffer", "cut")
                                                       or (r["decision"] == "poisson" and "view2" in r["scene"]))]
    with io.atomic_path(csv_path) as tmp, open(tmp, "w", newline="") as f:
        wr = csv.DictWriter(f, fieldnames=FIELDS)
        wr.writeheader()
        wr.writerows(old + rows)
    print(f"wrote {csv_path}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default=str(ROOT / "data_samples"))
    ap.add_argument("--config", default=str(ROOT / "configs" / "demo.toml"))
    ap.add_argument("--out", default=str(ROOT / "bench" / "_work" / "plan"))
    ap.add_argument("--csv", default=str(HERE / "plan_decisions.csv"))
    ap.add_argument("--size", default="128x128")
    ap.add_argument("--view", default="view1")
    ap.add_argument("--no-dim", action="store_true", help="skip the dimmed scene's rows")
    ap.add_argument("--reuse", action="store_true",
                    help="take the pipeline runs from a previous bench's run.json in --out (their measured seconds)")
    ap.add_argument("--table", nargs="?", const=str(ROOT / "configs" / "presets" / "relight_plan.csv"), default=None,
                    help="write the planner's measured relight table (default configs/presets/relight_plan.csv) and stop")
    ap.add_argument("--table-scenes", default=f"shipped={ROOT / 'data_samples'},lamps=/tmp/w2/lamps",
                    help="name=folder,… of the make-scene folders the table measures")
    ap.add_argument("--rows", default=None, metavar="WS",
                    help="only the microbuffer, cut and poisson-view2 rows, on the planned workspace WS")
    a = ap.parse_args()
    scene, out, base = Path(a.scene).resolve(), Path(a.out).resolve(), Path(a.config).resolve()
    out.mkdir(parents=True, exist_ok=True)
    if a.table:
        scenes = [(n, Path(p).resolve()) for n, p in (x.split("=", 1) for x in a.table_scenes.split(","))]
        table(scenes, base, out / "table", Path(a.table))
        return
    if a.rows:
        relight_rows(scene, base, Path(a.rows).resolve(), out / "rows", Path(a.csv), a.size)
        return
    rows: list[dict[str, Any]] = []

    def pipeline(toml: Path, ws: Path, **kw: Any) -> dict[str, Any]:
        """run_pipeline (every stage forced, so each is timed), or with --reuse the previous bench's record."""
        if a.reuse and (ws / "run.json").exists():
            print(f"reusing {ws / 'run.json'}", flush=True)
            return io.read_json(ws / "run.json")
        return run_pipeline(str(toml), force=True, **kw)

    def row(decision: str, sc: str, way: str, planner: str, stages: str, seconds: float, r: dict | None,
            ref: float | None, same: str = "", note: str = "") -> None:
        err = None if r is None else float(r["err"])
        rows.append({"decision": decision, "scene": sc, "way": way, "planner": planner, "stages": stages,
                     "seconds": f"{seconds:.1f}", "err": "" if err is None else f"{err:.4f}",
                     "mean_ratio": "" if r is None else f"{float(r['mean_ratio_block']):.4f}",
                     "d_err": "" if err is None or ref is None else f"{err - ref:+.4f}", "same_bytes": same, "note": note})
        print(rows[-1], flush=True)

    # ---------------------------------------------------------------- the planned run (the base)
    ws_p = out / "plan"
    t_p = write_toml(out / "plan.toml", base, scene, ws_p)
    rep_p = pipeline(t_p, ws_p, to_stage="build-bsh")
    skipped = [v for v, e in rep_p["stages"].items() if e.get("skipped")]
    print("planned run: skipped", skipped, {v: e.get("seconds") for v, e in rep_p["stages"].items()}, flush=True)
    w_p = Workspace(scene, ws_p, hdr_cloud=rep_p["plan"]["hdr_cloud"])
    relit = Relighter(scene, t_p, a.view, a.size, out / "relit")
    relit(w_p.bsh)          # warm-up, untimed: the first relight of a process compiles the GL shaders
    r_base, s_rel, h_base = relit(w_p.bsh)

    # ---------------------------------------------------------------- faces: run them on the same exposure
    ws_f = out / "faces"
    wf = Workspace(scene, ws_f)
    ws_f.mkdir(parents=True, exist_ok=True)
    t_f = write_toml(out / "faces.toml", base, scene, ws_f, plan=False)
    if not (a.reuse and (ws_f / "run.json").exists()):
        for src, dst in zip(STAGE["expose-match"].outputs(w_p), STAGE["expose-match"].outputs(wf)):
            shutil.copy2(src, dst)
    rep_f = pipeline(t_f, ws_f, from_stage="render-cubemaps", to_stage="build-bsh")
    same_proj = md5(wf.cloud_proj) == md5(w_p.cloud_proj)
    same_hdr = md5(wf.cloud_hdr) == md5(w_p.cloud_hdr)
    same_bsh = md5(wf.bsh) == md5(w_p.bsh)
    r_f, _, h_f = (r_base, 0.0, h_base) if same_bsh else relit(wf.bsh)
    fv = ("render-cubemaps", "patchmatch", "reproject")
    row("faces", "shipped", "planned", "skip", "render-cubemaps, patchmatch (reproject: photo alone)",
        stage_seconds(rep_p, fv), r_base, r_base["err"], "", "reproject on the registered photo alone")
    row("faces", "shipped", "forced", "", "render-cubemaps, patchmatch, reproject", stage_seconds(rep_f, fv), r_f,
        r_base["err"], f"cloud_proj {'yes' if same_proj else 'NO'}, cloud_hdr {'yes' if same_hdr else 'NO'}, bsh {'yes' if same_bsh else 'NO'}, "
        f"relit {'yes' if h_f == h_base else 'NO'}", "[run] plan = false from render-cubemaps, same exposure.npz")

    # ---------------------------------------------------------------- expansion (needed here): forced skip
    exp_s = stage_seconds(rep_p, EXPANSION)
    b_ldr = out / "ldr" / "bsh.npz"
    s_b = build(w_p.cloud_ldr, b_ldr, t_p)
    r_ldr, _, _ = relit(b_ldr)
    n_over = next(d for d in rep_p["plan"]["decisions"] if d["name"] == "expansion")["value"]["overexposed"]
    row("expansion", "shipped", "planned", "run", "expose-match … poisson", exp_s, r_base, r_base["err"], "",
        f"{n_over} overexposed points")
    row("expansion", "shipped", "forced", "", "none (build-bsh on cloud_ldr.ply)", 0.0, r_ldr, r_base["err"], "",
        f"build-bsh {s_b:.1f} s")

    # ---------------------------------------------------------------- poisson (needed here): forced skip
    b_proj = out / "proj" / "bsh.npz"
    build(w_p.cloud_proj, b_proj, t_p)
    r_proj, _, _ = relit(b_proj)
    inv = next(d for d in rep_p["plan"]["decisions"] if d["name"] == "poisson")["value"]
    row("poisson", "shipped", "planned", "run", "poisson", stage_seconds(rep_p, ("poisson",)), r_base, r_base["err"], "",
        f"{inv['invalid']} invalid points")
    row("poisson", "shipped", "forced", "", "none (build-bsh on cloud_proj.ply)", 0.0, r_proj, r_base["err"])

    # poisson with nothing invalid (--unseen ldr): the copy it would write
    from pipeline.expansion.poisson import PoissonConfig, run_poisson
    from pipeline.expansion.reproject import ReprojectConfig, run_reproject

    ul = out / "unseen_ldr"
    ul.mkdir(parents=True, exist_ok=True)
    rcfg = resolve(ReprojectConfig, t_p, "reproject", {"unseen": "ldr"})
    t0 = time.perf_counter()
    run_reproject(w_p.cloud_ldr, None, None, ul / "cloud_proj.ply", rcfg, photo=w_p.photo, exposure=w_p.exposure)
    s_rp = time.perf_counter() - t0
    t0 = time.perf_counter()
    run_poisson(ul / "cloud_proj.ply", ul / "cloud_hdr.ply", resolve(PoissonConfig, t_p, "poisson", {}), ldr=w_p.cloud_ldr)
    s_po = time.perf_counter() - t0
    a_, b_ = io.read_cloud(ul / "cloud_proj.ply"), io.read_cloud(ul / "cloud_hdr.ply")
    same_ul = np.array_equal(a_.colors, b_.colors) and np.array_equal(a_.valid, b_.valid)
    row("poisson", "shipped --unseen ldr", "planned", "skip", "poisson", 0.0, None, None, "",
        f"0 invalid; reproject {s_rp:.1f} s")
    row("poisson", "shipped --unseen ldr", "forced", "", "poisson (a copy)", s_po, None, None,
        f"colours and valid {'yes' if same_ul else 'NO'}")

    # ---------------------------------------------------------------- glossy
    r_g, s_g, _ = relit(w_p.bsh, brdf="disney", metallic=0.0, roughness=1.0)
    row("glossy", "shipped", "planned", "skip", "relight (lambert)", s_rel, r_base, r_base["err"])
    row("glossy", "shipped", "forced", "", "relight (--brdf disney, metallic 0, roughness 1)", s_g, r_g, r_base["err"])

    # ---------------------------------------------------------------- emitters
    bj = io.read_json(w_p.bsh.with_suffix(".json"))
    b_off = out / "emitters_off" / "bsh.npz"
    s_off = build(w_p.bsh_cloud, b_off, t_p, emitters="none")
    r_off, s_rel_off, _ = relit(b_off)
    row("emitters", "shipped", "planned", f"{bj['counts'].get('n_emitters', 0)} emitters",
        "build-bsh + relight", stage_seconds(rep_p, ("build-bsh",)) + s_rel, r_base, r_base["err"])
    row("emitters", "shipped", "forced", "none", "build-bsh + relight", s_off + s_rel_off, r_off, r_base["err"])

    # ---------------------------------------------------------------- expansion on a scene with nothing overexposed
    if not a.no_dim:
        dim = out / "dim_in"
        n_dim = dim_inputs(scene, dim)
        reps = {}
        for name, plan in (("dim_plan", True), ("dim_full", False)):
            t = write_toml(out / f"{name}.toml", base, dim, out / name, plan=plan)
            reps[name] = pipeline(t, out / name, to_stage="build-bsh")
        wp, wf2 = (Workspace(dim, out / n, hdr_cloud=reps[n]["plan"]["hdr_cloud"]) for n in ("dim_plan", "dim_full"))
        rd = Relighter(scene, t_p, a.view, a.size, out / "relit_dim")
        r_dp, _, h_dp = rd(wp.bsh)
        same = md5(wp.bsh) == md5(wf2.bsh)
        r_df, _, h_df = (r_dp, 0.0, h_dp) if same else rd(wf2.bsh)
        row("expansion", "shipped dimmed (0 overexposed)", "planned", "skip", "none (build-bsh on cloud_ldr.ply)",
            stage_seconds(reps["dim_plan"], EXPANSION), r_dp, r_dp["err"], "", f"{n_dim} points dimmed to Y 0.85")
        row("expansion", "shipped dimmed (0 overexposed)", "forced", "", "expose-match … poisson",
            stage_seconds(reps["dim_full"], EXPANSION), r_df, r_dp["err"],
            f"bsh {'yes' if same else 'NO'}, relit {'yes' if h_df == h_dp else 'NO'}", "[run] plan = false")

    with io.atomic_path(Path(a.csv)) as tmp:
        with open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=FIELDS)
            w.writeheader()
            w.writerows(rows)
    print(f"wrote {a.csv}")
    print("| decision | scene | way | planner | stages | s | err | Δerr | same bytes | note |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print("| " + " | ".join(str(r[k]) for k in ("decision", "scene", "way", "planner", "stages", "seconds", "err",
                                                    "d_err", "same_bytes", "note")) + " |")


if __name__ == "__main__":
    main()
