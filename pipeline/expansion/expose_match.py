"""expose-match (seed 000 §4.1, Eq. 1): the exposure α that makes the HDR photo look like the LDR cloud.

photo.exr (linear HDR, any scale) + cloud_ldr.ply → exposure.npz (α, the Wasserstein distance, every
tried α) and photo_ldr.exr = clamp(α · I_HDR, 0, 1) (Eq. 1, per channel).

Method
------
* Exposure is searched in **log2** (stops).  Candidates: a fixed grid ``stop_min..stop_max`` step
  ``stop_step`` (default −48…+48 stops in 1-stop steps: photos scaled by 1e-6…1e6 relative to the
  cloud are 20 stops away from a unit exposure, well inside).  The paper builds its fixed-exposure
  images with exposure fusion [MKR07]; we use Eq. 1 directly for every candidate (that is the image
  the later stages see).
* Histogram: 128 bins on [0, 1] of the CIE Y luminance (colour-science's sRGB/Rec.709 row, from
  *linear* RGB) **re-encoded with the sRGB transfer function**, i.e. in the space the cloud is stored
  in (8-bit sRGB-encoded colours).  Why: the cloud's quantisation is uniform in that space, so the
  128 bins each hold exactly two 8-bit codes' worth of values; in linear space the first bin alone
  would swallow the codes 0…~90 (all of the dark half of the cloud) and the match would be decided
  by the highlights only.  ``--hist-space linear`` is available for comparison.  Clamped photo pixels
  (Y = 1) land in the last bin exactly like clipped cloud points.
* Distance: ``scipy.stats.wasserstein_distance`` between the two histograms (bin centres as values,
  counts as weights), in encoded-luminance units.
* Refinement: bisection in log2 α between the best grid candidate's neighbours — each iteration
  evaluates the midpoints of the two half-brackets, re-centres on the best of the three and halves
  the bracket; it stops when the distance has not decreased for ``patience`` consecutive iterations
  ("until the error stops decreasing"), when the bracket is narrower than ``tol_stops`` or after
  ``max_iter`` (≤ 50) iterations.  Deterministic: no randomness.

Exposure from correspondences (not in the paper; issue 14)
-----------------------------------------------------------
Eq. 1 assumes the photo's histogram is the cloud's; people photograph the window, not the wall, and
on the shipped photos Eq. 1 is 47–83 % low.  With the photo camera's vertical field of view
(``--photo-fov``, degrees, as its EXIF gives it) the photo is **registered** against the cloud
(:mod:`pipeline.expansion.register_photo`: pose search by NCC of log luminance and log chroma between the
photo and splatted cube maps of the cloud), and α is re-estimated from the cloud points the
registered camera sees: Σ cloud / Σ photo over the photo blocks of unclipped, non-dark points.  ``--alpha-from auto`` (default) takes it when the registration is confident (final
NCC ≥ ``min_register_ncc`` and ≥ ``min_register_blocks`` blocks), else Eq. 1 with a WARNING naming
the figures; both estimates and the winner are logged and kept in exposure.npz
(``alpha_histogram``, ``alpha_register``, ``alpha_source``) together with the registered camera
(``photo_K``, ``photo_world_to_camera``), which reproject uses to give the overexposed points the
photo sees their photo value directly.  Without ``--photo-fov`` nothing changes: Eq. 1.

Several photos (issue 25; :mod:`pipeline.expansion.photo_set`)
-----------------------------------------------------
PHOTO… (or a folder of them): each photo is registered on its own (``--photo-fov``, else its EXIF); a photo
whose registration is not confident (the ``min_register_*`` rules above) is dropped with a WARNING naming it;
α with one scale k_i per kept photo is fitted jointly (:func:`pipeline.expansion.photo_set.joint_fit`: each photo's
registration and the points two photos see), pairs whose exposures disagree beyond their errors are warned
about; exposure.npz then holds the set (``photos*`` keys), photo_ldr.exr is the reference's (the first kept).
``--photo-model equirect|fisheye --photo-at x,y,z``: a panorama or fisheye placed at its centre (not
registered), α from the points it sees; ``--photo-model pinhole,equirect`` (one model per photo): a set mixing
them (``--photo-at`` then holds the placed photos' centres in order). A panorama without a centre (none given, or
past the last ``--photo-at`` triple) is **registered**: a level panorama's centre and yaw
(:func:`pipeline.expansion.register_photo.register_panorama`; pitch and roll are not searched), α from the points it sees,
kept by the same ``min_register_*`` rules as a pinhole photo; one that fails them is dropped from a set with a
WARNING, and refused (one line, exit 1) when no photo of the set is kept. One pinhole photo writes exactly what
it wrote before.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..camera import MODELS, pose_matrix
from ..color import T_L, apply_exposure, luminance, srgb_decode, srgb_encode
from ..config import StageConfig
from ..errors import InputError
from ..runtime import Timings, get_logger

log = get_logger("expose-match")

HIST_SPACES = ("srgb", "linear")
ALPHA_SOURCES = ("auto", "histogram", "register")


# a placed photo (--photo-at) whose points give exposures this scattered is refused: the cloud contradicts the
# placement (the shipped panorama at its centre: see docs/photos.md; a yaw 84° off: 1.32)
PLACED_MAX_MAD = 0.5


@dataclass
class ExposeMatchConfig(StageConfig):
    bins: int = field(default=128, metadata={"help": "histogram bins of the luminance (the paper: 128)"})
    hist_space: str = field(default="srgb", metadata={
        "help": "space of the luminance histograms: srgb = CIE Y sRGB-encoded (the cloud's 8-bit storage), linear = CIE Y",
        "choices": HIST_SPACES})
    stop_min: float = field(default=-48.0, metadata={"help": "lowest candidate exposure [log2 α, stops]"})
    stop_max: float = field(default=48.0, metadata={"help": "highest candidate exposure [log2 α, stops]"})
    stop_step: float = field(default=1.0, metadata={"help": "spacing of the candidate grid [stops]"})
    max_iter: int = field(default=50, metadata={"help": "bisection iterations at most (the paper: 50)"})
    patience: int = field(default=4, metadata={
        "help": "stop the bisection after this many iterations without a lower distance"})
    tol_stops: float = field(default=1e-4, metadata={"help": "stop when the bracket is narrower than this [stops]"})
    max_photo_pixels: int = field(default=4_000_000, metadata={
        "help": "histogram a regular subsample of the photo above this many pixels (0 = all)"})
    alpha_from: str = field(default="auto", metadata={
        "help": "α from: histogram = Eq. 1 only; register = the photo registered against the cloud, α from the "
                "points it sees (needs --photo-fov); auto = register when --photo-fov is given and the "
                "registration is confident, else Eq. 1", "choices": ALPHA_SOURCES})
    photo_fov: float = field(default=0.0, metadata={
        "help": "vertical field of view of the photo's camera [degrees]; 0 = its EXIF's where the file carries a focal "
                "length (camera.exif_fov), else unknown: no registration"})
    min_register_ncc: float = field(default=0.45, metadata={
        "help": "auto: the registration counts when its final NCC (log luminance + chroma on the cloud points' "
                "projections, -1..1) is at least this (shipped photos 0.60–0.90, an unrelated image 0.21–0.29)"})
    min_register_blocks: int = field(default=20, metadata={
        "help": "auto: ... and at least this many photo blocks gave an exposure ratio"})
    photo_model: str = field(default="pinhole", metadata={
        "help": "the photos' camera model (pipeline/camera.py MODELS): pinhole (registered against the cloud), "
                "equirect (a 360° panorama: placed at its --photo-at with the world's axes, else registered as a level "
                "panorama: centre and yaw) or fisheye (equidistant, --photo-fov its circle's field of view; placed at "
                "--photo-at). One name: every photo; "
                "comma-separated: one per photo, in order (a set mixing a panorama and pinhole photos)"})
    photo_at: tuple[float, ...] = field(default=(), metadata={
        "help": "equirect/fisheye: the camera's centre x,y,z [m] (three numbers for every such photo, or for each "
                "such photo in turn, in the photos' order); required for a fisheye; a panorama without one (none "
                "given, or past the last triple) is registered: its centre and yaw are searched for"})
    min_exposure_error: float = field(default=0.02, metadata={
        "help": "several photos: floor of each exposure estimate's error [ln units] in the joint fit and the "
                "disagreement test (the registration's exposure scatters by ±1–2.5 % from view to view on the shipped sample)"})
    disagree_z: float = field(default=3.0, metadata={
        "help": "several photos: warn when two photos' exposure ratio from the points both see and from their "
                "registrations differ by more than this many combined errors"})
    min_register_cover: float = field(default=0.6, metadata={
        "help": "auto: ... and the cloud points it matched cover at least this share of the photo's 16-px grid cells "
                "(shipped photos ≥ 0.6; an unrelated image matched on a corner: NCC 0.46, cover 0.50)"})

    def check(self) -> None:
        self._require(2 <= self.bins <= 65536, "bins", "must be in [2, 65536]")
        self._require(self.hist_space in HIST_SPACES, "hist_space", f"must be one of {HIST_SPACES}")
        self._require(self.stop_step > 0, "stop_step", "must be > 0")
        self._require(self.stop_max > self.stop_min, "stop_max", "must be > --stop-min")
        self._require((self.stop_max - self.stop_min) / self.stop_step <= 10000, "stop_step",
                      "gives more than 10000 candidates")
        self._require(0 <= self.max_iter <= 50, "max_iter", "must be in [0, 50]")
        self._require(self.patience >= 1, "patience", "must be ≥ 1")
        self._require(self.tol_stops > 0, "tol_stops", "must be > 0")
        self._require(self.max_photo_pixels >= 0, "max_photo_pixels", "must be ≥ 0")
        self._require(self.alpha_from in ALPHA_SOURCES, "alpha_from", f"must be one of {ALPHA_SOURCES}")
        models = [m.strip() for m in self.photo_model.split(",")]
        self._require(all(m in MODELS for m in models), "photo_model",
                      f"must be one of {', '.join(MODELS)}, or one of them per photo, comma-separated")
        self._require(self.photo_fov == 0 or 0 < self.photo_fov < (180 if "fisheye" in models else 170), "photo_fov",
                      "must be 0 (unknown) or in (0, 170) (a fisheye's circle: (0, 180))")
        self._require(self.alpha_from != "register" or self.photo_fov > 0 or "pinhole" not in models, "photo_fov",
                      "must be given (> 0) with --alpha-from register")
        self._require(-1 <= self.min_register_ncc <= 1, "min_register_ncc", "must be in [-1, 1]")
        self._require(self.min_register_blocks >= 1, "min_register_blocks", "must be ≥ 1")
        self._require(0 <= self.min_register_cover <= 1, "min_register_cover", "must be in [0, 1]")
        self._require(len(self.photo_at) % 3 == 0, "photo_at", "must be x,y,z (three numbers per photo)")
        self._require(set(models) != {"fisheye"} or self.alpha_from != "register", "alpha_from",
                      "register needs --photo-model pinhole or equirect (fisheye photos are placed with --photo-at)")
        self._require("fisheye" not in models or self.photo_fov > 0, "photo_fov",
                      "must be given with --photo-model fisheye (its circle's field of view [degrees])")
        self._require(self.min_exposure_error > 0, "min_exposure_error", "must be > 0")
        self._require(self.disagree_z > 0, "disagree_z", "must be > 0")


# ----------------------------------------------------------------------------- pure functions
_EDGES: dict[tuple[int, str], np.ndarray] = {}


def _linear_edges(bins: int, space: str) -> np.ndarray:
    """Inner bin edges in *linear* luminance of ``bins`` uniform bins of [0, 1] in ``space``: the
    sRGB transfer function is monotone, so binning encoded values on uniform edges is binning linear
    values on the decoded edges (colour-science's sRGB EOTF) — exact, and no per-pixel encoding."""
    key = (bins, space)
    if key not in _EDGES:
        e = np.arange(1, bins) / bins
        if space != "linear":
            e = srgb_decode(e, np.float64)
        _EDGES[key] = e
    return _EDGES[key]


def luminance_histogram(rgb_ldr: np.ndarray, bins: int = 128, space: str = "srgb") -> np.ndarray:
    """Normalised histogram (bins,) on [0, 1] of the luminance of linear LDR RGB (..., 3) in ``space``
    (``srgb``: of the sRGB-encoded CIE Y; ``linear``: of CIE Y)."""
    y = np.clip(luminance(np.asarray(rgb_ldr).reshape(-1, 3), np.float64), 0.0, 1.0)
    idx = np.searchsorted(_linear_edges(bins, space), y, side="right")
    h = np.bincount(idx, minlength=bins).astype(np.float64)
    s = h.sum()
    return h / s if s > 0 else h


def histogram_distance(h1: np.ndarray, h2: np.ndarray) -> float:
    """1-D Wasserstein distance between two histograms on the same bins of [0, 1] (scipy)."""
    from scipy.stats import wasserstein_distance

    bins = len(h1)
    centres = (np.arange(bins) + 0.5) / bins
    if h1.sum() <= 0 or h2.sum() <= 0:
        return float("inf")
    return float(wasserstein_distance(centres, centres, h1, h2))


class _Objective:
    """Distance as a function of log2 α, memoised, recording every evaluation in order."""

    def __init__(self, photo_rgb: np.ndarray, cloud_hist: np.ndarray, bins: int, space: str):
        self.photo = photo_rgb.reshape(-1, 3).astype(np.float64)
        self.cloud_hist = cloud_hist
        self.bins, self.space = bins, space
        self.tried: list[tuple[float, float, int]] = []
        self._memo: dict[float, float] = {}

    def __call__(self, s: float, phase: int) -> float:
        if s in self._memo:
            return self._memo[s]
        h = luminance_histogram(np.minimum(self.photo * 2.0 ** s, 1.0), self.bins, self.space)
        d = histogram_distance(h, self.cloud_hist)
        self._memo[s] = d
        self.tried.append((s, d, phase))
        return d


def match_exposure(photo: np.ndarray, cloud_colors: np.ndarray, cfg: ExposeMatchConfig | None = None) -> dict:
    """Find α (Eq. 1) whose photo luminance histogram is closest to the cloud's.

    photo: linear HDR (H, W, ≥3) or (P, 3), non-negative finite; cloud_colors: linear LDR (N, 3).
    Returns a dict: alpha, log2_alpha, distance, grid_best_log2, tried_log2_alpha, tried_distance,
    tried_phase (0 grid, 1 bisection), iterations, stop_reason, cloud_hist, photo_hist.
    """
    cfg = cfg or ExposeMatchConfig()
    rgb = np.asarray(photo, dtype=np.float64)[..., :3].reshape(-1, 3)
    if cfg.max_photo_pixels and len(rgb) > cfg.max_photo_pixels:
        stride = int(np.ceil(len(rgb) / cfg.max_photo_pixels))
        rgb = rgb[::stride]
    cloud_hist = luminance_histogram(np.clip(cloud_colors, 0.0, 1.0), cfg.bins, cfg.hist_space)
    f = _Objective(rgb, cloud_hist, cfg.bins, cfg.hist_space)
    grid = np.arange(cfg.stop_min, cfg.stop_max + 0.5 * cfg.stop_step, cfg.stop_step)
    dists = np.array([f(float(s), 0) for s in grid])
    i = int(np.argmin(dists))  # first of ties: deterministic
    best_s, best_d = float(grid[i]), float(dists[i])
    grid_best = best_s
    half = cfg.stop_step
    it, since_better, reason = 0, 0, "max_iter"
    if cfg.max_iter == 0:
        reason = "max_iter"
    while it < cfg.max_iter:
        if 2 * half < cfg.tol_stops:
            reason = "bracket below tol_stops"
            break
        it += 1
        cands = [(best_s - half / 2, None), (best_s + half / 2, None)]
        improved = False
        for s, _ in cands:
            d = f(float(s), 1)
            if d < best_d:
                best_s, best_d, improved = float(s), d, True
        half /= 2
        since_better = 0 if improved else since_better + 1
        if since_better >= cfg.patience:
            reason = f"no decrease for {cfg.patience} iterations"
            break
    tried = np.array(f.tried, dtype=np.float64).reshape(-1, 3)
    alpha = 2.0 ** best_s
    return dict(alpha=alpha, log2_alpha=best_s, distance=best_d, grid_best_log2=grid_best,
                tried_log2_alpha=tried[:, 0], tried_distance=tried[:, 1],
                tried_phase=tried[:, 2].astype(np.int32), iterations=it, stop_reason=reason,
                cloud_hist=cloud_hist,
                photo_hist=luminance_histogram(np.minimum(rgb * alpha, 1.0), cfg.bins, cfg.hist_space))


def registered_exposure(points: np.ndarray, colors: np.ndarray, normals: np.ndarray, photo: np.ndarray,
                        fov_deg: float) -> dict:
    """α from the photo registered against the cloud (:mod:`pipeline.expansion.register_photo`): the photo's
    pose (world→camera ``world_to_camera`` (4,4), OpenCV axes; ``K`` (3,3)), the registration's NCC
    and α = Σ cloud / Σ photo over the photo blocks of cloud points the registered camera sees
    (unclipped, non-dark; ``alpha_sum`` of :func:`pipeline.expansion.register_photo.exposure_from_pose`: the
    block median is biased low by the skewed path-traced noise, −3.9 % on photo_sun)."""
    from . import register_photo as rp
    from ..camera import intrinsics

    h, w = photo.shape[:2]
    K = intrinsics(fov_deg, (w, h))
    reg = rp.register(points, colors, photo, fov_deg, normals=normals)
    ex = rp.exposure_from_pose(points, colors, photo, K, reg.R, reg.eye, normals=normals)
    w2c = pose_matrix(reg.R, reg.eye)
    return dict(alpha=float(ex["alpha_sum"]), ncc=float(reg.score), cover=float(reg.cover), blocks=int(ex["blocks"]), points=int(ex["points"]),
                mad_ln=float(ex["mad_ln"]), world_to_camera=w2c, K=K, eye=np.asarray(reg.eye, float),
                seconds=float(reg.seconds))


def registered_panorama(points: np.ndarray, colors: np.ndarray, normals: np.ndarray, pano: np.ndarray) -> dict:
    """A panorama registered against the cloud (:func:`pipeline.expansion.register_photo.register_panorama`: a level
    panorama's centre ``eye`` [m] and ``yaw_deg``, ``world_to_camera`` (4,4), the point NCC ``ncc``, ``cover``,
    ``margin``) and α = Σ cloud / Σ photo over its 16-px blocks of the points it sees
    (:func:`pipeline.expansion.photo_set.exposure_from_camera`), the keys of :func:`registered_exposure` (``K`` zeros)."""
    from . import register_photo as rp
    from .photo_set import PhotoCam, exposure_from_camera

    h, w = pano.shape[:2]
    reg = rp.register_panorama(points, colors, pano, normals=normals)
    w2c = pose_matrix(reg.R, reg.eye)
    ex = exposure_from_camera(points, colors, normals, pano, PhotoCam(Path("panorama"), "equirect", (w, h), w2c))
    return dict(alpha=float(ex["alpha_sum"]), ncc=float(reg.score), cover=float(reg.cover), blocks=int(ex["blocks"]),
                points=int(ex["points"]), mad_ln=float(ex["mad_ln"]), world_to_camera=w2c, K=np.zeros((3, 3)),
                eye=np.asarray(reg.eye, float), yaw_deg=float(reg.yaw_deg), margin=float(reg.margin),
                seconds=float(reg.seconds))


def choose_alpha(hist_alpha: float, reg: dict | None, cfg: ExposeMatchConfig) -> tuple[float, str, str]:
    """(α, source "histogram"|"register", why) by ``cfg.alpha_from`` (module docstring)."""
    if reg is None:
        return hist_alpha, "histogram", ("--alpha-from histogram" if cfg.alpha_from == "histogram"
                                         else "no --photo-fov: the photo cannot be registered")
    ok_a = np.isfinite(reg["alpha"]) and reg["alpha"] > 0
    cover = float(reg.get("cover", 1.0))
    figures = (f"NCC {reg['ncc']:.3f} (min {cfg.min_register_ncc:g}), cover {cover:.2f} (min {cfg.min_register_cover:g}), "
               f"{reg['blocks']} blocks (min {cfg.min_register_blocks})")
    if cfg.alpha_from == "register":
        if not ok_a:
            raise InputError(None, f"the registered photo sees no usable cloud point ({figures})")
        return reg["alpha"], "register", "--alpha-from register"
    if ok_a and reg["ncc"] >= cfg.min_register_ncc and cover >= cfg.min_register_cover and reg["blocks"] >= cfg.min_register_blocks:
        return reg["alpha"], "register", f"registration confident: {figures}"
    return hist_alpha, "histogram", f"registration not confident: {figures}"


def plot_fit(path, res: dict, cfg: ExposeMatchConfig) -> None:
    """PNG: distance vs log2 α (grid and bisection) and the two histograms at the chosen α."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io import save_figure

    fig, ax = plt.subplots(1, 3, figsize=(15, 4))
    s, d, ph = res["tried_log2_alpha"], res["tried_distance"], res["tried_phase"]
    g = ph == 0
    order = np.argsort(s[g])
    ax[0].plot(s[g][order], d[g][order], ".-", label="grid")
    ax[0].axvline(res["log2_alpha"], color="r", lw=0.8, label=f"log2 α = {res['log2_alpha']:.4f}")
    ax[0].set_xlabel("log2 α [stops]"); ax[0].set_ylabel("Wasserstein distance"); ax[0].legend()
    ax[0].set_title("candidate grid")
    lo, hi = res["grid_best_log2"] - cfg.stop_step, res["grid_best_log2"] + cfg.stop_step
    sel = (s >= lo) & (s <= hi)
    o = np.argsort(s[sel])
    ax[1].plot(s[sel][o], d[sel][o], ".-", color="k", lw=0.5)
    ax[1].scatter(s[sel & (ph == 1)], d[sel & (ph == 1)], c="tab:orange", s=12, label="bisection", zorder=3)
    ax[1].axvline(res["log2_alpha"], color="r", lw=0.8)
    ax[1].set_xlabel("log2 α [stops]"); ax[1].set_title(f"refinement ({res['iterations']} iterations)")
    ax[1].legend()
    b = len(res["cloud_hist"])
    x = (np.arange(b) + 0.5) / b
    ax[2].step(x, res["cloud_hist"], where="mid", label="cloud")
    ax[2].step(x, res["photo_hist"], where="mid", label="clamp(α·photo)")
    ax[2].set_yscale("log"); ax[2].set_xlabel(f"luminance ({cfg.hist_space})"); ax[2].legend()
    ax[2].set_title(f"histograms, distance {res['distance']:.3g}")
    fig.tight_layout()
    save_figure(path, fig)


# ----------------------------------------------------------------------------- the action
def _read_photo(photo) -> np.ndarray:
    """The photo's linear RGB (H, W, 3), negatives clipped (logged); bad input is an InputError naming it."""
    from .. import io

    img = io.read_image(photo)
    if img.shape[2] < 3:
        raise InputError(photo, f"expected an RGB image, got {img.shape[2]} channel(s)")
    rgb = img[..., :3]
    nonfinite = int(np.count_nonzero(~np.isfinite(rgb).all(axis=2)))
    if nonfinite:
        raise InputError(photo, f"{nonfinite} pixels are not finite (NaN or Inf)")
    neg = int(np.count_nonzero((rgb < 0).any(axis=2)))
    if neg:
        log.info("%s: %d pixels with negative values clipped to 0", photo, neg)
        rgb = np.maximum(rgb, 0.0)
    if float(rgb.max(initial=0.0)) <= 0.0:
        raise InputError(photo, "image is entirely black; no exposure can be matched")
    return rgb


def photo_models(cfg: ExposeMatchConfig, photos: list) -> list[str]:
    """Each photo's camera model: ``--photo-model`` one name (every photo) or one per photo, comma-separated
    (another count is a ConfigError naming both)."""
    models = [m.strip() for m in cfg.photo_model.split(",")]
    if len(models) == 1:
        return models * len(photos)
    if len(models) != len(photos):
        from ..errors import ConfigError

        raise ConfigError(f"--photo-model {cfg.photo_model}: {len(models)} models for {len(photos)} photos (give one "
                          "for all, or one per photo in order)")
    return models


def _camera_of(i: int, photo, rgb: np.ndarray, c, colors: np.ndarray, cfg: ExposeMatchConfig, t: Timings,
               model: str = "pinhole", placed: int = 0):
    """Photo ``i``'s camera and its own exposure: (PhotoCam or None, registration dict or None, why). A pinhole
    photo with a field of view (``--photo-fov``, else its EXIF) is registered; an equirect/fisheye one (``model``;
    the ``placed``-th such photo of the set) is placed at its ``--photo-at``."""
    from .photo_set import PhotoCam, exposure_from_camera, placed_camera

    h, w = rgb.shape[:2]
    at = cfg.photo_at[3 * placed:3 * placed + 3] if len(cfg.photo_at) > 3 else cfg.photo_at
    if model == "equirect" and len(at) != 3:
        return _registered_panorama(photo, rgb, c, colors, cfg, t)
    if model != "pinhole":
        if len(at) != 3:
            from ..errors import ConfigError

            raise ConfigError(f"--photo-model {model} needs --photo-at x,y,z for {photo} (three numbers, or "
                              "three per such photo): a fisheye's pose is not searched for")
        rotation, how = None, "world-aligned"
        if model == "equirect":                      # the centre is known, the yaw is not: search it there
            from .register_photo import PLACED_MIN_NCC, level_rotation, placed_panorama_yaw

            with t.step("yaw"):
                yaw, ncc = placed_panorama_yaw(c.points.astype(np.float64), np.clip(colors, 0, 1).astype(np.float64),
                                               rgb.astype(np.float64), np.asarray(at, np.float64))
            if not ncc >= PLACED_MIN_NCC:
                raise InputError(photo, f"the cloud contradicts its placement at --photo-at "
                                        f"{','.join(f'{x:g}' for x in at)}: no yaw there matches it (best NCC {ncc:.2f} "
                                        f"< {PLACED_MIN_NCC:g}); give its true centre, or drop --photo-at to register it")
            rotation, how = level_rotation(yaw), f"yaw {np.degrees(yaw):.2f}° searched at the centre (NCC {ncc:.3f})"
        cam = placed_camera(photo, model, (w, h), at, cfg.photo_fov, rotation=rotation)
        with t.step("exposure"):
            ex = exposure_from_camera(c.points.astype(np.float64), np.clip(colors, 0, 1).astype(np.float64),
                                      c.normals.astype(np.float64), rgb.astype(np.float64), cam)
        if not float(ex["mad_ln"]) <= PLACED_MAX_MAD:
            raise InputError(photo, f"the cloud contradicts its placement at --photo-at "
                                    f"{','.join(f'{x:g}' for x in at)} ({how}): the exposure its points give scatters "
                                    f"by a MAD of ln α of {float(ex['mad_ln']):.2f} (> {PLACED_MAX_MAD:g}); give its "
                                    f"true centre{', or drop --photo-at to register it' if model == 'equirect' else ''}")
        cam.alpha_register = float(ex["alpha_sum"])
        reg = dict(alpha=float(ex["alpha_sum"]), ncc=1.0, cover=1.0, blocks=int(ex["blocks"]), points=int(ex["points"]),
                   mad_ln=float(ex["mad_ln"]), world_to_camera=cam.world_to_camera, K=cam.K, eye=cam.eye, seconds=0.0)
        log.info("%s: %s camera placed at %s (--photo-at; %s); α = %.6g from %d photo blocks (%d points, MAD of ln α "
                 "%.3f)", photo, model, np.round(cam.eye, 3).tolist(), how, reg["alpha"], reg["blocks"], reg["points"],
                 reg["mad_ln"])
        return cam, reg, "--photo-at"
    fov = cfg.photo_fov
    if cfg.alpha_from != "histogram" and fov <= 0:
        from ..camera import exif_fov

        fov, how = exif_fov(photo)
        fov = fov or 0.0
        log.info("photo field of view: %s", f"{fov:.4g}° ({how['by']})" if fov else f"unknown ({how['by']}; --photo-fov sets it)")
    if cfg.alpha_from == "histogram" or fov <= 0:
        return None, None, "--alpha-from histogram" if cfg.alpha_from == "histogram" else "no field of view"
    with t.step("register"):
        reg = registered_exposure(c.points.astype(np.float64), np.clip(colors, 0, 1).astype(np.float64),
                                  c.normals.astype(np.float64), rgb.astype(np.float64), fov)
    log.info("registration: camera at %s, NCC %.3f; α = %.6g from %d photo blocks (%d points, MAD of ln α %.3f) "
             "in %.1f s", np.round(reg["eye"], 2).tolist(), reg["ncc"], reg["alpha"], reg["blocks"],
             reg["points"], reg["mad_ln"], reg["seconds"])
    cam = PhotoCam(Path(photo), "pinhole", (w, h), np.asarray(reg["world_to_camera"], np.float64),
                   np.asarray(reg["K"], np.float64), float(fov), True, float(reg["ncc"]), True, 1.0, float(reg["alpha"]))
    return cam, reg, "registered"


def _registered_panorama(photo, rgb: np.ndarray, c, colors: np.ndarray, cfg: ExposeMatchConfig, t: Timings):
    """:func:`_camera_of` for a panorama without ``--photo-at``: registered (:func:`registered_panorama`); with
    ``--alpha-from histogram`` (no registration) a ConfigError: a panorama is placed or registered, its pixels need
    a camera."""
    from .photo_set import PhotoCam

    if cfg.alpha_from == "histogram":
        from ..errors import ConfigError

        raise ConfigError(f"--alpha-from histogram registers no photo, and the panorama {photo} has no --photo-at: "
                          "give its centre, or let it be registered (--alpha-from auto)")
    h, w = rgb.shape[:2]
    with t.step("register"):
        reg = registered_panorama(c.points.astype(np.float64), np.clip(colors, 0, 1).astype(np.float64),
                                  c.normals.astype(np.float64), rgb.astype(np.float64))
    log.info("%s: panorama registered (level: centre and yaw; no --photo-at): centre %s, yaw %.3f°, NCC %.3f, cover "
             "%.2f, margin %.3f; α = %.6g from %d photo blocks (%d points, MAD of ln α %.3f) in %.1f s", photo,
             np.round(reg["eye"], 3).tolist(), reg["yaw_deg"], reg["ncc"], reg["cover"], reg["margin"], reg["alpha"],
             reg["blocks"], reg["points"], reg["mad_ln"], reg["seconds"])
    cam = PhotoCam(Path(photo), "equirect", (w, h), np.asarray(reg["world_to_camera"], np.float64), np.zeros((3, 3)),
                   0.0, True, float(reg["ncc"]), True, 1.0, float(reg["alpha"]))
    return cam, reg, "registered"


def _joint(cams, rgbs, regs, c, cfg: ExposeMatchConfig, t: Timings) -> dict:
    """Several kept photos: α and k_i fitted jointly (:func:`pipeline.expansion.photo_set.joint_fit`) on the registrations
    and the points two photos see; the pairs that disagree are logged as warnings naming both photos."""
    from .photo_set import joint_fit, pair_ratio, photo_values
    from .splats import knn_splat_radii

    pts, nrm = c.points.astype(np.float64), c.normals.astype(np.float64)
    with t.step("overlap"):
        radii = knn_splat_radii(pts)
        q = np.arange(len(pts))
        vals = [photo_values(pts, nrm, radii, q, rgbs[i].astype(np.float64), cams[i], 1.0) for i in range(len(cams))]
    pairs, pair_log = {}, []
    for i in range(len(cams)):
        for j in range(i + 1, len(cams)):
            r = pair_ratio(vals[i][0], vals[i][1], vals[j][0], vals[j][1])
            n_both = int((vals[i][0] & vals[j][0]).sum())
            if r is not None:
                pairs[(i, j)] = r
            pair_log.append(dict(photos=[str(cams[i].path), str(cams[j].path)], points_both=n_both,
                                 **({} if r is None else {"ratio": float(np.exp(r["ln_ratio"])), "ln_error": r["error"],
                                                          "points_used": r["points"]})))
            log.info("%s and %s: %d cloud points seen by both%s", cams[i].path, cams[j].path, n_both,
                     "" if r is None else f"; photo exposure ratio α_i/α_j = {np.exp(r['ln_ratio']):.5g} ± "
                                          f"{100 * r['error']:.2f} % from {r['points']} of them")
    err = [1.4826 * regs[i]["mad_ln"] / np.sqrt(max(regs[i]["blocks"], 1)) if np.isfinite(regs[i]["mad_ln"]) else 1.0
           for i in range(len(cams))]
    fit = joint_fit([regs[i]["alpha"] for i in range(len(cams))], err, pairs, cfg.min_exposure_error, cfg.disagree_z)
    for i, j, ro, rr, z in fit["disagree"]:
        log.warning("%s and %s: their exposures disagree: the points both see give α_i/α_j = %.4g, their registrations "
                    "%.4g (%.1f× the combined error; --disagree-z %g): has the light changed between the shots, or is one "
                    "registered wrongly?", cams[i].path, cams[j].path, ro, rr, z, cfg.disagree_z)
    return dict(alpha=fit["alpha"], residual=fit["residual"], pairs=pair_log, reg_error=err,
                disagree=[dict(photos=[str(cams[i].path), str(cams[j].path)], overlap_ratio=ro, register_ratio=rr, z=z)
                          for i, j, ro, rr, z in fit["disagree"]])


def run_expose_match(photo, cloud, out_npz, out_photo_ldr, cfg: ExposeMatchConfig, preview=None) -> dict:
    """Read the photo(s) (a file, a folder of them or a list: :func:`pipeline.expansion.photo_set.expand_photos`) and
    cloud_ldr.ply; write exposure.npz, photo_ldr.exr (the reference photo's: the first kept), ``<npz stem>.json``
    (report) and ``<npz stem>_fit.png`` (the distance plot); ``preview``: PNG of photo_ldr. One pinhole photo
    writes what it always did; a set (or a placed panorama/fisheye) adds the ``photos*`` keys
    (:func:`pipeline.expansion.photo_set.set_keys`): the cameras, which photos were kept, and the scales k_i."""
    from .. import io
    from .photo_set import expand_photos, set_keys

    cfg.check()
    t = Timings()
    photos = expand_photos(photo)
    models = photo_models(cfg, photos)
    single = len(photos) == 1 and models[0] == "pinhole"
    photo = photos[0]
    with t.step("read"):
        rgbs = [_read_photo(p) for p in photos]
        c = io.read_cloud(cloud)
    for p, rgb in zip(photos, rgbs):
        log.info("read %s: %dx%d photo, peak %.4g; %s: %d points", p, rgb.shape[1], rgb.shape[0],
                 float(rgb.max()), cloud, len(c))
    colors = c.colors
    if float(colors.max()) > 1.0 + 1e-6:
        log.info("%s: colours above 1 (max %.4g) — not an LDR cloud; clipped to [0,1] for the histogram",
                 cloud, float(colors.max()))
    over = float(np.mean(luminance(np.clip(colors, 0, 1)) > T_L))
    log.info("%.2f%% of the cloud's points are overexposed (LDR luminance > %g)%s", 100 * over, T_L,
             "" if over > 0 else " — α is still computed (the later stages will pass the cloud through)")
    with t.step("match"):
        res = match_exposure(rgbs[0], colors, cfg)
    log.info("Eq. 1: α = %.6g (log2 %.4f), Wasserstein %.4g (%s space), grid best %+g stops, %d bisection "
             "iterations (%s), %d evaluations", res["alpha"], res["log2_alpha"], res["distance"],
             cfg.hist_space, res["grid_best_log2"], res["iterations"], res["stop_reason"],
             len(res["tried_distance"]))
    cams, regs, whys = [], [], []
    for i, (p, rgb) in enumerate(zip(photos, rgbs)):
        cam, reg, how = _camera_of(i, p, rgb, c, colors, cfg, t, models[i], sum(m != "pinhole" for m in models[:i]))
        cams.append(cam), regs.append(reg), whys.append(how)
    # each photo's own α; in a set, a photo without a confident registration is dropped
    chosen = [choose_alpha(res["alpha"], reg, cfg) if cam is None or cam.registered else (reg["alpha"], "placed", "--photo-at")
              for cam, reg in zip(cams, regs)]
    kept = [i for i in range(len(photos)) if cams[i] is not None and chosen[i][1] in ("register", "placed")
            and np.isfinite(chosen[i][0]) and chosen[i][0] > 0]
    if not single:
        for i in range(len(photos)):
            if i not in kept:
                log.warning("%s: dropped from the set of photos (%s): %s", photos[i],
                            "not registered" if regs[i] is None else "its registration is not confident: is it a photo of this room?",
                            chosen[i][2] if regs[i] is not None else whys[i])
                if cams[i] is not None:
                    cams[i].kept = False
        if not kept and models[0] != "pinhole" and regs[0] is not None:
            raise InputError(photos[0], f"not used: the panorama's {chosen[0][2]}, and no other photo is kept: is it a "
                                        "panorama of this room? (--photo-at x,y,z places it)")
        if not kept:
            log.warning("no photo of the set is registered: α from Eq. 1 on %s alone (the others are not used)", photos[0])
    joint = None
    if single or not kept:
        alpha, source, why = choose_alpha(res["alpha"], regs[0], cfg) if cams[0] is None or cams[0].registered \
            else chosen[0]
        ref = 0
    else:
        ref = kept[0]
        if len(kept) == 1:
            alpha, source, why = chosen[ref]
        else:
            sub = [cams[i] for i in kept]
            joint = _joint(sub, [rgbs[i] for i in kept], [regs[i] for i in kept], c, cfg, t)
            for n, i in enumerate(kept):
                cams[i].k = float(joint["alpha"][n] / joint["alpha"][0])
            alpha, source = float(joint["alpha"][0]), "joint"
            why = f"fitted jointly on {len(kept)} photos' registrations and the points two of them see"
            for n, i in enumerate(kept):
                log.info("%s: k = %.5g (α·k = %.6g; its registration alone %.6g, %+.2f %%)", photos[i], cams[i].k,
                         alpha * cams[i].k, regs[i]["alpha"], 100 * (np.exp(joint["residual"][n]) - 1))
    reg = regs[ref]
    log2_alpha = res["log2_alpha"] if source == "histogram" else float(np.log2(alpha))
    msg = (f"α = {alpha:.6g} from the {source} ({why}); Eq. 1 gave {res['alpha']:.6g}"
           + (f", the registration {reg['alpha']:.6g} ({reg['alpha'] / res['alpha'] - 1:+.1%} from Eq. 1)" if reg else ""))
    (log.warning if (reg is not None and source == "histogram") else log.info)(msg)
    stem = Path(out_npz).with_suffix("")
    with t.step("write"):
        ldr = apply_exposure(rgbs[ref], alpha)
        io.write_image(out_photo_ldr, ldr)
        if single:
            pose = {} if reg is None else dict(
                alpha_register=np.float64(reg["alpha"]), register_ncc=np.float64(reg["ncc"]),
                register_blocks=np.int32(reg["blocks"]), photo_K=reg["K"].astype(np.float64),
                photo_world_to_camera=reg["world_to_camera"].astype(np.float64))
        else:
            from .photo_set import PhotoCam

            sset = [cm if cm is not None else PhotoCam(Path(p), m, (r.shape[1], r.shape[0]), kept=False)
                    for cm, p, r, m in zip(cams, photos, rgbs, models)]
            if not kept:
                sset[0].kept = True                        # Eq. 1 on the first: its look-alikes, no direct transfer
            pose = set_keys(sset, Path(out_npz).resolve().parent)
            if reg is not None:
                pose.update(alpha_register=np.float64(reg["alpha"]), register_ncc=np.float64(reg["ncc"]),
                            register_blocks=np.int32(reg["blocks"]))
        io.write_npz(out_npz, "pcrelight.exposure/1",
                     alpha=np.float64(alpha), alpha_histogram=np.float64(res["alpha"]), alpha_source=np.asarray(source),
                     log2_alpha=np.float64(log2_alpha), **pose,
                     distance=np.float64(res["distance"]),
                     tried_log2_alpha=res["tried_log2_alpha"].astype(np.float64),
                     tried_distance=res["tried_distance"].astype(np.float64),
                     tried_phase=res["tried_phase"].astype(np.int32),
                     cloud_hist=res["cloud_hist"].astype(np.float64),
                     photo_hist=res["photo_hist"].astype(np.float64),
                     hist_space=np.asarray(cfg.hist_space), iterations=np.int32(res["iterations"]))
        plot_fit(f"{stem}_fit.png", res, cfg)
        if preview:
            io.write_png(preview, srgb_encode(ldr))
    clipped = float(np.mean((ldr >= 1.0).any(axis=2)))

    def jsonable(r):
        return None if r is None else {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in r.items()}

    report = dict(stage="expose-match", inputs=dict(photo=str(photo) if single else [str(p) for p in photos], cloud=str(cloud)),
                  outputs=dict(exposure=str(out_npz), photo_ldr=str(out_photo_ldr), plot=f"{stem}_fit.png"),
                  config=cfg.as_dict(), alpha=alpha, alpha_source=source, alpha_why=why,
                  alpha_histogram=res["alpha"], log2_alpha=log2_alpha,
                  registration=jsonable(reg),
                  distance=res["distance"], grid_best_log2=res["grid_best_log2"],
                  iterations=res["iterations"], stop_reason=res["stop_reason"],
                  evaluations=len(res["tried_distance"]), photo_size=[rgbs[ref].shape[1], rgbs[ref].shape[0]],
                  cloud_points=len(c), cloud_overexposed_fraction=over,
                  photo_ldr_clipped_fraction=clipped, timings=t.as_dict())
    if not single:
        report["photos"] = [dict(photo=str(p), kept=i in kept, reference=i == ref and bool(kept), how=whys[i],
                                 alpha_own=chosen[i][0], alpha_own_source=chosen[i][1], why=chosen[i][2],
                                 k=(cams[i].k if cams[i] is not None and i in kept else None),
                                 model=models[i], registration=jsonable(regs[i]))
                            for i, p in enumerate(photos)]
        report["joint"] = None if joint is None else dict(pairs=joint["pairs"], disagree=joint["disagree"],
                                                          reg_error_ln=joint["reg_error"],
                                                          residual_ln=joint["residual"].tolist())
    io.write_json(f"{stem}.json", report)
    log.info("wrote %s, %s (%.1f%% pixels clipped) in %.2f s", out_npz, out_photo_ldr, 100 * clipped, t.total)
    return report
