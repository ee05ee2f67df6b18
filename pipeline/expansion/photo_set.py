"""A set of photos of one room (issue 25): the photos a stage is given, their cameras, and their joint exposure.

Not a stage: expose-match writes the set into exposure.npz (:func:`set_keys`), patchmatch and reproject read it
back (:func:`read_set`). Conventions as :mod:`pipeline.camera` (OpenCV photo axes, world right-handed, +Y up,
metres; linear Rec.709 colours).

* **The photos**: a list of files and folders; a folder stands for its HDR files (``.exr``, ``.hdr``) in name
  order (:func:`expand_photos`).
* **The cameras** (:class:`PhotoCam`): one per photo, of a model of :data:`pipeline.camera.MODELS` — a pinhole
  photo is registered against the cloud (:mod:`pipeline.expansion.register_photo`), a panorama (``equirect``) or a
  fisheye is placed at ``--photo-at`` with the world's axes (its centre column looks along world +Z, its top row
  towards world +Y; a fisheye looks along world +Z).
* **The exposure**: one cloud exposure α and one scale k_i per photo: photo i in the LDR cloud's units is
  α·k_i·photo_i (k = 1 for the first kept photo, the reference). From each photo alone the registration gives
  α_i = Σ cloud / Σ photo over the photo's unclipped blocks (:func:`pipeline.expansion.register_photo.exposure_from_pose`);
  where two photos see the same cloud points, the photos themselves give the ratio ln α_i − ln α_j = median of
  ln photo_j − ln photo_i over those points (HDR against HDR: also where the cloud is clipped).
  :func:`joint_fit` solves the weighted least squares of both kinds of equations for ln α_i (each weighted by
  1/σ², σ = the MAD-based error of its median, floored at ``min_error``: the exposure step scatters by ±1–2.5 %
  from view to view on the shipped sample); a pair whose overlap ratio disagrees with the two registrations by
  more than ``z`` of their combined error is reported (expose-match warns, naming both photos).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..camera import PANORAMA_ROTATION
from ..color import luminance
from ..errors import InputError

PHOTO_SUFFIXES = (".exr", ".hdr", ".pic", ".rgbe")


def expand_photos(photos: str | Path | Sequence[str | Path]) -> list[Path]:
    """The photo files of ``photos`` (a path or a list): a folder stands for its HDR files (:data:`PHOTO_SUFFIXES`)
    in name order; a folder without any is an InputError; files are kept as given (checked by their readers)."""
    items = [photos] if isinstance(photos, (str, Path)) else list(photos)
    out: list[Path] = []
    for p in map(Path, items):
        if p.is_dir():
            found = sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in PHOTO_SUFFIXES)
            if not found:
                raise InputError(p, f"a folder of photos without any HDR photo ({', '.join(PHOTO_SUFFIXES)})")
            out += found
        else:
            out.append(p)
    return out


@dataclass
class PhotoCam:
    """One photo of a set: its file, camera model (``pinhole``/``equirect``/``fisheye``), size (W, H) [pixels],
    ``world_to_camera`` (4,4, OpenCV axes), pinhole ``K`` (3,3; zeros for the other models), vertical/circle
    field of view [degrees] (0: unknown), how its pose was found (``registered``: by registration; else given),
    registration ``quality`` (final NCC; 1 for a given pose), ``kept`` (0: dropped from the set), its scale
    ``k`` (photo in cloud units = α·k·photo) and its own registration exposure ``alpha_register``."""

    path: Path
    model: str = "pinhole"
    size: tuple[int, int] = (0, 0)
    world_to_camera: np.ndarray = field(default_factory=lambda: np.eye(4))
    K: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    fov_deg: float = 0.0
    registered: bool = False
    quality: float = 0.0
    kept: bool = True
    k: float = 1.0
    alpha_register: float = float("nan")

    @property
    def eye(self) -> np.ndarray:
        R, t = self.world_to_camera[:3, :3], self.world_to_camera[:3, 3]
        return -R.T @ t

    def params(self) -> dict[str, Any]:
        """The model's parameters for :data:`pipeline.camera.MODELS`."""
        return {"pinhole": {"K": self.K}, "fisheye": {"fov_deg": self.fov_deg}, "equirect": {}}[self.model]

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(u, v, ok) of world points (N,3) in this photo: continuous pixel coordinates (pixel centres at +0.5)."""
        from ..camera import project_points

        u, v, _, ok = project_points(self.model, points, self.size, self.world_to_camera, **self.params())
        return u, v, ok


def placed_camera(path: Path, model: str, size: tuple[int, int], at: Sequence[float], fov_deg: float = 0.0,
                  rotation: np.ndarray | None = None) -> PhotoCam:
    """A photo whose centre is given (``--photo-at``; panoramas and fisheyes): world→camera ``rotation`` (3,3) —
    a placed panorama's yaw searched at its centre (:func:`pipeline.expansion.register_photo.placed_panorama_yaw`),
    else world-aligned axes (:data:`PANORAMA_ROTATION`) —, quality 1."""
    R = PANORAMA_ROTATION if rotation is None else np.asarray(rotation, np.float64)
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ np.asarray(at, np.float64)
    return PhotoCam(Path(path), model, (int(size[0]), int(size[1])), w2c, np.zeros((3, 3)), float(fov_deg),
                    registered=False, quality=1.0)


def photo_values(points: np.ndarray, normals: np.ndarray, radii: np.ndarray, query: np.ndarray, photo: np.ndarray,
                 cam: PhotoCam, scale: float, margin_px: float = 1.0,
                 isolated: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(seen (M,) bool, scale × photo (M,3)) for the points ``query`` of the cloud in a photo of any model: seen =
    in the image (≥ ``margin_px`` inside; an equirect sees every direction), facing the camera and not occluded
    (:func:`pipeline.expansion.register_photo.surfel_visible`); bilinear reads, or the 3×3 peak for ``isolated`` points.
    A pinhole photo is :func:`pipeline.expansion.register_photo.photo_samples` exactly."""
    from .register_photo import peak_reads, photo_samples, surfel_visible

    if cam.model == "pinhole":
        return photo_samples(points, normals, radii, query, photo, cam.K, cam.world_to_camera, scale,
                             margin_px=margin_px, isolated=isolated)
    from scipy.ndimage import map_coordinates

    eye = cam.eye
    p = points[query]
    u, v, ok = cam.project(p)
    h, w = photo.shape[:2]
    inside = ok & (v >= margin_px) & (v <= h - margin_px)
    if cam.model != "equirect":
        inside &= (u >= margin_px) & (u <= w - margin_px)
    seen = np.zeros(len(query), bool)
    cand = np.flatnonzero(inside)
    if cand.size:
        seen[cand] = surfel_visible(points, normals, radii, eye, np.asarray(query)[cand])
    out = np.zeros((len(query), 3))
    if seen.any():
        coords = np.stack([v[seen] - 0.5, u[seen] - 0.5])
        mode = "grid-wrap" if cam.model == "equirect" else "nearest"
        out[seen] = scale * np.stack([map_coordinates(photo[..., k].astype(np.float64), coords, order=1, mode=mode)
                                      for k in range(3)], -1)
    peak = seen & (np.asarray(isolated, bool) if isolated is not None else False)
    if peak.any():
        out[peak] = scale * peak_reads(photo, u[peak], v[peak])
    return seen, out


# ----------------------------------------------------------------------------- exposure.npz
def set_keys(cams: list[PhotoCam], folder: Path) -> dict[str, np.ndarray]:
    """The ``photos*`` keys of exposure.npz (schema ``pcrelight.exposure/1``) for the set ``cams``; paths relative
    to ``folder`` (the npz's) with their SHA-256 (:func:`pipeline.io.file_ref`)."""
    from .. import io

    refs = [io.file_ref(c.path, folder) for c in cams]
    return dict(photos=np.asarray([r[0] for r in refs]), photos_sha256=np.asarray([r[1] for r in refs]),
                photos_model=np.asarray([c.model for c in cams]),
                photos_size=np.asarray([c.size for c in cams], np.int32).reshape(-1, 2),
                photos_world_to_camera=np.asarray([c.world_to_camera for c in cams], np.float64).reshape(-1, 4, 4),
                photos_K=np.asarray([c.K for c in cams], np.float64).reshape(-1, 3, 3),
                photos_fov_deg=np.asarray([c.fov_deg for c in cams], np.float64),
                photos_registered=np.asarray([c.registered for c in cams], np.uint8),
                photos_quality=np.asarray([c.quality for c in cams], np.float64),
                photos_kept=np.asarray([c.kept for c in cams], np.uint8),
                photos_scale=np.asarray([c.k for c in cams], np.float64),
                photos_alpha_register=np.asarray([c.alpha_register for c in cams], np.float64))


def read_set(ex: dict[str, np.ndarray], exposure: str | Path,
             given: Sequence[str | Path] | None = None) -> list[PhotoCam] | None:
    """The set recorded in exposure.npz (``ex``, read from ``exposure``), or None when it records none (a single
    pinhole photo: ``photo_K``/``photo_world_to_camera``). The photos are ``given`` (as many as recorded, in
    order), else the recorded files (checked by SHA-256; a missing or changed one is an InputError)."""
    from .. import io

    if "photos" not in ex:
        return None
    rel = [str(x) for x in np.atleast_1d(ex["photos"])]
    if given is not None and len(given) != len(rel):
        raise InputError(exposure, f"records {len(rel)} photos, {len(given)} given: give them all, in its order, or none")
    folder = Path(exposure).parent
    cams = []
    for i, r in enumerate(rel):
        if given is not None:
            p = Path(given[i])
        else:
            p = io.follow_ref(folder, r, str(np.atleast_1d(ex["photos_sha256"])[i]), "a photo expose-match read")
        cams.append(PhotoCam(p, str(ex["photos_model"][i]), tuple(int(x) for x in ex["photos_size"][i]),
                             np.asarray(ex["photos_world_to_camera"][i], np.float64), np.asarray(ex["photos_K"][i], np.float64),
                             float(ex["photos_fov_deg"][i]), bool(ex["photos_registered"][i]), float(ex["photos_quality"][i]),
                             bool(ex["photos_kept"][i]), float(ex["photos_scale"][i]), float(ex["photos_alpha_register"][i])))
    return cams


# ----------------------------------------------------------------------------- the joint exposure
def pair_ratio(seen_i: np.ndarray, vals_i: np.ndarray, seen_j: np.ndarray, vals_j: np.ndarray,
               min_points: int = 50) -> dict[str, float] | None:
    """ln(α_i/α_j) from the points both photos see (``seen_*`` (N,) bool over the same points, ``vals_*`` (N,3)
    their photo values): the median of ln Y_j − ln Y_i over the points non-dark in both (above each photo's 5 %
    quantile there), its error 1.4826·MAD/√n; None below ``min_points`` such points."""
    both = seen_i & seen_j
    if both.sum() < min_points:
        return None
    yi, yj = luminance(vals_i[both], np.float64), luminance(vals_j[both], np.float64)
    ok = (yi > max(np.quantile(yi, 0.05), 1e-12)) & (yj > max(np.quantile(yj, 0.05), 1e-12))
    if ok.sum() < min_points:
        return None
    d = np.log(yj[ok]) - np.log(yi[ok])
    med = float(np.median(d))
    return {"ln_ratio": med, "error": float(1.4826 * np.median(np.abs(d - med)) / np.sqrt(ok.sum())), "points": int(ok.sum())}


def joint_fit(alpha_reg: Sequence[float], reg_error: Sequence[float], pairs: dict[tuple[int, int], dict[str, float]],
              min_error: float = 0.02, z: float = 3.0) -> dict[str, Any]:
    """Weighted least squares of ln α_i (i = 0…P−1) on the registrations (ln α_i = ln ``alpha_reg[i]``, error
    ``reg_error[i]`` in ln units) and the overlaps (``pairs[(i, j)]``: ln α_i − ln α_j = ``ln_ratio``), each
    error floored at ``min_error``. Returns ``alpha`` (P,) (exp of the solution), ``residual`` (P,) (ln α_reg −
    ln α, per photo) and ``disagree``: [(i, j, overlap ratio α_i/α_j, registrations' ratio, z-score)] for the pairs
    whose overlap ratio and registrations' ratio differ by more than ``z`` combined errors."""
    P = len(alpha_reg)
    rows, rhs, wts = [], [], []
    for i in range(P):
        r = np.zeros(P)
        r[i] = 1.0
        rows.append(r), rhs.append(np.log(alpha_reg[i])), wts.append(1.0 / max(reg_error[i], min_error))
    for (i, j), p in pairs.items():
        r = np.zeros(P)
        r[i], r[j] = 1.0, -1.0
        rows.append(r), rhs.append(p["ln_ratio"]), wts.append(1.0 / max(p["error"], min_error))
    A, b, w = np.array(rows), np.array(rhs), np.array(wts)
    sol = np.linalg.lstsq(A * w[:, None], b * w, rcond=None)[0]
    disagree = []
    for (i, j), p in pairs.items():
        reg = np.log(alpha_reg[i]) - np.log(alpha_reg[j])
        err = np.sqrt(max(reg_error[i], min_error) ** 2 + max(reg_error[j], min_error) ** 2 + max(p["error"], min_error) ** 2)
        zz = abs(reg - p["ln_ratio"]) / err
        if zz > z:
            disagree.append((i, j, float(np.exp(p["ln_ratio"])), float(np.exp(reg)), float(zz)))
    return {"alpha": np.exp(sol), "residual": np.log(np.asarray(alpha_reg, float)) - sol, "disagree": disagree}


def exposure_from_camera(points: np.ndarray, colors: np.ndarray, normals: np.ndarray, photo_rgb: np.ndarray,
                         cam: PhotoCam, margin_px: int = 2) -> dict:
    """α of a photo of any model at a known camera (``cam``; a placed panorama or fisheye): the cloud points
    seen (in the image ≥ ``margin_px`` inside, facing, not occluded: :func:`pipeline.expansion.register_photo.surfel_visible`)
    through :func:`pipeline.expansion.register_photo.block_exposure` (16-px photo blocks, Σ cloud / Σ photo)."""
    from .register_photo import block_exposure, surfel_visible
    from .splats import knn_splat_radii

    h, w = photo_rgb.shape[:2]
    u, v, ok = cam.project(points)
    ok &= (u >= margin_px) & (u < w - margin_px) & (v >= margin_px) & (v < h - margin_px)
    cand = np.flatnonzero(ok)
    ok[cand] = surfel_visible(points, normals, knn_splat_radii(points), cam.eye, cand)
    return block_exposure(u, v, ok, colors, photo_rgb)


def registered(exposure: str | Path | None) -> bool:
    """Whether ``exposure`` (exposure.npz) holds a camera for the direct transfer: the registered photo's
    (expose-match with a field of view), or, for a set of photos (``photos*`` keys), a kept photo with a camera —
    registered, or a placed panorama/fisheye (the cameras :func:`direct_cameras` uses)."""
    from .. import io

    if exposure is None or not Path(exposure).exists():
        return False
    ex = io.read_npz(exposure, "pcrelight.exposure/1")
    if "photos" in ex:
        kept = np.atleast_1d(ex["photos_kept"]).astype(bool)
        cam = np.atleast_1d(ex["photos_registered"]).astype(bool) | (np.atleast_1d(ex["photos_model"]) != "pinhole")
        return bool(np.any(kept & cam))
    return "photo_world_to_camera" in ex
