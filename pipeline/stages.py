"""The ordered stage registry that ``pcrelight run`` walks, and the workspace layout.

Like OpenSfM's command list and COLMAP's automatic reconstructor: one list in pipeline order;
each stage declares its inputs and outputs inside one workspace folder (paths defined only
here), is skipped when its outputs are newer than its inputs (unless ``--force``), and a
stop request (SIGINT/SIGTERM) is honoured between stages.
"""

from __future__ import annotations

import importlib
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from .config import StageConfig, load_toml, resolve
from .errors import ConfigError, InputError, NotImplementedStage
from .runtime import get_logger, progress

log = get_logger("run")


@dataclass
class RunConfig(StageConfig):
    """``[run]`` table of a pipeline config."""

    inputs: str = field(default="data_samples", metadata={"help": "folder with photo.exr, cloud_ldr.ply, scene.json, object.glb"})
    workspace: str = field(default="out/demo", metadata={"help": "output folder of every stage"})
    object: str = field(default="", metadata={"help": "object file (default: <inputs>/object.glb)"})
    view: str = field(default="view1", metadata={"help": "camera view of scene.json"})
    previews: bool = field(default=True, metadata={"help": "write PNG previews"})


class Workspace:
    """Every path of a pipeline run, defined once."""

    def __init__(self, cfg: RunConfig):
        self.cfg = cfg
        self.inp = Path(cfg.inputs)
        self.root = Path(cfg.workspace)

    photo = property(lambda s: s.inp / "photo.exr")
    cloud_ldr = property(lambda s: s.inp / "cloud_ldr.ply")
    scene = property(lambda s: s.inp / "scene.json")
    object = property(lambda s: Path(s.cfg.object) if s.cfg.object else s.inp / "object.glb")
    exposure = property(lambda s: s.root / "exposure.npz")
    photo_ldr = property(lambda s: s.root / "photo_ldr.exr")
    cubemaps = property(lambda s: s.root / "cubemaps")
    hdr_faces = property(lambda s: s.root / "hdr_faces")
    cloud_proj = property(lambda s: s.root / "cloud_proj.ply")
    cloud_hdr = property(lambda s: s.root / "cloud_hdr.ply")
    bsh = property(lambda s: s.root / "bsh.npz")
    relit = property(lambda s: s.root / "relit.png")

    def preview(self, name: str) -> Path | None:
        return self.root / f"{name}.png" if self.cfg.previews else None


@dataclass(frozen=True)
class Stage:
    verb: str
    config: str                       # "module:Class"
    inputs: Callable[[Workspace], list[Path]]
    outputs: Callable[[Workspace], list[Path]]
    call: Callable[[Any, Workspace, StageConfig], Any]   # (module, workspace, cfg)


STAGES: list[Stage] = [
    Stage("expose-match", "pipeline.expose_match:ExposeMatchConfig",
          lambda w: [w.photo, w.cloud_ldr], lambda w: [w.exposure, w.photo_ldr],
          lambda m, w, c: m.run_expose_match(w.photo, w.cloud_ldr, w.exposure, w.photo_ldr, c, preview=w.preview("expose_match"))),
    Stage("render-cubemaps", "pipeline.render_cubemaps:RenderCubemapsConfig",
          lambda w: [w.cloud_ldr], lambda w: [w.cubemaps / "cameras.npz"],
          lambda m, w, c: m.run_render_cubemaps(w.cloud_ldr, w.cubemaps, c, preview=w.preview("cubemaps"))),
    Stage("patchmatch", "pipeline.patchmatch:PatchmatchConfig",
          lambda w: [w.cubemaps / "cameras.npz", w.exposure, w.photo], lambda w: [w.hdr_faces / "renderings.npz"],
          lambda m, w, c: m.run_patchmatch(w.cubemaps, w.photo, w.photo_ldr, w.exposure, w.hdr_faces, c,
                                           preview=w.preview("hdr_faces"))),
    Stage("reproject", "pipeline.reproject:ReprojectConfig",
          lambda w: [w.cloud_ldr, w.hdr_faces / "renderings.npz"], lambda w: [w.cloud_proj],
          lambda m, w, c: m.run_reproject(w.cloud_ldr, w.cubemaps, w.hdr_faces, w.cloud_proj, c, preview=w.preview("cloud_proj"))),
    Stage("poisson", "pipeline.poisson:PoissonConfig",
          lambda w: [w.cloud_proj], lambda w: [w.cloud_hdr],
          lambda m, w, c: m.run_poisson(w.cloud_proj, w.cloud_hdr, c, preview=w.preview("cloud_hdr"), ldr=w.cloud_ldr)),
    Stage("build-bsh", "pipeline.build_bsh:BuildBshConfig",
          lambda w: [w.cloud_hdr], lambda w: [w.bsh],
          lambda m, w, c: m.run_build_bsh(w.cloud_hdr, w.bsh, c, preview=w.preview("bsh"))),
    Stage("relight", "pipeline.relight:RelightConfig",
          lambda w: [w.bsh, w.cloud_hdr, w.scene], lambda w: [w.relit],
          lambda m, w, c: m.run_relight(w.bsh, w.root, c, object_path=w.object, scene_path=w.scene,
                                        view=w.cfg.view)),
]
VERBS = [s.verb for s in STAGES]


def _up_to_date(ins: list[Path], outs: list[Path]) -> bool:
    if not all(o.exists() for o in outs):
        return False
    newest_in = max((p.stat().st_mtime for p in ins if p.exists()), default=0.0)
    return min(o.stat().st_mtime for o in outs) >= newest_in


def run_pipeline(config_toml: str, from_stage: str | None = None, to_stage: str | None = None,
                 force: bool = False, seed: int | None = None) -> dict[str, Any]:
    """Run the stages from ``from_stage`` to ``to_stage`` with the options of ``config_toml``
    (its ``[run]`` table and one table per verb); writes ``<workspace>/run.json`` with the
    resolved config of every stage, what ran, what was skipped and the timings."""
    from . import io

    data = load_toml(config_toml)
    unknown = sorted(k for k, v in data.items() if isinstance(v, dict) and k not in set(VERBS) | {"run"})
    if unknown:
        raise ConfigError(f"{config_toml}: unknown table [{unknown[0]}] (known: run, {', '.join(VERBS)})")
    rcfg = resolve(RunConfig, config_toml, "run", {"seed": seed})
    for name in (from_stage, to_stage):
        if name is not None and name not in VERBS:
            raise ConfigError(f"--from/--to must be one of {', '.join(VERBS)}, got {name!r}")
    i0 = VERBS.index(from_stage) if from_stage else 0
    i1 = VERBS.index(to_stage) if to_stage else len(VERBS) - 1
    ws = Workspace(rcfg)
    ws.root.mkdir(parents=True, exist_ok=True)
    for p in (ws.photo, ws.cloud_ldr):
        if i0 == 0 and not p.exists():
            raise InputError(p, "no such file (the [run] inputs folder must hold photo.exr and cloud_ldr.ply)")
    report: dict[str, Any] = {"config": str(config_toml), "run": rcfg.as_dict(), "stages": {}}
    for st in progress(STAGES[i0:i1 + 1], total=i1 + 1 - i0, desc="pipeline"):
        mod_name, _, cls_name = st.config.partition(":")
        try:
            mod = importlib.import_module(mod_name)
            cls = getattr(mod, cls_name)
        except (ImportError, AttributeError):
            raise NotImplementedStage(st.verb) from None
        cfg = resolve(cls, config_toml, st.verb, {"seed": rcfg.seed})
        entry: dict[str, Any] = {"config": cfg.as_dict()}
        if not force and _up_to_date(st.inputs(ws), st.outputs(ws)):
            log.info("%s: outputs up to date, skipped (use --force to rerun)", st.verb)
            entry["skipped"] = True
        else:
            log.info("%s: running", st.verb)
            t0 = time.perf_counter()
            st.call(mod, ws, cfg)
            entry["seconds"] = round(time.perf_counter() - t0, 3)
            log.info("%s: done in %.1f s", st.verb, entry["seconds"])
        report["stages"][st.verb] = entry
        report.setdefault("order", []).append(st.verb)
        io.write_json(ws.root / "run.json", report)
    log.info("pipeline finished: %s", ws.relit if i1 == len(VERBS) - 1 else ws.root)
    return report
