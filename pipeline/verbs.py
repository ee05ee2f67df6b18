"""The verb registry: every ``pcrelight`` verb, declared once, in the order ``pcrelight --help`` lists them.

Pure data (no imports of the stages), so the lowest layer may read it: ``cli.py`` builds each verb from its row,
:func:`pipeline.config.check_file` takes the tables a config file may hold from it, ``pcrelight --help`` and
README's stage table are written from it, and :mod:`pipeline.run.stages` declares the stages ``run`` walks by
these names (``kind == "stage"``, in this order).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Verb:
    """One verb. ``config``: its options dataclass as ``"module:Class"`` (None: options of its own, no TOML
    table); ``kind``: ``input`` (makes a run's inputs), ``stage`` (a stage ``pcrelight run`` walks), ``measure``
    or ``tool``; ``short``: the one-line help; ``summary``: what it reads and writes, for the verb list;
    ``paper``: the section of paper 000 it implements."""

    name: str
    config: str | None
    kind: str
    short: str
    summary: str
    usage: tuple[str, ...]
    reads: str
    writes: str
    paper: str

    @property
    def table(self) -> str | None:
        """The TOML table of its options (``[<name>]``), or None for a verb without a config class."""
        return self.name if self.config is not None else None


VERBS: tuple[Verb, ...] = (
    Verb("make-scene", "pipeline.scene.make_scene:MakeSceneConfig", "input",
         short="build the Mitsuba 3 ground-truth scene",
         summary="Sponza-style ground truth (Mitsuba 3): clouds, photo, references",
         usage=("`pcrelight make-scene --preset tiny\\|small\\|full --out DIR [--only panorama]`",),
         reads="`configs/scene/*.toml`",
         writes="scene.json, scene.xml, meshes/, cloud_gt.ply, cloud_ldr.ply, photo*.exr, pano.exr, object.*, truth/",
         paper="ground truth (Mitsuba 3)"),
    Verb("import", "pipeline.ingest.import_scan:ImportConfig", "input",
         short="a scan → the pipeline's cloud (metres, +Y up)",
         summary="a scan (PLY, PCD, XYZ/PTS, E57, LAS/LAZ) → cloud.ply: metres, +Y up",
         usage=("`pcrelight import SCAN --out cloud.ply [--units auto\\|m\\|cm\\|mm] [--up auto\\|y\\|z…] [--max-points N]`",),
         reads="a scan: PLY, PCD, XYZ/XYZRGB/PTS, E57, LAS/LAZ",
         writes="a cloud PLY (metres, +Y up, linear colours, normals) + `<stem>.json`",
         paper="—"),
    Verb("merge-brackets", "pipeline.ingest.merge_brackets:MergeBracketsConfig", "input",
         short="a bracket set of LDR photos → one HDR photo",
         summary="LDR photos at several exposure times → one HDR photo.exr (OpenCV)",
         usage=("`pcrelight merge-brackets IMG… --out photo.exr [--times T1,T2,…] [--method debevec\\|robertson]`",),
         reads="JPEG/PNG/TIFF shots of one view at several exposure times (EXIF `ExposureTime`, or `--times` [s])",
         writes="an HDR photo (EXR, relative radiance) + `<stem>.json` (times, response curve)",
         paper="— (OpenCV's Debevec & Malik / Robertson merge; its accuracy: [docs/expansion.md](docs/expansion.md))"),
    Verb("expose-match", "pipeline.expansion.expose_match:ExposeMatchConfig", "stage",
         short="match the photo's exposure to the cloud (Eq. 1)",
         summary="photo.exr + cloud_ldr.ply → exposure.npz, photo_ldr.exr",
         usage=("`pcrelight expose-match PHOTO… CLOUD --out exposure.npz --photo-ldr photo_ldr.exr [--photo-fov DEG] [--photo-model equirect --photo-at X,Y,Z]`",),
         reads="photo.exr (or several, or a folder), cloud_ldr.ply",
         writes="exposure.npz, photo_ldr.exr",
         paper="§4.1, Eq. 1; with `--photo-fov` the photo registered to the cloud; several photos: below"),
    Verb("render-cubemaps", "pipeline.expansion.render_cubemaps:RenderCubemapsConfig", "stage",
         short="render cube maps of the LDR cloud",
         summary="cloud_ldr.ply → cube-map faces + cameras.npz",
         usage=("`pcrelight render-cubemaps CLOUD --out DIR`",),
         reads="cloud_ldr.ply",
         writes="DIR/cameras.npz, DIR/face_XXX.exr (R,G,B,A,Z)",
         paper="§4.1"),
    Verb("patchmatch", "pipeline.expansion.patchmatch:PatchmatchConfig", "stage",
         short="expand the cube-map faces to HDR",
         summary="faces + photo → HDR faces (or an ITMO baseline)",
         usage=("`pcrelight patchmatch DIR --photo P --photo-ldr P_LDR --exposure E --out OUT [--method pmatch\\|landis\\|banterle\\|rhee]`",),
         reads="cube maps, photo",
         writes="OUT/face_XXX.exr (R,G,B,Q), OUT/renderings.npz",
         paper="§4.1"),
    Verb("reproject", "pipeline.expansion.reproject:ReprojectConfig", "stage",
         short="project HDR faces back onto the points",
         summary="HDR faces → cloud with valid/quality/source",
         usage=("`pcrelight reproject CLOUD DIR OUT --out cloud_proj.ply [--transfer rgb\\|lum] [--photo P --exposure E]`",),
         reads="cloud, cube maps, HDR faces (+ the photo and exposure.npz patchmatch read, recorded in OUT/renderings.npz; `--photo/--exposure` override)",
         writes="cloud with `valid`, `quality`, `source`",
         paper="§4.1"),
    Verb("poisson", "pipeline.expansion.poisson:PoissonConfig", "stage",
         short="fill points without HDR colour (Eq. 2–3)",
         summary="fill invalid points by the Poisson equation",
         usage=("`pcrelight poisson cloud_proj.ply --ldr CLOUD --out cloud_hdr.ply [--rim free\\|dirichlet]`",),
         reads="cloud with `valid` (+ the LDR cloud: its exact colours guide the fill, as `run` does)",
         writes="HDR cloud",
         paper="§4.2, Eq. 2–3 (`free` rim: not in the paper)"),
    Verb("build-bsh", "pipeline.bsh.build_bsh:BuildBshConfig", "stage",
         short="build the bounding sphere hierarchy",
         summary="cloud → bounding sphere hierarchy bsh.npz",
         usage=("`pcrelight build-bsh cloud_hdr.ply --out bsh.npz`",),
         reads="HDR cloud",
         writes="bsh.npz",
         paper="§5.1, §5.4"),
    Verb("relight", "pipeline.relight.relight:RelightConfig", "stage",
         short="render the object relit by the cloud (PBGI)",
         summary="object + BSH → relit.exr / relit.png / stats.json",
         usage=("`pcrelight relight --bsh B --object O [--object O2] --scene S --view view1 [--method classic\\|mipmapped\\|hybrid\\|envmap\\|importance] [--preset fast\\|balanced\\|exact] [--bounces -1\\|0…4] [--surfels N\\|-1] [--adaptive ε] [--hdr-out] [--photo P --exposure E \\| --composite] --out DIR`",),
         reads="BSH, object(s); `--photo`: the photo and exposure.npz holding its registered camera",
         writes="relit.exr, relit.png, stats.json (`--hdr-out`: relit.hdr); `--photo`/`--composite`: composite.exr (layers), composite.png",
         paper="§5.2–5.4; the object in its own micro-buffers (Christensen 2008; `--surfels -1`: the paper's model)"),
    Verb("evaluate", "pipeline.measure.evaluate:EvaluateConfig", "measure",
         short="Table 2 metrics against the ground truth",
         summary="Table 2 metrics against the ground truth",
         usage=("`pcrelight evaluate --truth DIR CLOUD… --json T.json --md T.md [--photo-sets bright+lights+sun]`",),
         reads="clouds, ground truth (scored against the photo set the clouds were expanded with: its brightest photo's peak, the points any of its photos sees)",
         writes="Table 2",
         paper="§6"),
    Verb("trade", "pipeline.measure.trade:TradeConfig", "measure",
         short="sweep the knobs that cost time: error vs time, the presets",
         summary="error vs time of the costly knobs on a scene; the presets",
         usage=("`pcrelight trade --scene DIR [--config C] [--budget-min M] [--out O]`",),
         reads="a make-scene folder (path-traced `truth/full_*`)",
         writes="O/trade.csv, trade.png (the front), trade.json, fast/balanced/exact.toml",
         paper="—"),
    Verb("run", "pipeline.run.stages:RunConfig", "tool",
         short="run the whole pipeline from one config",
         summary="every stage in order on one workspace (or your scan, photo and object)",
         usage=("`pcrelight run configs/demo.toml [--from V] [--to V] [--force] [--seed N] [--workspace DIR]`", "`pcrelight run --cloud SCAN --photo PHOTO --object ASSET --out DIR`",),
         reads="a config (top-level `seed`, `[run]`, one table per verb; the command line wins) ; your scan, HDR photo (EXR, .hdr), object (glTF, OBJ, PLY); a config optional",
         writes="every stage's outputs in one workspace, run.json, composite.png ; the same, with the imported cloud, scene.json (placement, camera)",
         paper="— ; \"Relight your own object in your own room\""),
    Verb("report", None, "tool",
         short="a run's workspace → one self-contained HTML page",
         summary="a run's workspace → one self-contained HTML page",
         usage=("`pcrelight report WORKSPACE [--out report.html] [--inputs DIR] [--table table.json] [--trade trade.csv]`",),
         reads="a run's workspace",
         writes="one self-contained HTML page of the run",
         paper="—"),
    Verb("batch", None, "tool",
         short="many jobs against one room (objects × views × materials × presets)",
         summary="JOBS.toml → one relight a job, the room built once; summary.csv, contact sheet",
         usage=("`pcrelight batch JOBS.toml [--executor local\\|ray] [--address ADDR] [--workers N]`",),
         reads="a job list (objects × views × materials × presets, or a turntable) and a pipeline config",
         writes="the shared BSH once, `<out>/<job>/` per job, summary.csv, contact_sheet.png, batch.json",
         paper="—"),
    Verb("info", None, "tool",
         short="versions and the GL context",
         summary="versions, the GL context and whether GS + TF work",
         usage=("`pcrelight info`",),
         reads="—",
         writes="versions, GL vendor/renderer/version, GS + transform feedback check, Mitsuba/LLVM",
         paper="—"),
)

VERB = {v.name: v for v in VERBS}
STAGE_VERBS: tuple[str, ...] = tuple(v.name for v in VERBS if v.kind == "stage")
TABLES: frozenset[str] = frozenset(v.table for v in VERBS if v.table is not None)


def verb_list(indent: str = "  ") -> list[str]:
    """The verb list of ``pcrelight --help``: one line a verb, ``name  summary  (paper section)``."""
    w = max(len(v.name) for v in VERBS) + 2
    return [f"{indent}{v.name:<{w}}{v.summary}" for v in VERBS]


def stage_table() -> list[str]:
    """README's stage table (markdown): every verb, its kind and what it reads and writes."""
    rows = ["| command | reads | writes | paper |", "|---|---|---|---|"]
    rows += [f"| {'<br>'.join(v.usage)} | {v.reads} | {v.writes} | {v.paper} |" for v in VERBS]
    return rows


def write_readme_table(readme: str = "README.md") -> bool:
    """Rewrite README's stage table (between ``<!-- stages:begin -->`` and ``<!-- stages:end -->``) from
    :data:`VERBS`; True if it changed. ``python -m pipeline.verbs`` runs it."""
    from pathlib import Path

    p = Path(readme)
    text = p.read_text()
    a, b = "<!-- stages:begin -->\n", "<!-- stages:end -->"
    i, j = text.index(a) + len(a), text.index(b)
    new = text[:i] + "\n".join(stage_table()) + "\n" + text[j:]
    if new != text:
        p.write_text(new)
    return new != text


if __name__ == "__main__":
    print("README.md's stage table " + ("rewritten" if write_readme_table() else "already the registry's"))
