"""Where every artifact of a pipeline run lives: the one definition of the paths and of the face folders.

A run has an *inputs* folder (``photo.exr``, ``cloud_ldr.ply``, ``scene.json``, ``object.glb``, as
``make-scene`` writes them) and a *workspace* folder that every stage writes into. A **face folder**
holds numbered cube-map faces ``face_000.exr``, ``face_001.exr``… (six a view, in the order of
``cameras.npz``) and one NPZ: render-cubemaps writes faces with channels R,G,B,A,Z plus
``cameras.npz`` (schema ``pcrelight.cameras/1``); patchmatch writes faces with R,G,B,Q plus
``renderings.npz`` (``pcrelight.renderings/1``); both add ``report.json``. The stage registry
(:mod:`pipeline.run.stages`) declares each stage's inputs and outputs with these names.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from ..errors import InputError

FACE = "face_{:03d}.exr"


@dataclass(frozen=True)
class FaceFolder:
    """A folder of cube-map faces (see the module docstring)."""

    path: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", Path(self.path))

    cameras = property(lambda s: s.path / "cameras.npz")
    renderings = property(lambda s: s.path / "renderings.npz")
    report = property(lambda s: s.path / "report.json")

    def face(self, i: int) -> Path:
        return self.path / FACE.format(i)

    def stored_faces(self) -> list[Path]:
        """The face files present now (any number), sorted."""
        return sorted(self.path.glob("face_*.exr"))


def write_faces(folder: str | Path | FaceFolder, faces: Iterable[np.ndarray], first: int,
                channels: list[str]) -> None:
    """Write faces ``first``, ``first + 1``… of a face folder (float32 EXR, the given channel names)."""
    from .. import io

    ff = folder if isinstance(folder, FaceFolder) else FaceFolder(folder)
    for k, img in enumerate(faces):
        io.write_image(ff.face(first + k), img, channels=channels)


def read_face(folder: str | Path | FaceFolder, i: int, channels: list[str],
              size: tuple[int, int] | None = None) -> np.ndarray:
    """Face ``i`` of a face folder: the named channels, (H, W, len(channels)) float32. A missing
    channel, or a size other than ``size`` = (width, height), is an InputError naming the file."""
    from .. import io

    path = (folder if isinstance(folder, FaceFolder) else FaceFolder(folder)).face(i)
    names = io.image_channels(path)
    missing = [c for c in channels if c not in names]
    if missing:
        raise InputError(path, f"missing channel(s) {','.join(missing)} (has {','.join(names)})")
    img = io.read_image(path)
    if size is not None and img.shape[:2] != (size[1], size[0]):
        raise InputError(path, f"size {img.shape[1]}x{img.shape[0]} != {size[0]}x{size[1]} in cameras.npz")
    return img[:, :, [names.index(c) for c in channels]]


def read_faces(cubemaps: str | Path | FaceFolder, renderings: str | Path | FaceFolder
               ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], list[np.ndarray], list[np.ndarray],
                          list[np.ndarray], list[np.ndarray]]:
    """The rendered faces with their HDR expansion: ``(cameras, renderings, depth, coverage, hdr,
    quality)`` — the two NPZs, and per face Z (H, W), A (H, W), R,G,B (H, W, 3), Q (H, W)."""
    from .. import io

    cf = cubemaps if isinstance(cubemaps, FaceFolder) else FaceFolder(cubemaps)
    rf = renderings if isinstance(renderings, FaceFolder) else FaceFolder(renderings)
    cams = io.read_npz(cf.cameras, "pcrelight.cameras/1")
    rend = io.read_npz(rf.renderings, "pcrelight.renderings/1")
    nf = len(cams["K"])
    if int(rend["count"]) != nf:
        raise InputError(rf.renderings, f"count {int(rend['count'])} != {nf} faces in {cf.cameras}")
    depth, cover, hdr, qual = [], [], [], []
    for i in range(nf):
        size = tuple(int(x) for x in cams["resolution"][i])
        a = read_face(cf, i, ["A", "Z"], size)
        b = read_face(rf, i, ["R", "G", "B", "Q"], size)
        cover.append(a[:, :, 0])
        depth.append(a[:, :, 1])
        hdr.append(b[:, :, :3])
        qual.append(b[:, :, 3])
    return cams, rend, depth, cover, hdr, qual


# names of the workspace's artifacts, relative to the workspace folder (a run may rename some, as
# ``evaluate --run-all`` does to keep one expansion per method side by side)
NAMES: dict[str, str] = {
    "exposure": "exposure.npz", "photo_ldr": "photo_ldr.exr", "cubemaps": "cubemaps", "hdr_faces": "hdr_faces",
    "cloud_proj": "cloud_proj.ply", "cloud_hdr": "cloud_hdr.ply", "bsh": "bsh.npz", "relit": ".",
    "run_report": "run.json", "report": "report.html",
}


def report_of(path: Path) -> Path:
    """The JSON report a stage writes beside its single-file output (``x.ply`` → ``x.json``)."""
    return path.with_suffix(".json")


@dataclass(frozen=True)
class Workspace:
    """Every path of one pipeline run: the inputs folder's files and the workspace folder's artifacts."""

    inputs: Path
    root: Path
    object_file: Path | None = None          # default: <inputs>/object.glb
    previews: bool = True                    # the stages write <root>/<name>.png previews
    view: str = "view1"                      # the scene.json camera view relight renders
    names: dict[str, str] = dataclasses.field(default_factory=lambda: dict(NAMES))
    hdr_cloud: str = "cloud_hdr"             # the cloud build-bsh reads: cloud_hdr (poisson's), cloud_proj
                                             # (reproject's: nothing invalid) or cloud_ldr (nothing overexposed)
    cloud_file: Path | None = None           # default: <inputs>/cloud_ldr.ply (run --cloud: the imported scan)
    photo_file: Path | None = None           # default: <inputs>/photo.exr (run --photo: the user's EXR or .hdr)
    scene_file: Path | None = None           # default: <inputs>/scene.json (run --cloud: the one it writes)
    faces: bool = True                       # reproject reads the cube-map faces (False: the planner skipped
                                             # render-cubemaps and patchmatch, the registered photo alone)
    photo_files: tuple = ()                  # several photos (run --photo a --photo b, or a folder): all of them
    photo_view: bool = False                 # relight renders from the registered photo's camera and composites
                                             # into the photo (an own-room run whose exposure.npz holds its camera)

    def __post_init__(self) -> None:
        object.__setattr__(self, "inputs", Path(self.inputs))
        object.__setattr__(self, "root", Path(self.root))
        unknown = set(self.names) - set(NAMES)
        if unknown:
            raise ValueError(f"unknown artifact name(s) {sorted(unknown)}")
        object.__setattr__(self, "names", {**NAMES, **self.names})
        if self.hdr_cloud not in ("cloud_ldr", "cloud_proj", "cloud_hdr"):
            raise ValueError(f"hdr_cloud must be cloud_ldr, cloud_proj or cloud_hdr, got {self.hdr_cloud!r}")

    def renamed(self, **names: str) -> "Workspace":
        """The same workspace with some artifacts under other names (relative to the root)."""
        return dataclasses.replace(self, names={**self.names, **names})

    def _at(self, key: str) -> Path:
        return self.root / self.names[key]

    # inputs (make-scene's layout)
    photo = property(lambda s: Path(s.photo_file) if s.photo_file else s.inputs / "photo.exr")
    photos = property(lambda s: tuple(Path(p) for p in s.photo_files) if s.photo_files else (s.photo,))  # the set
    cloud_ldr = property(lambda s: Path(s.cloud_file) if s.cloud_file else s.inputs / "cloud_ldr.ply")
    scene = property(lambda s: Path(s.scene_file) if s.scene_file else s.inputs / "scene.json")
    object = property(lambda s: s.object_file if s.object_file else s.inputs / "object.glb")
    # expose-match
    exposure = property(lambda s: s._at("exposure"))
    exposure_report = property(lambda s: s.exposure.with_suffix(".json"))
    exposure_fit = property(lambda s: s.exposure.with_name(s.exposure.stem + "_fit.png"))
    photo_ldr = property(lambda s: s._at("photo_ldr"))
    # the face folders of render-cubemaps and patchmatch
    cubemaps = property(lambda s: FaceFolder(s._at("cubemaps")))
    hdr_faces = property(lambda s: FaceFolder(s._at("hdr_faces")))
    # the clouds, the hierarchy and the relit image
    cloud_proj = property(lambda s: s._at("cloud_proj"))
    cloud_hdr = property(lambda s: s._at("cloud_hdr"))
    bsh = property(lambda s: s._at("bsh"))
    bsh_cloud = property(lambda s: getattr(s, s.hdr_cloud))  # build-bsh's input (the planner's choice, pipeline/run/plan.py)
    relit_dir = property(lambda s: s._at("relit"))
    relit = property(lambda s: s.relit_dir / "relit.png")
    relit_exr = property(lambda s: s.relit_dir / "relit.exr")
    relit_hdr = property(lambda s: s.relit_dir / "relit.hdr")        # relight --hdr-out (Radiance RGBE)
    relit_stats = property(lambda s: s.relit_dir / "stats.json")
    composite = property(lambda s: s.relit_dir / "composite.png")
    composite_exr = property(lambda s: s.relit_dir / "composite.exr")
    composite_hdr = property(lambda s: s.relit_dir / "composite.hdr")  # run --hdr-out
    run_report = property(lambda s: s._at("run_report"))
    report = property(lambda s: s._at("report"))              # the run's HTML page (pipeline/run/report.py)

    def preview(self, name: str) -> Path | None:
        """``<root>/<name>.png`` when previews are on, else None."""
        return self.root / f"{name}.png" if self.previews else None
