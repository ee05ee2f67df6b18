"""The ordered stage registry: ``pcrelight run`` walks it, the CLI lists its verbs in its order and
``evaluate --run-all`` runs its expansion stages once per method.

Like OpenSfM's command list and COLMAP's automatic reconstructor: one list in pipeline order;
each stage declares every path it reads and writes in one workspace (the paths are defined in
:mod:`pipeline.io.workspace`), so an executor knows what to ship; a stage is skipped when its outputs
are newer than its inputs (unless ``--force``), and a stop request (SIGINT/SIGTERM) is honoured
between stages.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from ..config import StageConfig
from ..io.workspace import FaceFolder, Workspace, report_of
from ..runtime import get_logger
from ..verbs import VERB
from .own import OwnConfig

log = get_logger("run")


@dataclass
class RunConfig(OwnConfig):
    """``[run]`` table of a pipeline config (with :class:`pipeline.run.own.OwnConfig`'s: your scan, photo, placement,
    camera)."""

    inputs: str = field(default="data_samples", metadata={"help": "folder with photo.exr, cloud_ldr.ply, scene.json, object.glb"})
    workspace: str = field(default="out/demo", metadata={"help": "output folder of every stage"})
    object: str = field(default="", metadata={"help": "the object to relight: glTF/GLB, OBJ or PLY (default: <inputs>/object.glb)"})
    view: str = field(default="view1", metadata={"help": "camera view of scene.json"})
    previews: bool = field(default=True, metadata={"help": "write PNG previews"})
    plan: bool = field(default=True, metadata={
        "help": "follow the planner (pipeline/run/plan.py): skip the stages the inputs do not need (no overexposed point: "
                "no expansion; nothing invalid: no poisson) and hand relight its BRDF; false: every stage runs"})
    report: bool = field(default=True, metadata={
        "help": "end by writing <workspace>/report.html (pcrelight report: one self-contained page of the run)"})
    hdr_out: bool = field(default=False, metadata={
        "help": "also write relit.hdr and composite.hdr (Radiance RGBE) beside the EXRs ([relight] hdr_out = true: "
                "relit.hdr only)"})


def workspace_of(cfg: RunConfig) -> Workspace:
    """The workspace of a ``[run]`` table; with ``cloud`` (your scan) the inputs are the imported cloud and the
    scene.json that :mod:`pipeline.run.own` writes in the workspace, the photo and object as given."""
    root = Path(cfg.workspace)
    own = dict(cloud_file=root / "cloud_ldr.ply", scene_file=root / "scene.json") if cfg.cloud else {}
    from ..expansion.photo_set import expand_photos

    photos = expand_photos(cfg.photo) if cfg.photo else []
    return Workspace(root if cfg.cloud else cfg.inputs, cfg.workspace, Path(cfg.object) if cfg.object else None,
                     cfg.previews, cfg.view, photo_file=photos[0] if photos else None,
                     photo_files=tuple(photos) if len(photos) > 1 else (), **own)


def _face_folder(ff: FaceFolder, key: Path) -> list[Path]:
    """A face folder as declared: the folder (every face in it), its NPZ and its report."""
    return [ff.path, key, ff.report]


@dataclass(frozen=True)
class Param:
    """A path (or name) that the stage's verb takes when run by hand: a positional argument (``flag`` empty) or
    an option. ``kind``: file, dir or text; ``name``: the keyword the verb's ``by_hand`` call receives. The
    stage's other options are its config dataclass's fields (``cli.stage`` makes them)."""

    name: str
    flag: str = ""
    help: str = ""
    kind: str = "file"
    required: bool = False
    multiple: bool = False


def _arg(name: str, kind: str = "file", required: bool = True) -> Param:
    return Param(name, "", "", kind, required)


def _opt(flag: str, help: str, kind: str = "file", required: bool = False, name: str = "", multiple: bool = False) -> Param:
    return Param(name or flag.lstrip("-").replace("-", "_"), flag, help, kind, required, multiple)


@dataclass(frozen=True)
class Stage:
    """One pipeline stage: its verb, its options class, the workspace paths it reads and the ones it
    always writes (a folder means the folder and every file in it), the name of its optional preview
    ``<root>/<preview>.png`` (written when previews are on and there is something to show), how
    to call it: ``call(module, workspace, cfg, preview path or None)``, and the files it writes only when
    an option asks (``optional``: relight's relit.hdr)."""

    verb: str                         # its row in pipeline.verbs.VERBS (options class, one-line help)
    inputs: Callable[[Workspace], list[Path]]
    outputs: Callable[[Workspace], list[Path]]
    preview: str | None
    doc: str                          # the verb's help
    params: tuple[Param, ...]         # the paths the verb takes by hand, in their order on the command line
    call: Callable[..., Any]          # (module, cfg, preview, **params): the stage's one call, by hand or in a run
    paths: Callable[[Any, Workspace, StageConfig], dict[str, Any]]   # (module, ws, cfg) → call's params in a run
    optional: Callable[[Workspace], list[Path]] = lambda w: []   # files written only when an option asks

    @property
    def config(self) -> str:
        """Its options class, ``"module:Class"`` (the verb registry's)."""
        return VERB[self.verb].config

    @property
    def short(self) -> str:
        return VERB[self.verb].short

    def module(self) -> Any:
        return importlib.import_module(self.config.partition(":")[0])

    def config_class(self) -> type[StageConfig]:
        return getattr(self.module(), self.config.partition(":")[2])

    def preview_path(self, ws: Workspace) -> Path | None:
        return ws.preview(self.preview) if self.preview else None

    def all_outputs(self, ws: Workspace) -> list[Path]:
        """What the stage may write: its outputs, its preview and its optional outputs."""
        pv = self.preview_path(ws)
        return self.outputs(ws) + ([pv] if pv is not None else []) + self.optional(ws)

    def run(self, ws: Workspace, cfg: StageConfig) -> Any:
        """The stage on a workspace: its call with the workspace's paths."""
        m = self.module()
        return self.call(m, cfg, self.preview_path(ws), **self.paths(m, ws, cfg))


# The pipeline in order. `pcrelight run`, the CLI's verb order and `evaluate --run-all` are derived from it.
STAGES: list[Stage] = [
    Stage("expose-match",
          lambda w: [*w.photos, w.cloud_ldr],
          lambda w: [w.exposure, w.photo_ldr, w.exposure_report, w.exposure_fit],
          "expose_match",
          "Find α so that clamp(α·photo, 0, 1) has the cloud's luminance histogram (§4.1, Eq. 1); with several PHOTOs "
          "(or a folder of them) each is registered and α, with one scale per photo, is fitted jointly.",
          (Param("photo", "", "", "path", True, True), _arg("cloud"), _opt("--out", "output exposure.npz", required=True),
           _opt("--photo-ldr", "output photo_ldr.exr", required=True)),
          lambda m, c, pv, photo, cloud, out, photo_ldr: m.run_expose_match(list(photo), cloud, out, photo_ldr, c, preview=pv),
          lambda m, w, c: dict(photo=w.photos, cloud=w.cloud_ldr, out=w.exposure, photo_ldr=w.photo_ldr)),
    Stage("render-cubemaps",
          lambda w: [w.cloud_ldr],
          lambda w: _face_folder(w.cubemaps, w.cubemaps.cameras),
          "cubemaps",
          "Render the LDR cloud as point splats into cube maps with depth (§4.1).",
          (_arg("cloud"), _opt("--out", "output folder (faces + cameras.npz)", "dir", required=True)),
          lambda m, c, pv, cloud, out: m.run_render_cubemaps(cloud, out, c, preview=pv),
          lambda m, w, c: dict(cloud=w.cloud_ldr, out=w.cubemaps.path)),
    Stage("patchmatch",
          lambda w: [w.cubemaps.path, *w.photos, w.photo_ldr, w.exposure],
          lambda w: _face_folder(w.hdr_faces, w.hdr_faces.renderings),
          "hdr_faces",
          "Generalized PatchMatch against the photo, or an inverse tone-mapping baseline (§4.1).",
          (_arg("cubemaps", "dir"), _opt("--photo", "photo.exr (HDR); several photos, or a folder: the set expose-match "
                                          "read (default: the set exposure.npz records)", "path", multiple=True),
           _opt("--photo-ldr", "photo_ldr.exr from expose-match"), _opt("--exposure", "exposure.npz from expose-match"),
           _opt("--out", "output folder (HDR faces)", "dir", required=True)),
          lambda m, c, pv, cubemaps, photo, photo_ldr, exposure, out:
              m.run_patchmatch(cubemaps, list(photo) or None, photo_ldr, exposure, out, c, preview=pv),
          lambda m, w, c: dict(cubemaps=w.cubemaps.path, photo=w.photos, photo_ldr=w.photo_ldr, exposure=w.exposure,
                               out=w.hdr_faces.path)),
    Stage("reproject",  # photo + exposure: for --method landis-pc|banterle-pc
          lambda w: [w.cloud_ldr, *([w.cubemaps.path, w.hdr_faces.path] if w.faces else []), *w.photos, w.exposure],
          lambda w: [w.cloud_proj, report_of(w.cloud_proj)],
          "cloud_proj",
          "Give overexposed points the HDR values of the renderings that see them (§4.1).",
          (_arg("cloud"), _arg("cubemaps", "dir", False), _arg("renderings", "dir", False),
           _opt("--out", "output cloud PLY", required=True),
           _opt("--photo", "photo.exr (may be repeated, or a folder: the set expose-match read): the -pc methods' peak, and the registered photo's direct transfer (pmatch, with "
                "an exposure.npz that holds its camera; default: the photo patchmatch read, recorded in "
                "RENDERINGS/renderings.npz)", "path", multiple=True),
           _opt("--exposure", "exposure.npz: α for the -pc methods; with a registered camera (expose-match --photo-fov) "
                "the pmatch direct transfer and --unseen (default: the one patchmatch read, recorded in renderings.npz)")),
          lambda m, c, pv, cloud, cubemaps, renderings, out, photo, exposure:
              m.run_reproject(cloud, cubemaps, renderings, out, c, preview=pv, photo=list(photo) or None, exposure=exposure),
          lambda m, w, c: dict(cloud=w.cloud_ldr, **({"cubemaps": None, "renderings": None} if c.method in m.PC_METHODS or not w.faces
                                                  else {"cubemaps": w.cubemaps.path, "renderings": w.hdr_faces.path}),
                               out=w.cloud_proj, photo=w.photos, exposure=w.exposure)),
    Stage("poisson",
          lambda w: [w.cloud_proj, w.cloud_ldr],
          lambda w: [w.cloud_hdr, report_of(w.cloud_hdr)],
          "cloud_hdr",
          "Solve the Poisson equation on the kNN graph for the invalid points (§4.2).",
          (_arg("cloud"), _opt("--out", "output cloud PLY", required=True),
           _opt("--ldr", "cloud_ldr.ply: exact LDR colours for the guidance (optional)")),
          lambda m, c, pv, cloud, out, ldr: m.run_poisson(cloud, out, c, preview=pv, ldr=ldr),
          lambda m, w, c: dict(cloud=w.cloud_proj, out=w.cloud_hdr, ldr=w.cloud_ldr)),
    Stage("build-bsh",  # bsh_cloud: cloud_hdr, or what the plan says
          lambda w: [w.bsh_cloud],
          lambda w: [w.bsh, report_of(w.bsh)],
          "bsh",
          "Morton codes, Karras LBVH, spheres, normal cones, pruning, 40-byte nodes (§5.1, §5.4).",
          (_arg("cloud"), _opt("--out", "output bsh.npz", required=True)),
          lambda m, c, pv, cloud, out: m.run_build_bsh(cloud, out, c, preview=pv),
          lambda m, w, c: dict(cloud=w.bsh_cloud, out=w.bsh)),
    Stage("relight",  # relit.png is its picture; no separate preview
          lambda w: [w.bsh, w.scene, w.object, *([w.photo, w.exposure] if w.photo_view else [])],
          lambda w: [w.relit_exr, w.relit, w.relit_stats],
          None,
          "Point-based global illumination of the object: classic, mipmapped or hybrid (§5.2–5.4).",
          (_opt("--bsh", "bsh.npz from build-bsh", required=True),
           _opt("--object", "OBJ, PLY or glTF object; give it twice for two objects (each shadows the other)",
                name="object_path", multiple=True),
           _opt("--scene", "scene.json (camera views, object placement)"),
           _opt("--view", "view name in scene.json (view1, view2)", "text"),
           _opt("--photo", "photo to composite into (composite.exr/.png): its registered camera is the view"),
           _opt("--exposure", "exposure.npz from expose-match with --photo-fov: the photo's camera and α"),
           _opt("--out", "output folder", "dir", required=True)),
          lambda m, c, pv, bsh, object_path, scene, view, out, photo=None, exposure=None:
              m.run_relight(bsh, out, c, object_path=list(object_path) or None, scene_path=scene, view=view, preview=pv,
                            photo=photo, exposure=exposure),
          lambda m, w, c: dict(bsh=w.bsh, object_path=(w.object,), scene=w.scene, view=w.view, out=w.relit_dir,
                               **({"photo": w.photo, "exposure": w.exposure} if w.photo_view else {})),
          optional=lambda w: [w.relit_hdr, *([w.composite, w.composite_exr, w.composite_hdr] if w.photo_view else [])]),
]
VERBS = [s.verb for s in STAGES]
STAGE = {s.verb: s for s in STAGES}


def call_stage(verb: str, cfg: StageConfig, preview: Any = None, **paths: Any) -> Any:
    """Run the stage ``verb`` as its verb does by hand (``paths``: its :class:`Param` names): the one way a stage is
    called outside a workspace (the CLI, evaluate's renders, trade's rows)."""
    st = STAGE[verb]
    return st.call(st.module(), cfg, preview, **paths)
