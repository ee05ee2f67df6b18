"""reproject (seed 000 §4.1): HDR-expanded cube-map faces → the overexposed points of the cloud.

Per face i (cameras in ``cameras.npz``, conventions in :mod:`pipeline.expansion.splats`): every
overexposed point p (LDR luminance Y(L(p)) > t_l, CIE Y of linear RGB) is projected; it *sees* the
face when it is in front of the camera, faces it (n·(eye − p) > 0, render-cubemaps' facing test),
its nearest pixel (floor of the continuous pixel coordinates — no interpolation, so a point
on a pixel centre reads exactly that pixel) is covered (A > 0 in the render-cubemaps face) and its
depth d satisfies **d ≤ Z·(1 + depth_tol) + radius_tol·r**, Z being the depth channel there and r the
point's splat radius (relative tolerance, default 2 %, plus one splat radius: a point hidden behind
a surface nearer by more than that is occluded; its own splat — or a neighbour's of the same
surface — is what makes Z ≤ d).  The parameters (splat radius rule, culling, tolerances) are read
from cameras.npz, so the test is exactly render-cubemaps'; --depth-tol/--radius-tol override.

A seen point takes the sample  s = scale · (R, G, B)  of the expanded rendering (``scale`` from
renderings.npz turns the rendering into the cloud's units, 1.0 = LDR white) with quality Q (the
patch SSD: mean squared difference per pixel and channel, [0,1] LDR units; 0 for the operators).
Samples with Q > t_h (default 1) or non-finite values are dropped.  Several samples of a point are
averaged with weights w = 1/(Q + q_eps) for PatchMatch (method ``pmatch``: lower SSD, more weight),
w = 1 for the inverse tone-mapping operators (plain mean).

Transfer (Fig. 2): ``rgb`` (default) — the point takes the averaged colour; ``lum`` — the point keeps
its LDR chromaticity and takes the averaged luminance Ȳ = Σ w Y(s) / Σ w:  H = L · Ȳ / Y(L).  An
overexposed LDR colour is clipped per channel, so its chromaticity is wrong (a warm lamp clips to
near-white): ``lum`` carries that error into the HDR cloud — on the shipped scene it is the demo's
colour cast (relit Lambert object vs the path-traced reference, view1, R/G/B 0.74/0.84/1.04 with
``lum`` against 0.84/0.83/0.80 with ``rgb``; bench/README.md, expansion diagnosis).
``ldr_floor`` (default on; not in the paper): the result is raised to the LDR value where it is
below it (per channel for rgb, on Y for lum) — an overexposed LDR value is a lower bound of the
true one, since LDR = clamp(e·HDR) ≤ e·HDR; the count is reported (``raised_to_ldr``).

Per-point baselines ``landis-pc`` / ``banterle-pc`` (no renderings): :func:`pipeline.expansion.itmo.apply`
on the overexposed points' LDR colours (Banterle with the 3-D expand map of the whole cloud), peak
output = ``peak`` or α · max Y(photo) (:func:`pipeline.expansion.itmo.photo_peak`) from --photo/--exposure.

Registered photo (``photo_direct``, method ``pmatch``): when exposure.npz holds the photo's camera
(expose-match with ``--photo-fov``; the photo and exposure.npz are those given, else the ones patchmatch
read, which renderings.npz records: :func:`inputs_of`), the overexposed points that camera sees (in front, facing it,
not occluded: :func:`photo_samples`) take α × the photo at their projection instead of the faces'
look-alike samples — a geometric correspondence, not a look-alike.  The share of the overexposed
points so seen is logged, a WARNING below ``min_photo_share``.  ``unseen`` says what the overexposed
points the registered photo does *not* see get: ``poisson`` (default) — nothing: invalid, poisson fills
them (H = L + h; with poisson's default ``--rim free`` h is harmonic with the photo's excess over LDR on
the seen points of the same overexposed region as its only boundary — flat where the photo saw one
value — and 0 in a region the photo did not see: never below LDR, never above the brightest seen
excess; with ``--rim dirichlet`` h also falls to 0 at the unsaturated rim);
``ldr`` — their LDR value, a lower bound (source 0, valid); ``lookalike`` — the faces' look-alike
samples (the paper); ``calibrated`` — those look-alikes corrected by their error where the photo saw the same
points (the median photo / look-alike luminance ratio per cluster of similar LDR colour,
:func:`calibrate_lookalikes`; issue 25).  With ``ldr`` every point lies between its LDR value and
(up to α's and the photo's noise) its true value, so a relit Lambert object — irradiance is monotone
in the cloud's radiance — lies between the LDR cloud's rendering and the truth's: never worse than
LDR, pixel by pixel.  ``lookalike`` can overshoot by several times where the photo's saturated
regions are brighter than the unseen ones (bench/README.md, "end to end").

Several photos (issue 25): when exposure.npz holds a set (``photos*`` keys, :mod:`pipeline.expansion.photo_set`), every
kept photo with a camera (any model of :data:`pipeline.camera.MODELS`) is read the same way at α·k_i; a point
seen by several takes their mean weighted by each registration's NCC (1 for a placed panorama). The report
gives each photo's overexposed points (``photos``: seen, seen by it alone), those no photo sees
(``unseen_by_photos``) and their share of the cloud's estimated flux (``unseen_flux_share``: luminance × splat
area, the unseen points at their look-alike value where PatchMatch gave one, else LDR).

Isolated points (``isolated_sides``, default on; issue 25): a point whose splat radius exceeds 2 × its 16 neighbours'
median samples an object below the point spacing — a lamp of a few points whose normals are facets of a sphere the
cloud does not resolve. A photo that shows such an object unoccluded gives every one of its overexposed points its
value (the 3×3 peak at the point's projection), whichever way the point's own normal faces, and the object's few
points do not hide each other (:func:`isolated_any_side`): relight's emitters radiate such an object to every side
alike, so a facet facing away from every photo is the same lamp. In the lamp room a panorama beside the object saw
10 of the 19 lamp points by their normals and none of three of its six lamps; with the rule it reads all 19.

Output per point: ``valid`` (1 = has an HDR colour: kept LDR or projected), ``source`` (0 kept LDR,
1 projected), ``quality`` (0 for kept LDR points; the weighted mean Q of the kept samples for
projected points; for an invalid point the smallest dropped Q, or 1e30 when no face saw it or, with
``--unseen poisson``, when the registered photo did not see it: the faces' samples are not used there).
Invalid points (overexposed, no valid sample) keep their LDR colour and are left to ``poisson``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..color import T_L, luminance, overexposed_mask
from ..config import StageConfig
from ..errors import ConfigError
from ..runtime import Timings, check_interrupt, get_logger
from .splats import (
    DEPTH_TOL, FACING_TEST, RADIUS_TOL, SPLAT_K, SPLAT_SCALE, knn_splat_radii, seen_in_face, shrink_isolated,
)
from .photo_set import photo_values, registered
from .register_photo import photo_samples  # noqa: F401  (the direct transfer's reads; re-exported)
from ..io.workspace import read_faces

log = get_logger("reproject")

NO_SAMPLE_Q = 1e30
PC_METHODS = ("landis-pc", "banterle-pc")
ISOLATED = 2.0   # a point whose splat radius exceeds this × its 16 neighbours' median: an object below the spacing
ISOLATED_WINDOW = 3   # [px] --isolated-sides: an isolated point reads the peak within ± this of its projection
# --unseen: what the overexposed points the registered photo misses get
UNSEEN = {"lookalike": "look-alike samples of the renderings (unverified guesses)",
          "calibrated": "look-alike samples corrected by the look-alikes' error where the photo saw both (per region "
                        "of similar LDR appearance)",
          "ldr": "their LDR values (lower bounds)",
          "poisson": "poisson's fill from the photo's values in their region"}


@dataclass
class ReprojectConfig(StageConfig):
    t_l: float = field(default=T_L, metadata={"help": "overexposure threshold on LDR luminance (CIE Y, linear)"})
    t_h: float = field(default=1.0, metadata={
        "help": "drop samples whose SSD quality Q exceeds this (Q: mean squared difference per pixel and channel, LDR units)"})
    transfer: str = field(default="rgb", metadata={
        "help": "rgb: transfer the photo's colour; lum: keep the LDR chromaticity, transfer luminance (Fig. 2; "
                "a clipped LDR colour has lost its chromaticity: on the small ground truth lum gives the relit "
                "object a blue cast, R/G/B 0.74/0.84/1.04 of the reference against 0.84/0.83/0.80 with rgb)",
        "choices": ("lum", "rgb")})
    method: str = field(default="auto", metadata={
        "help": "auto: the renderings' method (renderings.npz); landis-pc|banterle-pc: expand the points directly",
        "choices": ("auto",) + PC_METHODS})
    depth_tol: float = field(default=-1.0, metadata={
        "help": "relative depth tolerance of the visibility test (seen if d ≤ Z·(1+tol) + radius_tol·r); −1 = as render-cubemaps (cameras.npz)"})
    radius_tol: float = field(default=-1.0, metadata={
        "help": "splat radii added to the depth tolerance; −1 = as render-cubemaps (cameras.npz)"})
    q_eps: float = field(default=1e-4, metadata={"help": "PatchMatch weight 1/(Q + q_eps)"})
    ldr_floor: bool = field(default=True, metadata={
        "help": "projected values never fall below the point's LDR value (its lower bound: LDR = clamp(e·HDR) ≤ e·HDR)"})
    peak: float = field(default=0.0, metadata={
        "help": "peak output of the -pc operators [LDR units]; 0 = α·max Y(photo) from --photo/--exposure"})
    min_photo_share: float = field(default=0.5, metadata={
        "help": "WARNING when the registered photo sees less than this share of the overexposed points"})
    photo_direct: bool = field(default=True, metadata={
        "help": "pmatch: the overexposed points the registered photo sees (exposure.npz with a camera, from "
                "expose-match --photo-fov) take α × the photo at their projection; the renderings give the others"})
    unseen: str = field(default="poisson", metadata={
        "help": "with a registered photo (photo_direct), the overexposed points it does not see: poisson = leave "
                "them to poisson (filled from the photo's values in the same overexposed region; LDR where it saw none); ldr = "
                "keep their LDR value (a lower bound); lookalike = the renderings' look-alike samples (the paper: "
                "on the shipped scene they overshoot, the relit object 2.0–2.3× too bright on view2); calibrated = "
                "the look-alikes times the median photo/look-alike luminance ratio of the seen points of similar LDR "
                "colour (k-means clusters, --calibrate-clusters)",
        "choices": tuple(UNSEEN)})

    isolated_sides: bool = field(default=True, metadata={
        "help": "an isolated overexposed point (an object below the point spacing: a lamp of a few points) takes a "
                "photo's value wherever the photo shows its object unoccluded, whichever way its own normal faces: "
                "its normal is a facet's of an object the cloud does not resolve, and relight's emitters radiate such "
                "an object to every side alike (a lamp room's panorama saw 10 of its 19 lamp points facing it and "
                "none of 3 of its 6 lamps)"})
    calibrate_clusters: int = field(default=8, metadata={
        "help": "--unseen calibrated: the number of LDR-colour clusters (k-means on sRGB-encoded LDR colours) whose "
                "seen points each give a correction; a cluster with fewer than 20 seen points takes all seen points' one"})

    def check(self) -> None:
        self._require(1 <= self.calibrate_clusters <= 256, "calibrate_clusters", "must be in [1, 256]")
        self._require(0.0 <= self.t_l < 1.0, "t_l", "must be in [0, 1) (LDR luminance; patchmatch's rule)")
        self._require(self.t_h >= 0, "t_h", "must be ≥ 0")
        self._require(self.transfer in ("lum", "rgb"), "transfer", "must be lum or rgb")
        self._require(self.method in ("auto",) + PC_METHODS, "method", "must be auto, landis-pc or banterle-pc")
        self._require(self.depth_tol >= 0 or self.depth_tol == -1, "depth_tol", "must be ≥ 0 or −1")
        self._require(self.radius_tol >= 0 or self.radius_tol == -1, "radius_tol", "must be ≥ 0 or −1")
        self._require(self.q_eps > 0, "q_eps", "must be > 0")
        self._require(self.peak == 0 or self.peak >= 1, "peak", "must be 0 (from the photo) or ≥ 1")
        self._require(0 <= self.min_photo_share <= 1, "min_photo_share", "must be in [0, 1]")
        self._require(self.unseen in UNSEEN, "unseen", "must be " + ", ".join(UNSEEN))


# ----------------------------------------------------------------------------- pure functions
def gather_samples(points: np.ndarray, cams: dict[str, np.ndarray], depth: list[np.ndarray],
                   cover: list[np.ndarray], hdr: list[np.ndarray], quality: list[np.ndarray],
                   scale: float, t_h: float, depth_tol: float, weighted: bool, q_eps: float,
                   normals: np.ndarray | None = None, abs_tol: np.ndarray | float = 0.0
                   ) -> dict[str, np.ndarray]:
    """Accumulate the visible, kept samples of every face for ``points`` (M,3).

    Returns per point: ``w`` (Σ weights), ``rgb`` (Σ w·s), ``y`` (Σ w·Y(s)), ``q`` (Σ w·Q),
    ``n`` (kept samples), ``seen`` (faces that see it), ``qmin_drop`` (smallest dropped Q, inf if none).
    """
    m = len(points)
    acc = {"w": np.zeros(m), "rgb": np.zeros((m, 3)), "y": np.zeros(m), "q": np.zeros(m),
           "n": np.zeros(m, dtype=np.int64), "seen": np.zeros(m, dtype=np.int64),
           "qmin_drop": np.full(m, np.inf)}
    for f in range(len(depth)):
        check_interrupt()
        seen, row, col = seen_in_face(points, cams["K"][f], cams["world_to_camera"][f], depth[f], cover[f], depth_tol,
                                      normals, abs_tol)
        idx = np.nonzero(seen)[0]
        if idx.size == 0:
            continue
        s = hdr[f][row[idx], col[idx], :3].astype(np.float64) * scale
        q = quality[f][row[idx], col[idx]].astype(np.float64)
        acc["seen"][idx] += 1
        keep = np.isfinite(s).all(axis=1) & np.isfinite(q) & (q <= t_h) & (s >= 0).all(axis=1)
        drop = idx[~keep]
        if drop.size:
            qd = np.where(np.isfinite(q[~keep]), q[~keep], np.inf)
            np.minimum.at(acc["qmin_drop"], drop, qd)
        idx, s, q = idx[keep], s[keep], q[keep]
        w = 1.0 / (q + q_eps) if weighted else np.ones(len(idx))
        acc["w"][idx] += w
        acc["rgb"][idx] += w[:, None] * s
        acc["y"][idx] += w * luminance(s).astype(np.float64)
        acc["q"][idx] += w * q
        acc["n"][idx] += 1
    return acc


def transfer_colors(ldr: np.ndarray, acc: dict[str, np.ndarray], mode: str, ldr_floor: bool = False
                    ) -> tuple[np.ndarray, np.ndarray, int]:
    """HDR colours of the points with ≥ 1 kept sample: (colours (M,3), has_sample (M,) bool, number
    of points raised to their LDR value by ``ldr_floor`` — per channel for rgb, on Y for lum)."""
    ok = acc["w"] > 0
    out = ldr.astype(np.float64).copy()
    wsum = np.where(ok, acc["w"], 1.0)
    raised = 0
    if mode == "rgb":
        col = acc["rgb"][ok] / wsum[ok, None]
        if ldr_floor:
            low = col < ldr[ok]
            raised = int(low.any(axis=1).sum())
            col = np.maximum(col, ldr[ok])
        out[ok] = col
    else:
        y_new = acc["y"][ok] / wsum[ok]
        y_old = luminance(ldr[ok]).astype(np.float64)
        if ldr_floor:
            raised = int((y_new < y_old).sum())
            y_new = np.maximum(y_new, y_old)
        safe = y_old > 0
        ratio = np.where(safe, y_new / np.where(safe, y_old, 1.0), 0.0)
        col = ldr[ok].astype(np.float64) * ratio[:, None]
        col[~safe] = y_new[~safe, None]  # a black LDR colour has no chromaticity: grey
        out[ok] = col
    return out, ok, raised


def expand_points(method: str, points: np.ndarray, colors: np.ndarray, over: np.ndarray, peak: float) -> np.ndarray:
    """landis-pc / banterle-pc: the operator applied to the overexposed points' LDR colours."""
    from . import itmo

    base = method.removesuffix("-pc")
    if base == "banterle":
        em = itmo.expand_map_points(points, colors)
        return itmo.banterle(colors[over], peak, expand_map=em[over])
    return itmo.apply(base, colors[over], max_luminance=peak)


def visibility_of(cams: dict[str, np.ndarray], cfg: ReprojectConfig) -> dict[str, Any]:
    """The visibility test's parameters: those render-cubemaps stored in cameras.npz (so the test is
    the one that rendered the faces), else render-cubemaps' defaults; ``depth_tol`` ≥ 0 in the
    config overrides the stored one."""
    out = {"splat_k": int(cams.get("splat_k", SPLAT_K)), "splat_scale": float(cams.get("splat_scale", SPLAT_SCALE)),
           "facing_test": bool(int(cams.get("facing_test", int(FACING_TEST)))),
           "depth_tol": float(cams.get("depth_tol", DEPTH_TOL)), "radius_tol": float(cams.get("radius_tol", RADIUS_TOL))}
    if cfg.depth_tol >= 0:
        out["depth_tol"] = cfg.depth_tol
    if cfg.radius_tol >= 0:
        out["radius_tol"] = cfg.radius_tol
    return out


def direct_cameras(ex: dict[str, np.ndarray], exposure: str | Path, photo: str | Path,
                   given: list) -> list[tuple[Any, float, float]]:
    """The photos of the direct transfer: [(camera (:class:`pipeline.expansion.photo_set.PhotoCam`), α·k (photo → cloud
    units), weight)] — exposure.npz's set (its kept photos with a camera; weight = the registration's NCC, 1 for a
    placed panorama), else its one registered camera (weight 1), else none. ``given``: the photos on the command
    line (all of the set's, in order, or they are not used: the recorded ones are)."""
    from .photo_set import PhotoCam, read_set

    alpha = float(ex["alpha"])
    if "photos" in ex:
        n = len(np.atleast_1d(ex["photos"]))
        if given and len(given) != n:
            log.warning("%d photo(s) given, exposure.npz records %d: the recorded ones are used", len(given), n)
        cams = read_set(ex, exposure, given if given and len(given) == n else None)
        return [(c, alpha * c.k, c.quality) for c in cams if c.kept and (c.registered or c.model != "pinhole")]
    if "photo_world_to_camera" in ex:
        h, w = 0, 0
        return [(PhotoCam(Path(photo), "pinhole", (w, h), ex["photo_world_to_camera"], ex["photo_K"]), alpha, 1.0)]
    return []


CALIBRATE_MIN_PAIRS = 20   # seen points with a look-alike that a cluster needs for its own correction


def calibrate_lookalikes(ldr: np.ndarray, lookalike: np.ndarray, has_lookalike: np.ndarray, photo: np.ndarray,
                         seen: np.ndarray, clusters: int = 8, seed: int = 0) -> tuple[np.ndarray, dict[str, Any]]:
    """The look-alike values corrected by their error where the photo saw the same points (``--unseen calibrated``).

    ``ldr``, ``lookalike``, ``photo`` (M,3) linear colours of the overexposed points (LDR, PatchMatch's look-alike,
    α·k × the photo); ``has_lookalike``, ``seen`` (M,) bool. The pairs (seen, with a look-alike, both luminances
    > 0) give r = ln(Y_photo / Y_lookalike). Regions of similar LDR appearance: k-means (scipy's ``kmeans2``,
    seeded, k-means++) on the pairs' sRGB-encoded LDR colours; every point joins its nearest centroid. Each
    cluster with ≥ :data:`CALIBRATE_MIN_PAIRS` pairs corrects by its median r (robust), the others by all pairs'
    median. Returns (look-alike × exp(correction), a report: pairs, the global and per-cluster corrections);
    with fewer pairs than that: the look-alikes unchanged, ``pairs`` says how many."""
    from scipy.cluster.vq import kmeans2, vq

    from ..color import srgb_encode

    y_la, y_ph = luminance(np.asarray(lookalike, np.float64)), luminance(np.asarray(photo, np.float64))
    pairs = np.asarray(seen, bool) & np.asarray(has_lookalike, bool) & (y_la > 0) & (y_ph > 0)
    n = int(pairs.sum())
    if n < CALIBRATE_MIN_PAIRS:
        return np.asarray(lookalike, np.float64).copy(), {"pairs": n, "correction_global": None, "clusters": []}
    r = np.log(y_ph[pairs] / y_la[pairs])
    glob = float(np.median(r))
    feat = srgb_encode(np.clip(np.asarray(ldr, np.float64), 0, 1))
    k = int(min(clusters, max(1, n // CALIBRATE_MIN_PAIRS)))
    cent, _ = kmeans2(feat[pairs], k, minit="++", seed=np.random.default_rng(seed))
    lab, _ = vq(feat, cent)
    corr, info = np.full(k, glob), []
    for j in range(k):
        rj = r[lab[pairs] == j]
        if len(rj) >= CALIBRATE_MIN_PAIRS:
            corr[j] = float(np.median(rj))
        info.append({"ldr_srgb": [round(float(x), 4) for x in cent[j]], "pairs": int(len(rj)),
                     "points": int((lab == j).sum()), "correction": float(np.exp(corr[j]))})
    out = np.asarray(lookalike, np.float64) * np.exp(corr[lab])[:, None]
    return out, {"pairs": n, "correction_global": float(np.exp(glob)), "clusters": info}


def isolated_any_side(points: np.ndarray, normals: np.ndarray, radii: np.ndarray, isolated: np.ndarray,
                      oidx: np.ndarray, photo: np.ndarray, cam, gain: float, seen: np.ndarray,
                      values: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """``--isolated-sides``: the isolated overexposed points (``isolated`` (N,) bool over the cloud; ``oidx`` the
    overexposed indices) that ``seen`` (M,) misses — they face away from the photo, or their object's other points
    hid them — are read again as if they faced it: :func:`pipeline.expansion.photo_set.photo_values` with their normals turned
    to the photo's eye and every isolated point's disc shrunk to 0.1 mm (the few points of one lamp, a few cm apart,
    do not hide each other; the room's surfaces, with their own normals and discs, still do). Their projection lies
    inside their object's silhouette, so the 3×3 peak read is the object's radiance towards the photo. Returns
    (seen, values, the number of points newly read)."""
    iso_o = np.asarray(isolated, bool)[oidx] & ~np.asarray(seen, bool)
    if not iso_o.any():
        return seen, values, 0
    q = np.asarray(oidx)[iso_o]
    nrm = np.array(normals, np.float64)
    d = cam.eye - points[q]
    nrm[q] = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    r = np.where(isolated, 1e-4, radii)
    s2, v2 = photo_values(points, nrm, r, q, photo, cam, gain, isolated=np.ones(len(q), bool))
    seen, values = np.array(seen), np.array(values)
    idx = np.flatnonzero(iso_o)[s2]
    seen[idx] = True
    values[idx] = v2[s2]
    return seen, values, int(s2.sum())


def near_isolated_images(cam, points: np.ndarray, query: np.ndarray, u_iso: np.ndarray, v_iso: np.ndarray,
                         reach: float = ISOLATED_WINDOW + 1) -> np.ndarray:
    """``--isolated-sides``: the indices of the ``query`` (M,) bool points of ``points`` (M,3) whose projection in the
    photo ``cam`` lies within ``reach`` pixels of an isolated point's it shows (``u_iso``, ``v_iso``): the registered
    pose is a few pixels off (:func:`window_peak`), so a read there may be the lamp's — on the lamp room's
    photo_lamps.exr a ceiling point 1.05 m from a lamp, 3.7 px from its image, read 674 × its radiance. Their read of
    this photo is dropped (the other photos', or poisson, give their value)."""
    from scipy.spatial import cKDTree

    q = np.flatnonzero(query)
    if not len(q) or not len(u_iso):
        return q[:0]
    u, v, _ = cam.project(points[q])
    d, _ = cKDTree(np.c_[u_iso, v_iso]).query(np.c_[u, v])
    return q[d <= reach]


def window_peak(photo: np.ndarray, u: np.ndarray, v: np.ndarray, half: int = ISOLATED_WINDOW) -> np.ndarray:
    """(M,3) the photo's pixel of highest luminance within ± ``half`` pixels of each continuous position (u, v): the
    brightest of :func:`pipeline.expansion.register_photo.peak_reads`' 3×3 peaks at offsets −(half−1), …, half−1 in steps of 2.
    A lamp of a pixel or two is found when the registered pose puts its projection a few pixels off (the lamp room's
    photo_lamps.exr: 0.1 m, 2–3 px; the 3×3 peak read the ceiling for 8 of its 19 lamp points)."""
    from .register_photo import peak_reads

    best, out = np.full(len(u), -np.inf), np.zeros((len(u), 3))
    for du in range(-(half - 1), half, 2):
        for dv in range(-(half - 1), half, 2):
            r = peak_reads(photo, np.asarray(u) + du, np.asarray(v) + dv)
            y = luminance(r).astype(np.float64)
            take = y > best
            best[take], out[take] = y[take], r[take]
    return out


def unseen_flux_share(ldr: np.ndarray, radii: np.ndarray, oidx: np.ndarray, estimate: np.ndarray,
                      unseen: np.ndarray) -> float:
    """Share of the cloud's estimated flux (Σ luminance × splat area πr²; the overexposed points at ``estimate``
    (M,3), the others at their LDR colours) carried by the overexposed points ``unseen`` (M,) bool."""
    y = luminance(np.asarray(ldr, np.float64), np.float64).copy()
    y[oidx] = luminance(np.asarray(estimate, np.float64), np.float64)
    f = y * np.asarray(radii, np.float64) ** 2
    tot = float(f.sum())
    return float(f[oidx[unseen]].sum() / tot) if tot > 0 else 0.0


# ----------------------------------------------------------------------------- action
def photo_alone(cfg: ReprojectConfig, photo: str | Path | None, exposure: str | Path | None) -> bool:
    """Whether the cube-map faces cannot change this stage's colours, ``valid`` and ``source``: the registered photo's
    direct transfer (``photo_direct``, a camera in ``exposure``) decides every overexposed point it sees, and
    ``--unseen poisson|ldr`` gives the others no face sample (invalid with their LDR colour and quality 1e30, or
    their LDR value): the faces reach no byte of the output cloud. Requires render-cubemaps' default splat radii,
    which the direct transfer's visibility uses (the planner checks them)."""
    return (cfg.method == "auto" and cfg.photo_direct and cfg.unseen in ("poisson", "ldr") and photo is not None
            and registered(exposure))


def inputs_of(renderings_dir: str | Path, rend: dict[str, np.ndarray], photo: str | Path | None,
              exposure: str | Path | None) -> tuple[str | Path | None, str | Path | None]:
    """The photo and exposure.npz of the direct transfer: those given, else those patchmatch read (recorded in
    renderings.npz by :func:`pipeline.io.file_ref`, checked by SHA-256: a missing or changed one is an
    InputError). A given file that is not the one patchmatch read is a WARNING (its faces and the direct
    transfer then come from different photos or exposures)."""
    from .. import io

    out: list[str | Path | None] = []
    for name, given in (("photo", photo), ("exposure", exposure)):
        if name not in rend:
            out.append(given)
            continue
        rel, digest = str(rend[name]), str(rend[f"{name}_sha256"])
        if given is not None:
            if io.sha256_of(given) != digest:
                log.warning("%s is not the %s patchmatch read (%s, recorded in %s/renderings.npz): the look-alike "
                            "faces and the direct transfer come from different files", given, name, rel, renderings_dir)
            out.append(given)
            continue
        p = io.follow_ref(renderings_dir, rel, digest, f"the {name} patchmatch read")
        log.info("--%s not given: %s, the one patchmatch read (recorded in renderings.npz)", name, p)
        out.append(p)
    if "photo" not in rend and (photo is None or exposure is None):
        log.warning("%s/renderings.npz does not record the photo and exposure patchmatch read (an older patchmatch): "
                    "without --photo and --exposure a registered photo's direct transfer is not made", renderings_dir)
    return out[0], out[1]


def run_reproject(cloud: str | Path, cameras_dir: str | Path | None, renderings_dir: str | Path | None,
                  out_ply: str | Path, cfg: ReprojectConfig, preview: str | Path | None = None,
                  photo: str | Path | None = None, exposure: str | Path | None = None) -> dict[str, Any]:
    """Read the LDR cloud (and the faces), give the overexposed points HDR colours, write the
    cloud with valid/quality/source to ``out_ply`` and a report ``<out stem>.json`` beside it."""
    from .. import io

    t = Timings()
    t0 = time.perf_counter()
    out_ply = Path(out_ply)
    photos_given = [] if photo is None else [photo] if isinstance(photo, (str, Path)) else list(photo)
    if len(photos_given) > 1 or any(Path(p).is_dir() for p in photos_given):
        from .photo_set import expand_photos

        photos_given = expand_photos(photos_given)
    photo = photos_given[0] if photos_given else None
    with t.step("read"):
        c = io.read_cloud(cloud)
    over = overexposed_mask(c.colors, cfg.t_l)
    log.info("%d overexposed points (LDR luminance > %g)", int(over.sum()), cfg.t_l)
    n, n_over = len(c), int(over.sum())
    colors = c.colors.astype(np.float64).copy()
    valid = np.ones(n, dtype=np.uint8)
    source = np.zeros(n, dtype=np.uint8)
    quality = np.zeros(n, dtype=np.float32)
    report: dict[str, Any] = {"input": str(cloud), "cameras": None if cameras_dir is None else str(cameras_dir),
                              "renderings": None if renderings_dir is None else str(renderings_dir),
                              "points": n, "overexposed": n_over, "config": cfg.as_dict()}
    method = cfg.method
    if n_over == 0:
        log.info("no overexposed point: the cloud passes through unchanged (all points valid, kept LDR)")
        report.update({"skipped": "no overexposed point", "method": method, "projected": 0, "invalid": 0})
    elif cfg.method in PC_METHODS:
        report["skipped"] = None
        peak = cfg.peak
        if peak == 0:
            if photo is None or exposure is None:
                raise ConfigError(f"--method {cfg.method} needs --peak or both --photo and --exposure")
            from .itmo import photo_peak

            alpha = float(io.read_npz(exposure, "pcrelight.exposure/1")["alpha"])
            peak = photo_peak(io.read_image(photo), alpha)
            log.info("peak output %.4g (α=%.4g × max Y of %s)", peak, alpha, photo)
        with t.step("expand"):
            exp = expand_points(cfg.method, c.points, c.colors, over, peak)
        colors[over] = exp  # the operators scale luminance and keep chromaticity: lum and rgb agree
        source[over] = 1
        report.update({"method": cfg.method, "peak": peak, "projected": n_over, "invalid": 0})
        log.info("%s: %d overexposed points expanded directly (peak %.4g)", cfg.method, n_over, peak)
    else:
        report["skipped"] = None
        if cameras_dir is None or renderings_dir is None:
            if not photo_alone(cfg, photo, exposure):
                raise ConfigError("reproject needs the CUBEMAPS and RENDERINGS folders (or --method landis-pc|banterle-pc, "
                                  "or --photo and --exposure with a registered camera and --unseen poisson|ldr)")
            # no faces: what they give never reaches the cloud here (see photo_alone)
            cams, rend, depth, cover, hdr, qual = {}, {"method": "pmatch", "scale": 1.0}, [], [], [], []
            log.info("no cube-map faces: the registered photo alone (--unseen %s); the faces would give only the "
                     "unseen points' look-alike samples, which --unseen %s does not use", cfg.unseen, cfg.unseen)
        else:
            with t.step("read faces"):
                cams, rend, depth, cover, hdr, qual = read_faces(cameras_dir, renderings_dir)
        method = str(rend["method"])
        scale = float(rend["scale"])
        if method == "pmatch" and cfg.photo_direct and renderings_dir is not None:
            # several given: the set's reference is checked as recorded (no faces: nothing recorded, the given ones)
            photo, exposure = inputs_of(renderings_dir, rend, photo if len(photos_given) < 2 else None, exposure)
        report.update(photo=None if photo is None else str(photo), exposure=None if exposure is None else str(exposure))
        weighted = method == "pmatch"
        log.info("read %d faces of %s (method %s, scale %.6g); %s mean", len(depth), renderings_dir, method, scale,
                 "quality-weighted" if weighted else "plain")
        oidx = np.nonzero(over)[0]
        vis = visibility_of(cams, cfg)
        report["visibility"] = vis
        with t.step("radii"):
            radii = knn_splat_radii(c.points.astype(np.float64), vis["splat_k"], vis["splat_scale"], query=oidx).astype(np.float64)
        nrm = c.normals[oidx].astype(np.float64) if vis["facing_test"] else None
        with t.step("project"):
            acc = gather_samples(c.points[oidx].astype(np.float64), cams, depth, cover, hdr, qual, scale,
                                 cfg.t_h, vis["depth_tol"], weighted, cfg.q_eps, nrm, vis["radius_tol"] * radii)
            new, ok, raised = transfer_colors(c.colors[oidx], acc, cfg.transfer, cfg.ldr_floor)
        direct = 0
        kept = np.zeros(len(oidx), dtype=bool)   # unseen points kept at LDR (--unseen ldr)
        left = np.zeros(len(oidx), dtype=bool)   # unseen points with look-alike samples left to poisson
        if cfg.photo_direct and method == "pmatch" and exposure is not None and photo is not None:
            ex = io.read_npz(exposure, "pcrelight.exposure/1")
            cams = direct_cameras(ex, exposure, photo, photos_given)
            if cams:
                with t.step("photo direct"):
                    allr = knn_splat_radii(c.points.astype(np.float64), vis["splat_k"], vis["splat_scale"]).astype(np.float64)
                    isor, n_iso = shrink_isolated(c.points.astype(np.float64), allr, ISOLATED)
                    guess = np.where(ok[:, None], new, c.colors[oidx])   # before the photos: look-alike, else LDR
                    wsum, vsum = np.zeros(len(oidx)), np.zeros((len(oidx), 3))
                    per_photo = []
                    seen_by = []
                    iso_all = isor < allr
                    iso_o = iso_all[oidx]
                    n_sides = n_near = 0
                    best_y, best_v = np.full(len(oidx), -np.inf), np.zeros((len(oidx), 3))   # isolated: brightest read
                    for cam, gain, wt in cams:
                        img = io.read_image(cam.path)[..., :3]
                        s_i, v_i = photo_values(c.points.astype(np.float64), c.normals.astype(np.float64), isor, oidx,
                                                img, cam, gain, isolated=iso_all[oidx])
                        if cfg.isolated_sides:
                            s_i, v_i, n_new = isolated_any_side(c.points.astype(np.float64), c.normals.astype(np.float64),
                                                                isor, iso_all, oidx, img, cam, gain, s_i, v_i)
                            n_sides += n_new
                            w_i = s_i & iso_o
                            if w_i.any():
                                u_, v_, _ = cam.project(c.points[oidx[w_i]].astype(np.float64))
                                j_ = near_isolated_images(cam, c.points[oidx].astype(np.float64), s_i & ~iso_o, u_, v_)
                                s_i[j_] = False
                                n_near += len(j_)
                                v_i[w_i] = gain * window_peak(img, u_, v_)
                                y_ = luminance(v_i[w_i]).astype(np.float64)
                                up = y_ > best_y[w_i]
                                j_ = np.flatnonzero(w_i)[up]
                                best_y[j_], best_v[j_] = y_[up], v_i[w_i][up]
                        wsum[s_i] += wt
                        vsum[s_i] += wt * v_i[s_i]
                        seen_by.append(s_i)
                        per_photo.append({"photo": str(cam.path), "model": cam.model, "weight": wt, "scale": gain,
                                          "overexposed_seen": int(s_i.sum())})
                    seen = wsum > 0
                    val = np.zeros((len(oidx), 3))
                    val[seen] = vsum[seen] / wsum[seen][:, None]
                    if cfg.isolated_sides:     # an emitter's reads are only ever too dark (missed, diluted): the brightest
                        b_ = seen & iso_o & np.isfinite(best_y)
                        val[b_] = best_v[b_]
                    nby = np.sum(seen_by, axis=0)
                    for p, s_i in zip(per_photo, seen_by):
                        p["overexposed_only_this"] = int((s_i & (nby == 1)).sum())
                        log.info("%s: sees %d overexposed points (%d seen by no other photo), weight %.3g, α·k = %.6g",
                                 p["photo"], p["overexposed_seen"], p["overexposed_only_this"], p["weight"], p["scale"])
                    report["isolated_points"] = n_iso
                    report["isolated_any_side"] = n_sides
                    report["reads_dropped_near_isolated"] = n_near
                    if cfg.isolated_sides:
                        log.info("%d isolated points (objects below the point spacing), %d of them overexposed; %d photo "
                                 "reads of them facing away from the photo (--isolated-sides: their object is in view); "
                                 "%d reads of other points within %d px of a shown isolated point's image dropped",
                                 n_iso, int(iso_all[oidx].sum()), n_sides, n_near, ISOLATED_WINDOW + 1)
                    if cfg.ldr_floor:
                        val = np.maximum(val, c.colors[oidx])
                    la_new, la_ok = new.copy(), ok.copy()   # PatchMatch's look-alikes, before the photos' values
                    new[seen], ok[seen] = val[seen], True
                    acc["q"][seen], acc["w"][seen] = 0.0, 1.0
                    direct = int(seen.sum())
                    if cfg.unseen == "ldr":
                        kept = ~seen
                        new[kept], ok[kept] = c.colors[oidx][kept], True
                        acc["q"][kept], acc["w"][kept] = 0.0, 1.0
                    elif cfg.unseen == "calibrated":
                        cal, report["calibration"] = calibrate_lookalikes(c.colors[oidx], la_new, la_ok, val, seen,
                                                                          cfg.calibrate_clusters, cfg.seed)
                        fix = ~seen & la_ok
                        new[fix] = np.maximum(cal[fix], c.colors[oidx][fix]) if cfg.ldr_floor else cal[fix]
                        ci = report["calibration"]
                        log.info("--unseen calibrated: %d seen points with a look-alike; look-alike × %s overall, per "
                                 "LDR-colour cluster %s; applied to %d unseen points", ci["pairs"],
                                 "—" if ci["correction_global"] is None else f"{ci['correction_global']:.3g}",
                                 ", ".join(f"{x['correction']:.3g} ({x['pairs']})" for x in ci["clusters"]) or "none",
                                 int(fix.sum()))
                    elif cfg.unseen == "poisson":
                        left = ~seen & ok
                        ok[~seen] = False
                        # their look-alike samples are not used: they keep their LDR colour, as every invalid
                        # point does, and no dropped sample (so the faces reach no byte of the cloud)
                        new[~seen] = c.colors[oidx][~seen]
                        acc["qmin_drop"][~seen] = np.inf
                    share = unseen_flux_share(c.colors, allr, oidx, np.where(seen[:, None], val, guess), ~seen)
                report["photos"] = per_photo
                report["unseen_by_photos"] = int((~seen).sum())
                report["unseen_flux_share"] = share
                log.info("%d of %d overexposed points are seen by the %s: they take α·k × the photo there; "
                         "the others (--unseen %s): %s", direct, n_over,
                         "registered photo" if len(cams) == 1 else f"{len(cams)} photos", cfg.unseen, UNSEEN[cfg.unseen])
                log.info("%d overexposed points stay unseen by every photo: %.1f%% of the cloud's estimated flux (their "
                         "look-alike values where PatchMatch gave one, else LDR; flux ∝ luminance × splat area)",
                         int((~seen).sum()), 100 * share)
                report["unseen"] = cfg.unseen
                if direct < cfg.min_photo_share * n_over:
                    log.warning("only %.1f%% of the overexposed points are in the photo: the others' HDR values are "
                                "%s — a photo of the other bright regions (lamps, windows, sun patches) would pin them",
                                100.0 * direct / n_over, UNSEEN[cfg.unseen])
            else:
                log.info("exposure.npz has no registered camera (expose-match without --photo-fov): no direct photo transfer")
        colors[oidx] = new
        pid = oidx[ok]
        bad = oidx[~ok]
        source[pid] = 1
        quality[pid] = (acc["q"][ok] / acc["w"][ok]).astype(np.float32)
        source[oidx[kept]] = 0
        valid[bad] = 0
        qd = acc["qmin_drop"][~ok]
        quality[bad] = np.where(np.isfinite(qd), qd, NO_SAMPLE_Q).astype(np.float32)
        n_unseen = int((acc["seen"][~ok] == 0).sum())
        n_left = int(left.sum())
        report.update({"method": method, "scale": scale, "weighting": "1/(Q+q_eps)" if weighted else "plain",
                       "faces": len(depth), "projected": int(ok.sum()) - int(kept.sum()), "invalid": int(len(bad)),
                       "invalid_unseen": n_unseen, "invalid_all_dropped": int(len(bad)) - n_unseen - n_left,
                       "invalid_unseen_by_photo": n_left,
                       "samples_kept": int(acc["n"].sum()), "raised_to_ldr": raised, "from_photo": direct,
                       "kept_ldr_unseen": int(kept.sum()),
                       "samples_per_projected_point": float(acc["n"][ok].mean()) if ok.any() else 0.0})
        log.info("%d of %d overexposed points projected (%.1f%%), %d kept at LDR; %d invalid (%d seen by no face, "
                 "%d with every sample's Q > %g, %d unseen by the photo) → poisson", int(ok.sum()) - int(kept.sum()),
                 n_over, 100 * (ok.sum() - kept.sum()) / max(n_over, 1), int(kept.sum()), len(bad), n_unseen,
                 len(bad) - n_unseen - n_left, cfg.t_h, n_left)
        if cfg.ldr_floor:
            log.info("%d projected points were below their LDR value and were raised to it (--no-ldr-floor to keep them)",
                     raised)
    out = io.Cloud(c.points, c.normals, colors.astype(np.float32), valid=valid, quality=quality, source=source)
    with t.step("write"):
        io.write_cloud(out_ply, out)
    if preview is not None:
        from .splats import preview_cloud

        preview_cloud(preview, out)
    report.update({"output": str(out_ply), "transfer": cfg.transfer, "timings": t.as_dict(),
                   "seconds": time.perf_counter() - t0})
    io.write_json(out_ply.with_suffix(".json"), report)
    log.info("wrote %s (%d points) in %.2f s", out_ply, n, time.perf_counter() - t0)
    return report
