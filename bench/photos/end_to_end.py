"""End to end against the path tracer (issue 14): the LDR cloud and one photo → the relit object.

For every photo of a make-scene ground truth (scene.json ``photos``) the pipeline runs as a user
runs it — ``pcrelight run CONFIG --to poisson`` (every stage with its defaults plus CONFIG's tables,
on a folder whose photo.exr is that photo) — then the HDR cloud is relit (build-bsh + relight, the
reference's material: Lambert, albedo 0.8; relight's defaults otherwise, ``--method`` from CONFIG)
from each view and compared with the path-traced ``truth/full_<view>_lambert.exr`` (the object in the room, its
own shadows and bounces included; ``gather_*`` columns: against ``truth/gather_<view>_lambert.exr``, the object lit
by the room without it: what PBGI computes) by :func:`pipeline.metrics.compare_to_reference`:
per-channel mean ratio (relit ÷ e against the reference), pixel and 4×4 block relative RMS, the
reference's own noise.  Rows ``gt`` (the exact HDR cloud: PBGI's own error) and ``ldr`` (no
expansion) bracket the expansion; ``--split`` adds rows of the exact cloud with one class of the
overexposed points reset to LDR (just saturated / bright / the sun: where the light comes from); ``--oracle`` adds, per
photo, the LDR cloud whose overexposed points the photo shows are exact (what a method that invents
nothing can reach with that photo); ``--register-panoramas``: the sets' panoramas registered (centre and yaw
searched for) instead of placed at scene.json's centre; ``--unseen ldr,poisson`` adds rows with reproject's other
treatments of the overexposed points the registered photo does not see.  relit.exr is in the LDR cloud's units (e × scene radiance), so it is divided by the truth's ``e`` first.

Run: ``.venv/bin/python -m bench.photos.end_to_end [--scene data_samples] [--config configs/demo.toml]
[--out bench/_work/e2e] [--csv bench/photos/end_to_end_small.csv]`` → CSV + Markdown on stdout.
"""
from __future__ import annotations

import argparse
import csv
import subprocess
import sys
from pathlib import Path

import numpy as np


from pipeline.bsh import build_bsh
from pipeline import io
from pipeline.relight import relight  # noqa: E402
from pipeline.config import resolve  # noqa: E402
from pipeline.measure.evaluate import photo_truths, photo_view
from pipeline.metrics import compare_to_reference  # noqa: E402

PCR = str(Path(sys.executable).with_name("pcrelight"))
FIELDS = ("scene", "photo", "cloud", "alpha_rel_error", "alpha_source", "view", "material", "ratio_r", "ratio_g", "ratio_b",
          "mean_ratio", "rms", "rms_block", "ref_noise", "ref_noise_block", "rms_corrected_block", "n_blocks",
          "gather_ratio_r", "gather_ratio_g", "gather_ratio_b", "gather_mean_ratio", "gather_rms_block",
          "exact_ratio_r", "exact_ratio_g", "exact_ratio_b", "exact_rms_block")


def materials_of(scene: Path, spec: str) -> list[str]:
    """The materials to relight with: ``spec`` comma-separated, or ``all`` = every material of scene.json's
    ``references`` whose ``truth/full_view1_<material>.exr`` exists (the path-traced references)."""
    if spec != "all":
        return [m for m in spec.split(",") if m]
    sj = io.read_json(scene / "scene.json")
    names = sj.get("references", {}).get("materials") or list(sj.get("materials", {})) or ["lambert"]
    return [m for m in names if (scene / "truth" / f"full_view1_{m}.exr").exists()]


def _fresh(out: Path, *inputs: Path) -> bool:
    """``out`` exists and is newer than every input (the bench's ``--reuse``)."""
    return out.exists() and all(out.stat().st_mtime >= i.stat().st_mtime for i in inputs)


def hdr_of(ws: Path) -> Path:
    """The HDR cloud of a ``pcrelight run`` workspace: the plan's ``hdr_cloud`` (run.json; cloud_proj.ply when no
    point is left invalid after reproject and poisson is skipped), else cloud_hdr.ply."""
    rj = ws / "run.json"
    name = io.read_json(rj).get("plan", {}).get("hdr_cloud") if rj.exists() else None
    return ws / f"{name or 'cloud_hdr'}.ply"


def _have(cloud: Path) -> bool:
    """Whether an expansion's cloud exists (``--no-expand`` leaves out the rows of those that do not)."""
    if not cloud.exists():
        print(f"{cloud}: absent (--no-expand): its rows are left out", file=sys.stderr)
    return cloud.exists()


def relight_vs_reference(scene: Path, cloud: Path, work: Path, method: str, views=("view1", "view2"),
                         block: int = 4, seed: int = 0, units: str = "ldr", materials=("lambert",),
                         exact: dict | None = None, keep: dict | None = None,
                         reuse: bool = False) -> dict[tuple[str, str], dict]:
    """Relight ``cloud`` with each reference material (scene.json ``materials``: Lambert 0.8, white GGX metals,
    :func:`pipeline.run.batch.material_options`) from each view; per (view, material) :func:`compare_to_reference`
    against ``full_<view>_<material>`` (the object in the room: what a camera sees) + per-channel ratios, and the
    same against ``gather_<view>_<material>`` (the object absent from its own light: isolates the gatherer's
    error) as ``gather_*`` keys.  ``exact``: the exact cloud's images (``keep`` of the ``gt`` call), compared as
    ``exact_*`` keys: relit ÷ relight on the exact cloud (the expansion's own error, the same camera and
    material).  ``units``: "ldr" = the LDR cloud's (relit ÷ e first), "scene" = scene radiance (cloud_gt.ply).
    ``reuse``: keep bsh.npz / relit.exr that are newer than their inputs."""
    from pipeline.run.batch import material_options

    e = float(io.read_npz(scene / "truth" / "truth.npz", "pcrelight.truth/1")["e"]) if units == "ldr" else 1.0
    sj = io.read_json(scene / "scene.json")
    bsh = work / "bsh.npz"
    if not (reuse and _fresh(bsh, cloud)):
        build_bsh.run_build_bsh(cloud, bsh, resolve(build_bsh.BuildBshConfig, None, "build-bsh", {"seed": seed}))
    out = {}
    for mat in materials:
        for view in views:
            key = (view, mat)
            dst = work / (view if mat == "lambert" else f"{view}_{mat}")
            if not (reuse and _fresh(dst / "relit.exr", bsh)):
                cfg = resolve(relight.RelightConfig, None, "relight", {"seed": seed, "method": method,
                                                                       **material_options(sj, mat)})
                relight.run_relight(bsh, dst, cfg, scene_path=scene / "scene.json", view=view)
            img = io.read_image(dst / "relit.exr")
            est = img[..., :3].astype(np.float64) / e
            if keep is not None:
                keep[key] = (est, img[..., 3] > 0.5)
            for kind, pre in (("full", ""), ("gather", "gather_")):
                ref = io.read_image(scene / "truth" / f"{kind}_{view}_{mat}.exr")
                var = io.read_image(scene / "truth" / f"{kind}_{view}_{mat}_var.exr")
                m = (img[..., 3] > 0.5) & (ref[..., 3] > 0.5)
                r = compare_to_reference(est, ref[..., :3].astype(np.float64), m, var[..., :3].astype(np.float64),
                                         block=block)
                rgb = r["mean_ratio_rgb"]
                if pre:
                    out[key].update({"gather_ratio_r": rgb[0], "gather_ratio_g": rgb[1], "gather_ratio_b": rgb[2],
                                     "gather_mean_ratio": r["mean_ratio"], "gather_rms_block": r["rms_block"]})
                else:
                    out[key] = {"ratio_r": rgb[0], "ratio_g": rgb[1], "ratio_b": rgb[2], **r}
            if exact is not None and key in exact:
                ref_est, ref_m = exact[key]
                r = compare_to_reference(est, ref_est, (img[..., 3] > 0.5) & ref_m, block=block)
                rgb = r["mean_ratio_rgb"]
                out[key].update({"exact_ratio_r": rgb[0], "exact_ratio_g": rgb[1], "exact_ratio_b": rgb[2],
                                 "exact_rms_block": r["rms_block"]})
    return out


SPLIT = (("just-saturated", 0.0, 2.0), ("bright", 2.0, 1e3), ("sun", 1e3, np.inf))  # true luminance [LDR units]


def split_clouds(scene: Path, out: Path) -> list[tuple[str, Path, int]]:
    """Where the relit object's light comes from: the exact cloud in LDR units (cloud_gt × e) with one
    class of the overexposed points (by true luminance, :data:`SPLIT`) set back to its LDR colour;
    returns (row name, cloud file, points reset)."""
    from pipeline.color import luminance

    e = float(io.read_npz(scene / "truth" / "truth.npz", "pcrelight.truth/1")["e"])
    gt, ldr = io.read_cloud(scene / "cloud_gt.ply"), io.read_cloud(scene / "cloud_ldr.ply")
    hdr = gt.colors.astype(np.float64) * e
    y = luminance(hdr)
    over = io.read_npz(scene / "truth" / "truth.npz", "pcrelight.truth/1")["overexposed"].astype(bool)
    res = []
    for name, lo, hi in SPLIT:
        m = over & (y >= lo) & (y < hi)
        c = hdr.copy()
        c[m] = ldr.colors[m]
        f = out / f"gt_without_{name}.ply"
        io.write_cloud(f, io.Cloud(gt.points, gt.normals, c.astype(np.float32)))
        res.append((f"gt without {name} ({int(m.sum())} pts)", f, int(m.sum())))
    return res


def oracle_cloud(scene: Path, photo: dict | list[dict], out: Path, reuse: bool = False) -> Path:
    """What a method that invents nothing can reach with this photo (or set of photos): the LDR cloud whose
    overexposed points the photo shows (truth ``photo_visible``: in frame, facing it, first hit from its eye;
    a set: any of them) take their exact values (cloud_gt × e, LDR units); every other point keeps its LDR colour."""
    photos = photo if isinstance(photo, list) else [photo]
    trs = [io.read_npz(scene / p["truth"], "pcrelight.truth/1") for p in photos]
    tr = trs[0]
    photo = {"name": "+".join(p["name"] for p in photos)}
    gt, ldr = io.read_cloud(scene / "cloud_gt.ply"), io.read_cloud(scene / "cloud_ldr.ply")
    m = tr["overexposed"].astype(bool) & np.any([t["photo_visible"].astype(bool) for t in trs], axis=0)
    c = ldr.colors.astype(np.float64).copy()
    c[m] = gt.colors[m].astype(np.float64) * float(tr["e"])
    f = out / f"oracle_{photo['name']}.ply"
    if reuse and _fresh(f, scene / "cloud_gt.ply", scene / "cloud_ldr.ply"):
        return f
    f.parent.mkdir(parents=True, exist_ok=True)
    io.write_cloud(f, io.Cloud(ldr.points, ldr.normals, c.astype(np.float32)))
    return f


def unseen_variant(ws: Path, inputs: Path, config: str, mode: str, poisson_opts: dict | None = None,
                   tag: str = "") -> Path:
    """reproject (``--unseen mode``, the config's other reproject options) + poisson (the config's
    options and ``poisson_opts``) again in a run's workspace ``ws`` (its cube maps, PatchMatch faces
    and exposure.npz); returns the HDR cloud."""
    from pipeline.expansion import poisson, reproject

    tag = tag or f"unseen_{mode}"
    proj, hdr = ws / f"cloud_proj_{tag}.ply", ws / f"cloud_hdr_{tag}.ply"
    reproject.run_reproject(inputs / "cloud_ldr.ply", ws / "cubemaps", ws / "hdr_faces", proj,
                            resolve(reproject.ReprojectConfig, config, "reproject", {"unseen": mode}),
                            photo=inputs / "photo.exr", exposure=ws / "exposure.npz")
    poisson.run_poisson(proj, hdr, resolve(poisson.PoissonConfig, config, "poisson", poisson_opts or {}),
                        ldr=inputs / "cloud_ldr.ply")
    return hdr


def reproject_variant(ws: Path, inputs: Path, config: str, photos: list[Path], opts: dict, tag: str) -> Path:
    """reproject with ``opts`` over the config's options, then poisson, again in a run's workspace ``ws`` (its
    exposure.npz; its cube maps and PatchMatch faces where the run made them, else none — a registered set with
    ``--unseen poisson`` needs none) with every photo of the run; returns the HDR cloud."""
    from pipeline.expansion import poisson, reproject

    proj, hdr = ws / f"cloud_proj_{tag}.ply", ws / f"cloud_hdr_{tag}.ply"
    faces = (ws / "cubemaps").is_dir() and (ws / "hdr_faces").is_dir()
    reproject.run_reproject(inputs / "cloud_ldr.ply", ws / "cubemaps" if faces else None,
                            ws / "hdr_faces" if faces else None, proj,
                            resolve(reproject.ReprojectConfig, config, "reproject", opts),
                            photo=[str(p) for p in photos], exposure=ws / "exposure.npz")
    poisson.run_poisson(proj, hdr, resolve(poisson.PoissonConfig, config, "poisson", {}), ldr=inputs / "cloud_ldr.ply")
    return hdr


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="data_samples")
    ap.add_argument("--config", default="configs/demo.toml")
    ap.add_argument("--out", default="bench/_work/e2e")
    ap.add_argument("--csv", default="")
    ap.add_argument("--photos", default="", help="comma-separated photo names (default: all)")
    ap.add_argument("--sets", default="", help="comma-separated photo sets, each photo names joined by '+' (e.g. "
                    "bright+lights+sun): the pipeline run with every photo of the set (run --photo …; α against the "
                    "first's truth); with --oracle also the set's oracle (the overexposed points any of them shows exact)")
    ap.add_argument("--baselines", action=argparse.BooleanOptionalAction, default=True,
                    help="rows ldr (no expansion); the exact cloud (gt) is always relit: the exact_* columns compare "
                    "every row with it")
    ap.add_argument("--materials", default="lambert", help="comma-separated scene.json materials to relight with, "
                    "or 'all' (every material with path-traced references in truth/)")
    ap.add_argument("--expand-only", action="store_true", help="only the expansions (`pcrelight run … --to poisson` "
                    "of every photo and set asked for), no relighting: run it beside a relighting pass, then the full "
                    "command with --reuse")
    ap.add_argument("--no-expand", action="store_true", help="run no expansion: relight the workspaces' cloud_hdr.ply "
                    "as they are (rows whose workspace has none are left out, with a line on stderr)")
    ap.add_argument("--reuse", action="store_true", help="keep bsh.npz and relit.exr that are newer than their inputs "
                    "(the expansions are `pcrelight run` in the same workspaces: their stages rerun only when stale)")
    ap.add_argument("--split", action="store_true", help="also relight the exact cloud with each class of overexposed "
                    "points reset to LDR (where the light comes from)")
    ap.add_argument("--oracle", action="store_true", help="also relight, per photo, the LDR cloud whose overexposed "
                    "points the photo shows take their exact values (rows 'seen exact, rest LDR': the most a method "
                    "that invents nothing can reach with that photo)")
    ap.add_argument("--unseen", default="", help="comma-separated reproject --unseen modes to run too on each "
                    "photo's workspace (reproject + poisson again, the same faces and exposure): rows "
                    "'pipeline unseen=<mode>'")
    ap.add_argument("--rim", default="", help="comma-separated poisson --rim values to run too (rows "
                    "'pipeline rim=<rim>'; with rim=dirichlet also mode=lum: the previous defaults)")
    ap.add_argument("--no-isolated-sides", action="store_true", help="also run reproject --no-isolated-sides (+ "
                    "poisson) on each photo's and set's workspace: rows 'pipeline isolated_sides=off' (the isolated "
                    "points' reads before issue 25's lamp-room fix)")
    ap.add_argument("--register-panoramas", action="store_true", help="the sets' panoramas registered (expose-match "
                    "without --photo-at: their centre and yaw searched for) instead of placed at scene.json's centre")
    a = ap.parse_args()
    scene, out = Path(a.scene).resolve(), Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    from pipeline.config import load_toml

    method = load_toml(a.config).get("relight", {}).get("method", "hybrid")
    rows = []
    mats, exact = materials_of(scene, a.materials), {}

    def add(photo, cloud, alpha_err, source, res):
        for (view, mat), r in res.items():
            rows.append({"scene": scene.name, "photo": photo, "cloud": cloud, "alpha_rel_error": alpha_err,
                         "alpha_source": source, "view": view, "material": mat,
                         **{k: r.get(k) for k in FIELDS if k in r}})

    def rvr(cloud, work, units="ldr", keep=None):
        return relight_vs_reference(scene, cloud, work, method, units=units, materials=mats, reuse=a.reuse,
                                    exact=None if keep is not None else exact, keep=keep)

    if not a.expand_only:
        add("-", "gt", None, "-", rvr(scene / "cloud_gt.ply", out / "base_gt", units="scene", keep=exact))
    if a.baselines and not a.expand_only:
        add("-", "ldr", None, "-", rvr(scene / "cloud_ldr.ply", out / "base_ldr"))
    if a.split and not a.expand_only:
        for name, f, _ in split_clouds(scene, out):
            add("-", name, None, "-", rvr(f, out / f"split_{f.stem}"))
    wanted = {p for p in a.photos.split(",") if p}
    for ph in photo_truths(scene):
        if wanted and ph["name"] not in wanted:
            continue
        ws = out / f"photo_{ph['name']}"
        if a.oracle and not a.expand_only:
            add(ph["name"], "seen exact, rest LDR", None, "-",
                rvr(oracle_cloud(scene, ph, out, a.reuse), out / f"oracle_{ph['name']}"))
        inputs = photo_view(scene, ph, ws / "inputs")
        if not a.no_expand:
            subprocess.run([PCR, "run", a.config, "--inputs", str(inputs), "--workspace", str(ws), "--to", "poisson",
                            "--no-previews", "-q"], check=True)
        if a.expand_only or not _have(hdr_of(ws)):
            continue
        ex = io.read_npz(ws / "exposure.npz", "pcrelight.exposure/1")
        at = float(io.read_npz(scene / ph["truth"], "pcrelight.truth/1")["alpha_true"])
        src = str(ex["alpha_source"]) if "alpha_source" in ex else "histogram"
        add(ph["name"], "pipeline", float(ex["alpha"]) / at - 1, src,
            rvr(hdr_of(ws), ws / "relit"))
        if a.no_isolated_sides:
            off = ws / "cloud_hdr_iso_off.ply"
            if not (a.no_expand and off.exists()):
                off = reproject_variant(ws, inputs, a.config, [inputs / "photo.exr"], {"isolated_sides": False}, "iso_off")
            add(ph["name"], "pipeline isolated_sides=off", float(ex["alpha"]) / at - 1, src, rvr(off, ws / "relit_iso_off"))
        for mode in (m for m in a.unseen.split(",") if m):
            hdr = unseen_variant(ws, inputs, a.config, mode)
            add(ph["name"], f"pipeline unseen={mode}", float(ex["alpha"]) / at - 1, src,
                rvr(hdr, ws / f"relit_unseen_{mode}"))
        for rim in (r for r in a.rim.split(",") if r):
            opts = {"rim": rim} if rim != "dirichlet" else {"rim": rim, "mode": "lum"}
            hdr = unseen_variant(ws, inputs, a.config, "poisson", opts, tag=f"rim_{rim}")
            add(ph["name"], "pipeline " + ",".join(f"{k}={v}" for k, v in opts.items()), float(ex["alpha"]) / at - 1, src,
                rvr(hdr, ws / f"relit_rim_{rim}"))
    from pipeline.measure.evaluate import photo_set, set_inputs

    for spec in (x for x in a.sets.split(",") if x):
        phs = photo_set(scene, spec)
        ws = out / f"set_{spec.replace('+', '_')}"
        config = a.config
        _, em = set_inputs(scene, phs)
        if em:       # a panorama (alone or with pinhole photos): placed at its centre (expose-match --photo-model --photo-at)
            ws.mkdir(parents=True, exist_ok=True)         # or registered (--register-panoramas: no --photo-at)
            at = ",".join(f"{x!r}" for x in em["photo_at"])
            config = str(ws / "config.toml")
            text = Path(a.config).read_text()
            extra = f'photo_model = "{em["photo_model"]}"\n' + ("" if a.register_panoramas else f"photo_at = [{at}]\n")
            text = text.replace("[expose-match]\n", "[expose-match]\n" + extra) if "[expose-match]\n" in text \
                else text + "\n[expose-match]\n" + extra
            Path(config).write_text(text)
        if a.oracle and not a.expand_only:
            add(spec, "seen exact, rest LDR", None, "-",
                rvr(oracle_cloud(scene, phs, out, a.reuse), out / f"oracle_{spec.replace('+', '_')}"))
        inputs = photo_view(scene, phs[0], ws / "inputs")
        if not a.no_expand:
            subprocess.run([PCR, "run", config, "--inputs", str(inputs), "--workspace", str(ws), "--to", "poisson",
                            "--no-previews", "-q", *[x for p in phs for x in ("--photo", str(scene / p["file"]))]],
                           check=True)
        if a.expand_only or not _have(hdr_of(ws)):
            continue
        ex = io.read_npz(ws / "exposure.npz", "pcrelight.exposure/1")
        ref = int(np.flatnonzero(ex["photos_kept"])[0]) if "photos_kept" in ex else 0
        at = float(io.read_npz(scene / phs[ref]["truth"], "pcrelight.truth/1")["alpha_true"])
        add(spec, "pipeline", float(ex["alpha"]) / at - 1, str(ex["alpha_source"]),
            rvr(hdr_of(ws), ws / "relit"))
        if a.no_isolated_sides:
            off = ws / "cloud_hdr_iso_off.ply"
            if not (a.no_expand and off.exists()):
                off = reproject_variant(ws, inputs, config, [scene / p["file"] for p in phs], {"isolated_sides": False},
                                        "iso_off")
            add(spec, "pipeline isolated_sides=off", float(ex["alpha"]) / at - 1, str(ex["alpha_source"]),
                rvr(off, ws / "relit_iso_off"))
    if a.csv:
        with io.atomic_path(a.csv) as tmp, open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=FIELDS, extrasaction="ignore")
            w.writeheader()
            for r in rows:
                w.writerow({k: (f"{v:.4f}" if isinstance(v, float) else v) for k, v in r.items()})
    print("| photo | cloud | α err | α from | view | material | R | G | B | block RMS | ref noise (block) "
          "| ÷ exact R / G / B | ÷ exact block RMS |")
    print("|---|---|---:|---|---|---|---:|---:|---:|---:|---:|---|---:|")
    for r in rows:
        ae = "—" if r["alpha_rel_error"] is None else f"{r['alpha_rel_error']:+.1%}"
        ex = (f"{r['exact_ratio_r']:.3f} / {r['exact_ratio_g']:.3f} / {r['exact_ratio_b']:.3f} | "
              f"{r['exact_rms_block']:.3f}") if r.get("exact_ratio_r") is not None else "— | —"
        print(f"| {r['photo']} | {r['cloud']} | {ae} | {r['alpha_source']} | {r['view']} | {r['material']} | "
              f"{r['ratio_r']:.3f} | {r['ratio_g']:.3f} | {r['ratio_b']:.3f} | {r['rms_block']:.3f} | "
              f"{r['ref_noise_block']:.3f} | {ex} |", flush=True)


if __name__ == "__main__":
    main()
