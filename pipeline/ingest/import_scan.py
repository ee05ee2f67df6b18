"""import: a scan as users bring it → the pipeline's point cloud (metres, +Y up, right-handed, linear
LDR colours, unit normals), ``pcrelight import SCAN --out cloud.ply``.

Reading is :mod:`pipeline.io`'s (:func:`pipeline.io.read_scan`, by suffix through
:data:`pipeline.io.CLOUD_READERS`: PLY, PCD, XYZ/XYZN/XYZRGB, PTS, E57, LAS/LAZ, no parser of our own); it
gives positions in file units and linear colours in [0, 1]; anything above 1 is clipped here (counted, a
warning).

Every decision below is logged with the number that decided it and written to ``<out stem>.json``.

1. **Non-finite points** (NaN/Inf: invalid returns of organised PCD/E57 scans) are dropped and counted
   (a PLY with them is refused by the PLY reader, as everywhere in the pipeline).
2. **Outliers** (raw units, so before the units are known), two rules:
   *isolated* — a point with fewer than ``outlier_neighbours`` other points within ``outlier_radius`` ×
   the median nearest-neighbour spacing (the criterion of Open3D's ``remove_radius_outlier``, evaluated
   with one k-NN query of scipy's cKDTree: 0.5 s instead of 4 s on the 200k-point sample);
   *far* — a point outside the box of the 0.1–99.9th percentiles of every axis grown on every side by
   ``far_margin`` × its largest side (a cluster of stray returns seen through a window passes the first
   rule). Both depend on the room only through medians and percentiles, which a few outliers do not move,
   so a scan with 10 outliers 50 m away gives the clean scan's cloud exactly (``tests/test_import_scan.py``).
   Not Open3D's statistical rule: on the shipped sample it removed 426 points, 68 of them lamp and sun
   points (LDR luminance > 0.95) — the light this pipeline exists to keep. Removed points that are
   overexposed (LDR luminance > t_l = 0.9, what the HDR expansion works on) are counted and warned about
   (``--outlier-neighbours 0`` and ``--far-margin 0`` keep every point).
3. **Units** (``units``: auto, m, cm, mm): E57 is metres by its standard. Otherwise the room's size s =
   the geometric mean of the sides of its bounding box (each at least 1 % of the largest) in file units
   decides: s < 100 → metres, 100 ≤ s < 2500 → centimetres (a 1–25 m room), s ≥ 2500 → millimetres (a
   room of 2.5 m and up). Between 1500 and 4000 both cm and mm give a plausible room (1.5–40 m): the log
   warns and ``--units`` decides. The shipped atrium is 30 × 24 × 14 m: s = 21.6 m.
4. **Down-sampling** (``max_points`` > 0 and more points than that): averages on a voxel grid (positions,
   linear colours, normals renormalised) whose size is the smallest found by bisection (to 0.1 %) that
   leaves ≤ ``max_points`` voxels; its size in metres is logged. Output order: by voxel, deterministic.
5. **Normals**: as read, or estimated (:func:`pipeline.io.estimate_normals`: k-NN PCA oriented towards
   the centroid, as for every cloud without normals) on the cleaned, down-sampled cloud.
6. **Up axis** (``up``: auto, x, y, z, -x, -y, -z): the floor is the largest plane at an end of an axis:
   for each of the six ends, the points within 5 % of the axis' extent of that end whose normal is within
   25° of the axis (either sign: given normals may face out) are counted; the end with the most is the
   floor and up points from it into the room. (Not "the most normals along an axis": the sample's long
   walls hold 79 944 such points against the floor and roof's 78 769.) A runner-up above 90 % of the
   winner is warned about. The cloud is then rotated (a proper rotation: right-handed stays
   right-handed) so that up is +Y: +z up maps (x, y, z) → (x, z, −y), as glTF exporters do.
7. **Far from the origin** (georeferenced LAS, E57 in site coordinates): when a coordinate exceeds 1 km
   (float32 would keep less than 0.1 mm) the cloud is shifted by its bounding-box centre rounded to 1 m;
   the shift is in the report.

Bad input (a file that is missing, of an unknown suffix, unreadable, empty, without colours, or whose every
point is an outlier) is one line ``pcrelight: <file>: <problem>``, exit 1; nothing is written before the
end, and then atomically (the cloud, then its report).
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import io
from ..color import T_L
from ..config import StageConfig
from ..errors import ConfigError, InputError
from ..runtime import Timings, get_logger, held_stops

log = get_logger("import")

UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}
UP_CHOICES = ("auto", "x", "y", "z", "-x", "-y", "-z")
M_BELOW, MM_FROM = 100.0, 2500.0          # the units rule on the room's size s (file units)
AMBIGUOUS = (1500.0, 4000.0)              # cm and mm both plausible for s in this band
SLAB, FLOOR_COS, TIE = 0.05, math.cos(math.radians(25.0)), 0.9  # the up rule
FAR_Q = 0.1                               # percentiles of the far rule
OVEREXPOSED = T_L                         # LDR luminance t_l (reproject): a removed point this bright may be a lamp
RECENTRE_ABOVE = 1000.0                   # metres


@dataclass
class ImportConfig(StageConfig):
    units: str = field(default="auto", metadata={
        "help": "units of the scan's coordinates; auto: E57 is metres, else from the room's size (log)",
        "choices": ("auto", "m", "cm", "mm")})
    up: str = field(default="auto", metadata={
        "help": "the scan's up axis (output: +Y up); auto: the normal of the largest plane at an axis' end (the floor)",
        "choices": UP_CHOICES})
    max_points: int = field(default=0, metadata={
        "help": "voxel down-sampling to at most this many points [points]; 0: keep every point"})
    outlier_radius: float = field(default=8.0, metadata={
        "help": "isolated-outlier radius [median nearest-neighbour spacings]"})
    outlier_neighbours: int = field(default=1, metadata={
        "help": "a point with fewer other points within the radius is an outlier [points]; 0: rule off"})
    far_margin: float = field(default=0.5, metadata={
        "help": "points beyond the 0.1-99.9th percentile box grown by this × its largest side are outliers "
                "[fraction]; 0: rule off"})

    def check(self) -> None:
        self.check_choices()
        self._require(self.max_points >= 0, "max_points", "must be ≥ 0 (0: no limit)")
        self._require(self.max_points == 0 or self.max_points >= 8, "max_points", "must be 0 or ≥ 8")
        self._require(self.outlier_radius > 0, "outlier_radius", "must be > 0")
        self._require(self.outlier_neighbours >= 0, "outlier_neighbours", "must be ≥ 0 (0: rule off)")
        self._require(self.far_margin >= 0, "far_margin", "must be ≥ 0 (0: rule off)")


# --------------------------------------------------------------------------- decisions (pure)
def find_outliers(points: np.ndarray, colors: np.ndarray, cfg: ImportConfig) -> tuple[np.ndarray, dict[str, Any]]:
    """Boolean mask of outliers (module docstring, step 2) and the numbers that decided it."""
    from scipy.spatial import cKDTree

    from ..color import luminance

    n = len(points)
    info: dict[str, Any] = {}
    out = np.zeros(n, dtype=bool)
    if cfg.outlier_neighbours > 0 and n > cfg.outlier_neighbours:
        k = cfg.outlier_neighbours
        with held_stops():   # SciPy's worker threads use these arrays
            d, _ = cKDTree(points).query(points, k=k + 1, workers=-1)
        spacing = float(np.median(d[:, 1]))
        radius = cfg.outlier_radius * spacing
        iso = d[:, k] > radius
        out |= iso
        info.update(spacing=spacing, radius=radius, isolated=int(iso.sum()))
        log.info("outliers, isolated: %d points with fewer than %d other point(s) within %.4g (= %g × the median "
                 "spacing %.4g, file units)", int(iso.sum()), k, radius, cfg.outlier_radius, spacing)
    if cfg.far_margin > 0:
        lo, hi = np.percentile(points, [FAR_Q, 100.0 - FAR_Q], axis=0)
        grow = cfg.far_margin * float((hi - lo).max())
        far = np.any((points < lo - grow) | (points > hi + grow), axis=1)
        out |= far
        info.update(box_min=lo.tolist(), box_max=hi.tolist(), margin=grow, far=int(far.sum()))
        log.info("outliers, far: %d points outside the %g–%g percentile box grown by %.4g (= %g × its largest side, "
                 "file units)", int(far.sum()), FAR_Q, 100 - FAR_Q, grow, cfg.far_margin)
    info["removed"] = int(out.sum())
    if out.any():
        bright = int(np.count_nonzero(luminance(colors[out]) > OVEREXPOSED))
        info["removed_bright"] = bright
        if bright:
            log.warning("%d of the removed points are overexposed (LDR luminance > %g): lamps? (--outlier-neighbours 0 "
                        "and --far-margin 0 keep them)", bright, OVEREXPOSED)
    return out, info


def detect_units(points: np.ndarray, fmt: str, cfg: ImportConfig) -> tuple[str, dict[str, Any]]:
    """The scan's unit (module docstring, step 3) and the numbers that decided it."""
    side = points.max(axis=0) - points.min(axis=0)
    floor = max(float(side.max()) * 0.01, 1e-12)
    size = float(np.exp(np.mean(np.log(np.maximum(side, floor)))))
    info: dict[str, Any] = {"sides": side.tolist(), "size": size}
    if cfg.units != "auto":
        unit, info["by"] = cfg.units, "given (--units)"
    elif fmt == "E57":
        unit, info["by"] = "m", "E57 stores metres (ASTM E2807)"
    else:
        unit = "m" if size < M_BELOW else "cm" if size < MM_FROM else "mm"
        info["by"] = (f"detected: room size s = {size:.4g} (geometric mean of the box sides); s < {M_BELOW:g} → m, "
                      f"< {MM_FROM:g} → cm, else mm")
        if AMBIGUOUS[0] <= size < AMBIGUOUS[1]:
            log.warning("units: room size %.4g is a plausible room in cm (%.3g m) and in mm (%.3g m); chose %s "
                        "(rule: below %g cm, from there mm); pass --units to be sure", size, size * 0.01,
                        size * 0.001, unit, MM_FROM)
            info["ambiguous"] = True
    info["unit"] = unit
    log.info("units: %s (%s); the room is %s m", unit, info["by"],
             " × ".join(f"{s * UNITS[unit]:.3g}" for s in side))
    return unit, info


ROTATIONS: dict[str, np.ndarray] = {  # proper rotations taking the named axis to +Y
    "y": np.eye(3), "-y": np.diag([1.0, -1.0, -1.0]),
    "z": np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]), "-z": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),
    "x": np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]), "-x": np.array([[0.0, 1, 0], [-1, 0, 0], [0, 0, 1]]),
}


def detect_up(points: np.ndarray, normals: np.ndarray, cfg: ImportConfig) -> tuple[str, dict[str, Any]]:
    """The scan's up axis (module docstring, step 6) and the numbers that decided it."""
    if cfg.up != "auto":
        log.info("up: %s (given)", cfg.up)
        return cfg.up, {"up": cfg.up, "by": "given (--up)"}
    lo, hi = points.min(axis=0), points.max(axis=0)
    scores: dict[str, int] = {}
    for a, name in enumerate("xyz"):
        slab = SLAB * (hi[a] - lo[a])
        along = np.abs(normals[:, a]) >= FLOOR_COS
        scores[name] = int(np.count_nonzero(along & (points[:, a] <= lo[a] + slab)))      # floor at the low end
        scores["-" + name] = int(np.count_nonzero(along & (points[:, a] >= hi[a] - slab)))  # at the high end
    ranked = sorted(scores, key=lambda k: (-scores[k], UP_CHOICES.index(k)))
    up, second = ranked[0], ranked[1]
    info = {"up": up, "by": (f"detected: the largest plane at an axis' end (points within {SLAB:.0%} of the extent "
                             f"of that end, normal within 25° of the axis)"), "scores": scores,
            "runner_up": second}
    log.info("up: %s (floor: %d plane points at that end; runner-up %s: %d)", up, scores[up], second, scores[second])
    if scores[up] == 0 or scores[second] >= TIE * scores[up]:
        info["ambiguous"] = True
        log.warning("up: %s and %s are close (%d vs %d floor-like points); pass --up to be sure", up, second,
                    scores[up], scores[second])
    return up, info


def voxel_size_for(points: np.ndarray, max_points: int) -> tuple[float, int]:
    """The smallest voxel size (to 0.1 %, bisection in log scale) leaving ≤ ``max_points`` occupied voxels."""
    lo_b = points.min(axis=0)
    span = float((points.max(axis=0) - lo_b).max())

    def count(v: float) -> int:
        return len(np.unique(_voxel_keys(points, lo_b, v)))

    lo, hi = span / 2 ** 20, span * 1.01  # hi: one voxel a side → ≤ 8 voxels ≤ max_points
    for _ in range(60):
        if hi / lo < 1.001:
            break
        mid = math.sqrt(lo * hi)
        if count(mid) > max_points:
            lo = mid
        else:
            hi = mid
    return hi, count(hi)


def _voxel_keys(points: np.ndarray, origin: np.ndarray, v: float) -> np.ndarray:
    ijk = np.floor((points - origin) / v).astype(np.int64)
    dims = ijk.max(axis=0) + 1
    return (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]


def voxel_average(points: np.ndarray, colors: np.ndarray, normals: np.ndarray | None, v: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Average positions, linear colours and normals (renormalised) per occupied voxel, ordered by voxel."""
    keys = _voxel_keys(points, points.min(axis=0), v)
    _, inv, cnt = np.unique(keys, return_inverse=True, return_counts=True)

    def mean(a: np.ndarray) -> np.ndarray:
        return np.stack([np.bincount(inv, weights=a[:, j], minlength=len(cnt)) for j in range(a.shape[1])], axis=1) / cnt[:, None]

    p = mean(points)
    c = mean(colors.astype(np.float64))
    n = None
    if normals is not None:
        s = mean(normals.astype(np.float64))
        ln = np.linalg.norm(s, axis=1)
        first = np.full(len(cnt), -1)
        first[inv[::-1]] = np.arange(len(inv))[::-1]  # a voxel's first point: its normal where the sum cancels
        bad = ln < 1e-6
        s[bad] = normals[first[bad]]
        ln[bad] = 1.0
        n = (s / ln[:, None]).astype(np.float32)
    return p, c.astype(np.float32), n


def import_scan(scan: io.Scan, cfg: ImportConfig, where: str | os.PathLike = "<scan>"
                ) -> tuple[Any, dict[str, Any]]:
    """The scan → a :class:`pipeline.io.Cloud` in metres, +Y up (module docstring) and the report."""

    rep: dict[str, Any] = {"format": scan.info.get("format"), "read": {**scan.info, "points": len(scan.points)}}
    pts, cols, nrm = scan.points, scan.colors, scan.normals
    fin = np.isfinite(pts).all(axis=1) & (np.isfinite(nrm).all(axis=1) if nrm is not None else True)
    rep["read"]["nonfinite_dropped"] = int((~fin).sum())
    if not fin.all():
        log.info("dropped %d points with non-finite positions or normals (invalid returns)", int((~fin).sum()))
        if not fin.any():
            raise InputError(where, "every point has a non-finite position (NaN or Inf)")
        pts, cols, nrm = pts[fin], cols[fin], (nrm[fin] if nrm is not None else None)
    over = int(np.count_nonzero((cols > 1.0).any(axis=1)))
    if over:
        log.warning("%d points have colours above 1 (max %.4g): clipped to 1 (an LDR scan's white)", over, float(cols.max()))
        cols = np.minimum(cols, 1.0)
    rep["read"]["clipped_above_1"] = over

    bad, rep["outliers"] = find_outliers(pts, cols, cfg)
    if bad.all():
        raise InputError(where, f"every one of its {len(pts)} points is an outlier (see --outlier-radius, --far-margin)")
    pts, cols, nrm = pts[~bad], cols[~bad], (nrm[~bad] if nrm is not None else None)

    unit, rep["units"] = detect_units(pts, rep["format"], cfg)
    pts = pts * UNITS[unit]

    rep["downsample"] = None
    if cfg.max_points and len(pts) > cfg.max_points:
        v, kept = voxel_size_for(pts, cfg.max_points)
        before = len(pts)
        pts, cols, nrm = voxel_average(pts, cols, nrm, v)
        rep["downsample"] = {"voxel_m": v, "before": before, "after": len(pts)}
        log.info("down-sampled %d → %d points (voxel %.4g m, the smallest that leaves ≤ %d)", before, len(pts), v,
                 cfg.max_points)

    if nrm is None:
        nrm = io.estimate_normals(pts)
        rep["normals"] = "estimated (k-NN PCA, oriented towards the centroid)"
        log.info("normals: estimated for %d points (k-NN PCA, oriented towards the centroid)", len(pts))
    else:
        rep["normals"] = "given"
    up, rep["up"] = detect_up(pts, nrm, cfg)
    r = ROTATIONS[up]
    pts = pts @ r.T
    nrm = (nrm.astype(np.float64) @ r.T).astype(np.float32)

    rep["shift_m"] = None
    if np.abs(pts).max() > RECENTRE_ABOVE:
        shift = np.round((pts.min(axis=0) + pts.max(axis=0)) / 2.0)
        pts = pts - shift
        rep["shift_m"] = shift.tolist()
        log.info("shifted by %s m (a coordinate was beyond %g m: float32 keeps < 0.1 mm there)", shift.tolist(),
                 RECENTRE_ABOVE)
    cloud = io.Cloud(pts.astype(np.float32), nrm.astype(np.float32), cols.astype(np.float32)).validate(where)
    rep["output"] = {"points": len(cloud), "min_m": cloud.points.min(axis=0).tolist(),
                     "max_m": cloud.points.max(axis=0).tolist()}
    return cloud, rep


def _preview(path: str | os.PathLike, cloud: Any, size: int = 384) -> None:
    """Plan (from above: each pixel the lowest point, the floor) and elevation (from −Z: the farthest
    point, the back wall), sRGB-encoded, side by side."""
    from ..color import srgb_encode

    p, c = cloud.points.astype(np.float64), srgb_encode(cloud.colors)
    panels = []
    for u, v, depth, pick_min in ((0, 2, 1, True), (0, 1, 2, False)):
        lo = p[:, [u, v]].min(axis=0)
        span = max(float((p[:, [u, v]].max(axis=0) - lo).max()), 1e-9)
        ij = np.minimum(((p[:, [u, v]] - lo) / span * (size - 1)).astype(np.int64), size - 1)
        order = np.argsort(p[:, depth] if not pick_min else -p[:, depth], kind="stable")  # the last write wins
        img = np.zeros((size, size, 3), np.float32)
        img[size - 1 - ij[order, 1], ij[order, 0]] = c[order]
        panels.append(img)
    io.write_png(path, np.concatenate([panels[0], np.ones((size, 4, 3), np.float32), panels[1]], axis=1))


def run_import(scan_path: str | os.PathLike, out: str | os.PathLike, cfg: ImportConfig,
               preview: str | os.PathLike | None = None) -> dict[str, Any]:
    """Read ``scan_path``, make it the pipeline's cloud, write ``out`` (PLY) and ``<out stem>.json``."""
    from ..io.workspace import report_of

    out = Path(out)
    if out.suffix.lower() != ".ply":
        raise ConfigError(f"--out {out}: the output must be a .ply file (the pipeline's point cloud)")
    t = Timings()
    t0 = time.perf_counter()
    with t.step("read"):
        scan = io.read_scan(scan_path)
    log.info("read %s: %d points (%s; colours %s; normals %s)", scan_path, len(scan.points), scan.info.get("format"),
             scan.info.get("colours"), "given" if scan.normals is not None else "none")
    with t.step("import"):
        cloud, rep = import_scan(scan, cfg, scan_path)
    with t.step("write"):
        io.write_cloud(out, cloud)
    if preview:
        with t.step("preview"):
            _preview(preview, cloud)
    report = {"input": str(scan_path), "output": str(out), **rep, "config": cfg.as_dict(),
              "timings": t.as_dict(), "seconds": round(time.perf_counter() - t0, 3)}
    io.write_json(report_of(out), report)
    log.info("wrote %s: %d points, metres, +Y up (%s)", out, len(cloud), report_of(out))
    return report
