"""The ordered stage registry: ``pcrelight run`` walks it, the CLI lists its verbs in its order and
``evaluate --run-all`` runs its expansion stages once per method.

Like OpenSfM's command list and COLMAP's automatic reconstructor: one list in pipeline order;
each stage declares every path it reads and writes in one workspace (the paths are defined in
:mod:`pipeline.workspace`), so an executor knows what to ship; a stage is skipped when its outputs
are newer than its inputs (unless ``--force``), and a stop request (SIGINT/SIGTERM) is honoured
between stages.
"""

from __future__ import annotations

import importlib
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from .config import StageConfig, load_toml, resolve
from .errors import ConfigError, InputError
from .runtime import get_logger, progress
from .workspace import FaceFolder, Workspace, report_of

log = get_logger("run")


@dataclass
class RunConfig(StageConfig):
    """``[run]`` table of a pipeline config."""

    inputs: str = field(default="data_samples", metadata={"help": "folder with photo.exr, cloud_ldr.ply, scene.json, object.glb"})
    workspace: str = field(default="out/demo", metadata={"help": "output folder of every stage"})
    object: str = field(default="", metadata={"help": "object file (default: <inputs>/object.glb)"})
    view: str = field(default="view1", metadata={"help": "camera view of scene.json"})
    previews: bool = field(default=True, metadata={"help": "write PNG previews"})


def workspace_of(cfg: RunConfig) -> Workspace:
    """The workspace of a ``[run]`` table."""
    return Workspace(cfg.inputs, cfg.workspace, Path(cfg.object) if cfg.object else None, cfg.previews, cfg.view)


def _face_folder(ff: FaceFolder, key: Path) -> list[Path]:
    """A face folder as declared: the folder (every face in it), its NPZ and its report."""
    return [ff.path, key, ff.report]


@dataclass(frozen=True)
class Stage:
    """One pipeline stage: its verb, its options class, the workspace paths it reads and the ones it
    always writes (a folder means the folder and every file in it), the name of its optional preview
    ``<root>/<preview>.png`` (written when previews are on and there is something to show), and how
    to call it: ``call(module, workspace, cfg, preview path or None)``."""

    verb: str
    config: str                       # "module:Class"
    inputs: Callable[[Workspace], list[Path]]
    outputs: Callable[[Workspace], list[Path]]
    call: Callable[[Any, Workspace, StageConfig, Path | None], Any]
    preview: str | None = None

    def config_class(self) -> type[StageConfig]:
        mod, _, cls = self.config.partition(":")
        return getattr(importlib.import_module(mod), cls)

    def preview_path(self, ws: Workspace) -> Path | None:
        return ws.preview(self.preview) if self.preview else None

    def all_outputs(self, ws: Workspace) -> list[Path]:
        """What the stage may write: its outputs and its preview."""
        pv = self.preview_path(ws)
        return self.outputs(ws) + ([pv] if pv is not None else [])

    def run(self, ws: Workspace, cfg: StageConfig) -> Any:
        return self.call(importlib.import_module(self.config.partition(":")[0]), ws, cfg, self.preview_path(ws))


# The pipeline in order. `pcrelight run`, the CLI's verb order and `evaluate --run-all` are derived from it.
STAGES: list[Stage] = [
    Stage("expose-match", "pipeline.expose_match:ExposeMatchConfig",
          lambda w: [w.photo, w.cloud_ldr],
          lambda w: [w.exposure, w.photo_ldr, w.exposure_report, w.exposure_fit],
          lambda m, w, c, pv: m.run_expose_match(w.photo, w.cloud_ldr, w.exposure, w.photo_ldr, c, preview=pv),
          "expose_match"),
    Stage("render-cubemaps", "pipeline.render_cubemaps:RenderCubemapsConfig",
          lambda w: [w.cloud_ldr],
          lambda w: _face_folder(w.cubemaps, w.cubemaps.cameras),
          lambda m, w, c, pv: m.run_render_cubemaps(w.cloud_ldr, w.cubemaps.path, c, preview=pv),
          "cubemaps"),
    Stage("patchmatch", "pipeline.patchmatch:PatchmatchConfig",
          lambda w: [w.cubemaps.path, w.photo, w.photo_ldr, w.exposure],
          lambda w: _face_folder(w.hdr_faces, w.hdr_faces.renderings),
          lambda m, w, c, pv: m.run_patchmatch(w.cubemaps.path, w.photo, w.photo_ldr, w.exposure, w.hdr_faces.path,
                                               c, preview=pv),
          "hdr_faces"),
    Stage("reproject", "pipeline.reproject:ReprojectConfig",  # photo + exposure: for --method landis-pc|banterle-pc
          lambda w: [w.cloud_ldr, w.cubemaps.path, w.hdr_faces.path, w.photo, w.exposure],
          lambda w: [w.cloud_proj, report_of(w.cloud_proj)],
          lambda m, w, c, pv: m.run_reproject(w.cloud_ldr, *((None, None) if c.method in m.PC_METHODS else
                                                              (w.cubemaps.path, w.hdr_faces.path)),
                                              w.cloud_proj, c, preview=pv, photo=w.photo, exposure=w.exposure),
          "cloud_proj"),
    Stage("poisson", "pipeline.poisson:PoissonConfig",
          lambda w: [w.cloud_proj, w.cloud_ldr],
          lambda w: [w.cloud_hdr, report_of(w.cloud_hdr)],
          lambda m, w, c, pv: m.run_poisson(w.cloud_proj, w.cloud_hdr, c, preview=pv, ldr=w.cloud_ldr),
          "cloud_hdr"),
    Stage("build-bsh", "pipeline.build_bsh:BuildBshConfig",
          lambda w: [w.cloud_hdr],
          lambda w: [w.bsh, report_of(w.bsh)],
          lambda m, w, c, pv: m.run_build_bsh(w.cloud_hdr, w.bsh, c, preview=pv),
          "bsh"),
    Stage("relight", "pipeline.relight:RelightConfig",  # relit.png is its picture; no separate preview
          lambda w: [w.bsh, w.scene, w.object],
          lambda w: [w.relit_exr, w.relit, w.relit_stats],
          lambda m, w, c, pv: m.run_relight(w.bsh, w.relit_dir, c, object_path=w.object, scene_path=w.scene,
                                            view=w.view)),
]
VERBS = [s.verb for s in STAGES]
STAGE = {s.verb: s for s in STAGES}


def files_of(paths: list[Path]) -> list[Path]:
    """The files a declaration names: a file itself, every file under a folder (none if absent)."""
    out: list[Path] = []
    for p in paths:
        if p.is_dir():
            out += sorted(f for f in p.rglob("*") if f.is_file() and not f.name.startswith("."))
        elif p.exists():
            out.append(p)
    return out


def _up_to_date(ins: list[Path], outs: list[Path]) -> bool:
    if not all(o.exists() for o in outs):
        return False
    newest_in = max((p.stat().st_mtime for p in files_of(ins)), default=0.0)
    return min(o.stat().st_mtime for o in files_of(outs)) >= newest_in


def run_pipeline(config_toml: str, from_stage: str | None = None, to_stage: str | None = None,
                 force: bool = False, seed: int | None = None,
                 overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """Run the stages from ``from_stage`` to ``to_stage`` with the options of ``config_toml``
    (its ``[run]`` table and one table per verb); writes ``<workspace>/run.json`` with the
    resolved config of every stage, what ran, what was skipped and the timings.

    Seeds: the file's top-level ``seed`` < a ``[verb]`` table's ``seed`` < ``seed`` (``--seed``;
    None = not given). ``overrides``: ``[run]`` options given on the command line (None = not given).
    """
    from . import io

    data = load_toml(config_toml)
    unknown = sorted(k for k, v in data.items() if isinstance(v, dict) and k not in set(VERBS) | {"run"})
    if unknown:
        raise ConfigError(f"{config_toml}: unknown table [{unknown[0]}] (known: run, {', '.join(VERBS)})")
    if isinstance(data.get("run"), dict) and "seed" in data["run"]:
        raise ConfigError(f"{config_toml}: put 'seed' at the top of the file (it applies to every stage), not in [run]")
    rcfg = resolve(RunConfig, config_toml, "run", {**(overrides or {}), "seed": seed})
    for name in (from_stage, to_stage):
        if name is not None and name not in VERBS:
            raise ConfigError(f"--from/--to must be one of {', '.join(VERBS)}, got {name!r}")
    i0 = VERBS.index(from_stage) if from_stage else 0
    i1 = VERBS.index(to_stage) if to_stage else len(VERBS) - 1
    ws = workspace_of(rcfg)
    ws.root.mkdir(parents=True, exist_ok=True)
    for p in (ws.photo, ws.cloud_ldr):
        if i0 == 0 and not p.exists():
            raise InputError(p, "no such file (the [run] inputs folder must hold photo.exr and cloud_ldr.ply)")
    report: dict[str, Any] = {"config": str(config_toml), "run": rcfg.as_dict(), "stages": {}}
    for st in progress(STAGES[i0:i1 + 1], total=i1 + 1 - i0, desc="pipeline"):
        cfg = resolve(st.config_class(), config_toml, st.verb, {"seed": seed})
        entry: dict[str, Any] = {"config": cfg.as_dict()}
        if not force and _up_to_date(st.inputs(ws), st.outputs(ws)):
            log.info("%s: outputs up to date, skipped (use --force to rerun)", st.verb)
            entry["skipped"] = True
        else:
            log.info("%s: running", st.verb)
            t0 = time.perf_counter()
            st.run(ws, cfg)
            entry["seconds"] = round(time.perf_counter() - t0, 3)
            log.info("%s: done in %.1f s", st.verb, entry["seconds"])
        report["stages"][st.verb] = entry
        report.setdefault("order", []).append(st.verb)
        io.write_json(ws.run_report, report)
    log.info("pipeline finished: %s", ws.relit if i1 == len(VERBS) - 1 else ws.root)
    return report
