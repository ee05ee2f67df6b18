"""render-cubemaps (seed 000 §4.1): LDR cloud → cube maps of point splats with depth + cameras.npz.

The cube-map conventions (face order, cameras, pixels, EXR channels) and the disc splatter (radii, depth
sprites, the numba and GL routes) live in :mod:`pipeline.expansion.splats`, shared with reproject and register_photo;
this stage chooses the viewpoints, renders the cube maps there and writes them.

Facing (``facing_test``, default on): a point whose normal faces away from the eye (n·(eye − p) ≤ 0)
is not counted as seen — a surface seen from behind (e.g. a roof seen from above, outside the
scene) is not a view of it.  ``backface_cull`` (default off) also stops drawing such splats; off,
every splat is opaque from both sides, as a thin single-layer surface (a drape) is.

Visibility (coverage here, and the same test in reproject, whose parameters are stored in
cameras.npz): a point is *seen* by a face when it faces the eye, its nearest pixel is covered and
its depth d ≤ Z·(1 + depth_tol) + radius_tol·r (Z the depth channel there, r its splat radius: a
neighbour's splat of the same surface may win the point's own pixel at grazing angles).

Stray points: Open3D's statistical outlier removal rule (``outlier_neighbors``, ``outlier_std``; computed on the k-d
tree query the splat radii share, :func:`pipeline.expansion.splats.statistical_inliers`) flags
points far from the others (scanner strays, 50 m away: their spacing radius is tens of metres, so
their depth sprites would cover whole faces, and they stretch the bounding box the viewpoint search
fills).  Flagged points do not set the bounding volumes of the viewpoint search (the box, hence the
lattice, the clearance and the in-box test of the normal candidates) and are drawn with at most the
median splat radius; they are still drawn and counted, since on clean clouds the test also flags
isolated real points — at the default 10 σ, 13 of the 200 000 points of the small ground truth,
all of them on the small bright sun (3 σ: 426, 66 overexposed), none of the tiny one's.  Counts
are logged and reported (``outliers``).  A coverage of the overexposed points below ``coverage``
is a WARNING, automatic viewpoints or not.

Automatic viewpoints (when ``viewpoints`` is empty)
---------------------------------------------------
Candidates: (a) the cell centres of a lattice of about ``grid``³ cells filling the bounding box,
kept when their nearest point is ≥ ``clearance`` away (default: 3 % of the box diagonal, at least 2
median splat radii); (b) in front of ``normal_seeds`` random overexposed points, p + h·n(p) for
h = 1, 2, 4, 8 × base (base = max(median radius, 1 % of the diagonal)), kept when their nearest
point is ≥ max(h/2, median radius) away — this reaches narrow spaces (a light shaft) the lattice
misses.  For each candidate a cheap ``probe_size``² cube map of (a random subset of at most
``probe_points`` of, radii × sqrt(N/subset)) the cloud is splatted; a candidate whose cube map is
covered on less than ``min_enclosure`` (90 %) of its pixels is outside the (closed) scene and is
dropped (all are kept, with a warning, if none passes).  Each overexposed point (LDR luminance >
t_l; a random subset of at most ``probe_targets``) is seen by the visibility test above with
tolerance ``probe_tol``.  Greedy selection: repeatedly take the candidate that sees the most
not-yet-covered overexposed points (ties → lowest candidate index) until the covered fraction ≥
``coverage`` or ``max_views`` views or no candidate adds a point.  The coverage actually reached by
the full-resolution cube maps is logged and reported (``coverage``; a warning when below target).

Model only what the scene requires: a cloud without overexposed points gets no cube map
(``cameras.npz`` with F = V = 0, a log line and ``skipped`` in the report).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..camera import cube_cameras
from ..color import T_L, overexposed_mask
from ..config import StageConfig, sub_seed
from ..errors import ConfigError
from ..runtime import Timings, check_interrupt, get_logger, held_stops, progress
from .splats import (
    DEPTH_TOL, FACING_TEST, RADIUS_TOL, SPLAT_K, SPLAT_SCALE, candidate_viewpoints, cross_layout, knn_distances,
    knn_splat_radii, render_cube_map, seen_in_face, splat_cube_faces, statistical_inliers,
)
from ..io.workspace import FaceFolder, write_faces

log = get_logger("render-cubemaps")


@dataclass
class RenderCubemapsConfig(StageConfig):
    size: int = field(default=1024, metadata={"help": "cube-map face size [pixels] (square faces)"})
    renderer: str = field(default="numba", metadata={
        "help": "numba: CPU disc splatter; gl: GL point sprites (pipeline/gl.py; same rules, 24-bit depth ties)",
        "choices": ("numba", "gl")})
    viewpoints: list[list[float]] = field(default_factory=list, metadata={
        "help": "cube-map centres [m] as x,y,z triples (TOML: [[x,y,z], ...]); empty = choose automatically"})
    max_views: int = field(default=6, metadata={"help": "most viewpoints chosen automatically"})
    coverage: float = field(default=0.95, metadata={
        "help": "automatic viewpoints stop once this fraction of the overexposed points is seen [0..1]"})
    t_l: float = field(default=T_L, metadata={"help": "overexposure threshold on LDR luminance (CIE Y, linear)"})
    splat_scale: float = field(default=SPLAT_SCALE, metadata={
        "help": "splat radius = splat_scale × mean distance to the splat_k nearest neighbours"})
    splat_k: int = field(default=SPLAT_K, metadata={"help": "neighbours for the local point spacing"})
    max_splat_px: float = field(default=32.0, metadata={"help": "cap of a splat's radius [pixels]"})
    near: float = field(default=1e-3, metadata={"help": "near plane: points closer than this are not drawn [m]"})
    depth_tol: float = field(default=DEPTH_TOL, metadata={
        "help": "relative depth tolerance of the visibility test (seen if d ≤ Z·(1+tol) + radius_tol·r)"})
    grid: int = field(default=6, metadata={"help": "candidate viewpoints: a lattice of about grid³ cells in the bounding box"})
    clearance: float = field(default=0.0, metadata={
        "help": "lattice candidates closer than this to a point are rejected [m]; 0 = max(3% of the box diagonal, 2 median splat radii)"})
    probe_size: int = field(default=64, metadata={"help": "face size of the visibility probe renders [pixels]"})
    probe_points: int = field(default=50_000, metadata={"help": "most points splatted by a probe render"})
    probe_targets: int = field(default=20_000, metadata={"help": "most overexposed points counted by the probe"})
    probe_tol: float = field(default=0.05, metadata={"help": "relative depth tolerance of the probe visibility"})
    radius_tol: float = field(default=RADIUS_TOL, metadata={
        "help": "visibility also accepts d ≤ Z·(1+tol) + radius_tol × the point's splat radius"})
    normal_seeds: int = field(default=64, metadata={
        "help": "extra candidates in front of this many random overexposed points (p + h·n, h = 1,2,4,8 × base); 0 = lattice only"})
    min_enclosure: float = field(default=0.9, metadata={
        "help": "automatic candidates must see surfaces on this fraction of their cube map (inside the scene)"})
    backface_cull: bool = field(default=False, metadata={
        "help": "do not draw splats whose normal faces away from the eye (off: every splat is opaque both ways, e.g. drapes)"})
    facing_test: bool = field(default=FACING_TEST, metadata={
        "help": "a point whose normal faces away from the eye is not counted as seen (coverage, reproject)"})
    outlier_neighbors: int = field(default=20, metadata={
        "help": "statistical outlier test (Open3D): neighbours of the mean-distance test; 0 = off"})
    outlier_std: float = field(default=10.0, metadata={
        "help": "statistical outlier test: a point whose mean neighbour distance exceeds the cloud's mean by this many "
                "standard deviations does not set the viewpoint search's bounding box and is drawn with at most the median splat radius"})

    def check(self) -> None:
        self._require(self.size >= 8, "size", "must be ≥ 8")
        self._require(self.renderer in ("numba", "gl"), "renderer", "must be numba or gl")
        self._require(self.max_views >= 1, "max_views", "must be ≥ 1")
        self._require(0.0 < self.coverage <= 1.0, "coverage", "must be in (0, 1]")
        self._require(0.0 <= self.t_l < 1.0, "t_l", "must be in [0, 1) (LDR luminance; patchmatch's rule)")
        self._require(self.splat_scale > 0, "splat_scale", "must be > 0")
        self._require(self.splat_k >= 1, "splat_k", "must be ≥ 1")
        self._require(self.max_splat_px >= 0.5, "max_splat_px", "must be ≥ 0.5")
        self._require(self.near > 0, "near", "must be > 0")
        self._require(self.depth_tol >= 0, "depth_tol", "must be ≥ 0")
        self._require(self.grid >= 1, "grid", "must be ≥ 1")
        self._require(self.clearance >= 0, "clearance", "must be ≥ 0")
        self._require(self.probe_size >= 4, "probe_size", "must be ≥ 4")
        self._require(self.probe_points >= 1, "probe_points", "must be ≥ 1")
        self._require(self.probe_targets >= 1, "probe_targets", "must be ≥ 1")
        self._require(self.probe_tol >= 0, "probe_tol", "must be ≥ 0")
        self._require(self.radius_tol >= 0, "radius_tol", "must be ≥ 0")
        self._require(self.normal_seeds >= 0, "normal_seeds", "must be ≥ 0")
        self._require(0 <= self.min_enclosure <= 1, "min_enclosure", "must be in [0, 1]")
        self._require(self.outlier_neighbors >= 0, "outlier_neighbors", "must be ≥ 0")
        self._require(self.outlier_std > 0, "outlier_std", "must be > 0")
        vp = [tuple(v) if isinstance(v, (list, tuple)) else (v,) for v in self.viewpoints]
        if vp and all(len(v) == 1 for v in vp):  # the CLI gives "x,y,z;x,y,z" as a flat list
            flat = [v[0] for v in vp]
            if len(flat) % 3:
                raise ConfigError(f"--viewpoints: {len(flat)} numbers is not a list of x,y,z triples")
            vp = [tuple(flat[i:i + 3]) for i in range(0, len(flat), 3)]
        self.viewpoints = [list(map(float, v)) for v in vp]
        for v in self.viewpoints:
            if len(v) != 3 or not all(math.isfinite(float(x)) for x in v):
                raise ConfigError(f"--viewpoints: each viewpoint must be 3 finite numbers x,y,z, got {v!r}")


# ----------------------------------------------------------------------------- viewpoints
def normal_candidates(points: np.ndarray, normals: np.ndarray, seeds: np.ndarray, base: float,
                      min_clear: float, box: np.ndarray | None = None) -> np.ndarray:
    """Candidates in front of overexposed points: p + h·n(p) for h ∈ {1, 2, 4, 8}·base, kept where
    the nearest point is ≥ max(h/2, min_clear) away (free space around the offset position)."""
    from scipy.spatial import cKDTree

    if len(seeds) == 0:
        return np.zeros((0, 3))
    hs = base * np.array([1.0, 2.0, 4.0, 8.0])
    c = (points[seeds][:, None, :] + hs[None, :, None] * normals[seeds][:, None, :]).reshape(-1, 3)
    need = np.maximum(np.tile(hs, len(seeds)) / 2.0, min_clear)
    with held_stops():   # SciPy's worker threads use these arrays
        d, _ = cKDTree(points).query(c, k=1, workers=-1)
    box = points if box is None else box
    lo, hi = box.min(0), box.max(0)
    inside = ((c >= lo) & (c <= hi)).all(axis=1)
    return c[(d >= need) & inside]


def probe_visibility(cands: np.ndarray, points: np.ndarray, radii: np.ndarray, normals: np.ndarray | None,
                     targets: np.ndarray, t_radii: np.ndarray, t_normals: np.ndarray | None, size: int,
                     rel_tol: float, radius_tol: float, near: float, max_px: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Probe renders: ((C, M) bool — target m seen from candidate c in a size² cube map of
    ``points``; (C,) the fraction of the cube map's pixels covered, i.e. how enclosed c is)."""
    out = np.zeros((len(cands), len(targets)), dtype=bool)
    enclosed = np.zeros(len(cands))
    chunk = 16
    for c0 in range(0, len(cands), chunk):
        check_interrupt()
        cams = cube_cameras(cands[c0:c0 + chunk], size)
        z, idx = splat_cube_faces(points, radii, cams["K"][0], cams["world_to_camera"], size, size, near, max_px, normals)
        cover = idx >= 0
        for f in range(len(z)):
            seen, _, _ = seen_in_face(targets, cams["K"][f], cams["world_to_camera"][f], z[f], cover[f], rel_tol,
                                        t_normals, radius_tol * t_radii)
            out[c0 + f // 6] |= seen
            enclosed[c0 + f // 6] += cover[f].mean() / 6.0
    return out, enclosed


def greedy_select(vis: np.ndarray, target: float, max_views: int) -> tuple[list[int], list[float]]:
    """Greedy set cover: indices of chosen candidates and the covered fraction after each pick."""
    m = vis.shape[1]
    covered = np.zeros(m, dtype=bool)
    chosen: list[int] = []
    fracs: list[float] = []
    if m == 0:
        return chosen, fracs
    while len(chosen) < max_views and covered.mean() < target:
        gain = vis[:, ~covered].sum(axis=1)
        best = int(np.argmax(gain))  # ties → lowest index
        if gain[best] == 0:
            break
        chosen.append(best)
        covered |= vis[best]
        fracs.append(float(covered.mean()))
    return chosen, fracs


def choose_viewpoints(points: np.ndarray, radii: np.ndarray, over: np.ndarray, cfg: RenderCubemapsConfig,
                      normals: np.ndarray | None = None, inliers: np.ndarray | None = None
                      ) -> tuple[np.ndarray, dict[str, Any]]:
    """Automatic viewpoints (module docstring). ``inliers`` (N,) bool: the points that set the bounding
    box, the lattice and the clearance (default all; see :func:`statistical_inliers`).
    Returns (eyes (V,3), info for the report)."""
    rng = np.random.default_rng(sub_seed(cfg.seed))
    box = points if inliers is None else points[inliers]
    diag = float(np.linalg.norm(box.max(0) - box.min(0)))
    clearance = cfg.clearance if cfg.clearance > 0 else max(0.03 * diag, 2.0 * float(np.median(radii)))
    cands = candidate_viewpoints(points, cfg.grid, clearance, box)
    n_grid = len(candidate_viewpoints(points, cfg.grid, -1.0, box))
    info: dict[str, Any] = {"grid": cfg.grid, "clearance_m": clearance, "candidates_grid": n_grid,
                            "candidates_free": int(len(cands))}
    if cfg.normal_seeds > 0 and normals is not None:
        oi = np.nonzero(over)[0]
        seeds = np.sort(rng.choice(oi, min(cfg.normal_seeds, len(oi)), replace=False))
        min_clear = float(np.median(radii))
        nc = normal_candidates(points, normals, seeds, max(min_clear, 0.01 * diag), min_clear, box)
        info["candidates_normal"] = int(len(nc))
        cands = np.concatenate([cands, nc])
        info["candidates_free"] = int(len(cands))
    if len(cands) == 0:
        c = 0.5 * (box.min(0) + box.max(0))
        log.warning("no candidate viewpoint is %.3g m away from the points; using the box centre", clearance)
        info["fallback"] = "bounding-box centre (no free-space candidate)"
        return c[None].astype(np.float64), info
    n = len(points)
    if n > cfg.probe_points:
        sub = np.sort(rng.choice(n, cfg.probe_points, replace=False))
        ppts, prad = points[sub], radii[sub] * math.sqrt(n / cfg.probe_points)
        pnrm = None if normals is None or not cfg.backface_cull else normals[sub]
    else:
        ppts, prad, pnrm = points, radii, (normals if cfg.backface_cull else None)
    oidx = np.nonzero(over)[0]
    if len(oidx) > cfg.probe_targets:
        oidx = np.sort(rng.choice(oidx, cfg.probe_targets, replace=False))
    vis, enclosed = probe_visibility(cands, ppts, prad, pnrm, points[oidx], radii[oidx],
                                     None if normals is None or not cfg.facing_test else normals[oidx],
                                     cfg.probe_size, cfg.probe_tol,
                                     cfg.radius_tol, cfg.near, cfg.max_splat_px)
    inside = enclosed >= cfg.min_enclosure
    if not inside.any():
        log.warning("no candidate sees surfaces over ≥ %.0f%% of its cube map (best %.0f%%): keeping all %d",
                    100 * cfg.min_enclosure, 100 * enclosed.max(), len(cands))
        inside[:] = True
    info["candidates_enclosed"] = int(inside.sum())
    keep = np.nonzero(inside)[0]
    chosen, fracs = greedy_select(vis[keep], cfg.coverage, cfg.max_views)
    if not chosen:
        chosen = [int(np.argmax(vis[keep].sum(1)))]
        fracs = [float(vis[keep][chosen[0]].mean())]
    chosen = [int(keep[c]) for c in chosen]
    info.update({"probe_targets": int(len(oidx)), "chosen_candidates": chosen, "probe_coverage_after_each": fracs,
                 "enclosure_of_chosen": [float(enclosed[c]) for c in chosen]})
    return cands[chosen], info


# ----------------------------------------------------------------------------- action
def visibility_params(cfg: RenderCubemapsConfig) -> dict[str, np.ndarray]:
    """The optional cameras.npz keys that let reproject repeat this stage's visibility test."""
    return {"splat_k": np.int32(cfg.splat_k), "splat_scale": np.float64(cfg.splat_scale),
            "backface_cull": np.int32(cfg.backface_cull), "facing_test": np.int32(cfg.facing_test),
            "depth_tol": np.float64(cfg.depth_tol),
            "radius_tol": np.float64(cfg.radius_tol)}


def read_overexposed(cloud: str | Path, t_l: float, t: Timings) -> tuple[Any, np.ndarray]:
    """Read an LDR cloud (timed as "read") and its overexposed mask, logging the count."""
    from .. import io

    with t.step("read"):
        c = io.read_cloud(cloud)
    over = overexposed_mask(c.colors, t_l)
    log.info("%d overexposed points (LDR luminance > %g)", int(over.sum()), t_l)
    return c, over


def run_render_cubemaps(cloud: str | Path, out_dir: str | Path, cfg: RenderCubemapsConfig,
                        preview: str | Path | None = None) -> dict[str, Any]:
    """Read the LDR cloud, choose/take viewpoints, splat the cube maps, write ``out_dir``:
    cameras.npz, face_XXX.exr (R,G,B,A,Z), report.json; a cross PNG when ``preview`` is given."""
    from .. import io

    t = Timings()
    t0 = time.perf_counter()
    folder = FaceFolder(out_dir)
    c, over = read_overexposed(cloud, cfg.t_l, t)
    n, n_over = len(c), int(over.sum())
    report: dict[str, Any] = {"input": str(cloud), "points": n, "overexposed": n_over, "t_l": cfg.t_l,
                              "config": cfg.as_dict(), "renderer": "numba disc splats (CPU)"}
    folder.path.mkdir(parents=True, exist_ok=True)

    def drop_stale(n_faces: int) -> None:
        # faces of an earlier run beyond this one's would mislead patchmatch; removed only once this run's faces
        # and cameras.npz are written (each file stays the old one or a complete new one if the stage is killed)
        for old in folder.stored_faces():
            try:
                if int(old.stem.split("_")[-1]) >= n_faces:
                    old.unlink()
            except ValueError:
                old.unlink()

    if n_over == 0:
        log.info("no overexposed point: nothing to expand, no cube map rendered (cameras.npz with 0 faces)")
        cams = cube_cameras(np.zeros((0, 3)), cfg.size)
        io.write_npz(folder.cameras, "pcrelight.cameras/1", **cams)
        drop_stale(0)
        report.update({"skipped": "no overexposed point", "views": 0, "faces": 0, "coverage": None,
                       "timings": t.as_dict(), "seconds": time.perf_counter() - t0})
        io.write_json(folder.report, report)
        return report
    report["skipped"] = None
    with t.step("knn"):   # one k-d tree query for the outlier test and the splat radii
        pts = c.points.astype(np.float64)
        dists = knn_distances(pts, max(cfg.outlier_neighbors, min(cfg.splat_k, n - 1) + 1))
    with t.step("outliers"):
        inl = statistical_inliers(pts, cfg.outlier_neighbors, cfg.outlier_std, dists=dists)
    n_out, n_out_over = int((~inl).sum()), int((~inl & over).sum())
    report["outliers"] = {"removed": n_out, "removed_overexposed": n_out_over,
                          "neighbors": cfg.outlier_neighbors, "std_ratio": cfg.outlier_std}
    with t.step("radii"):
        radii = knn_splat_radii(pts, cfg.splat_k, cfg.splat_scale, dists=dists).astype(np.float64)
        del dists
        if n_out:  # an isolated point's spacing radius is huge: its depth sprite would cover the room
            radii[~inl] = np.minimum(radii[~inl], float(np.median(radii[inl])))
    log.info("statistical outlier removal (%d neighbours, %g σ): %d of %d points (%d overexposed) left out of "
             "the viewpoint search's bounding box and drawn with at most the median splat radius",
             cfg.outlier_neighbors, cfg.outlier_std, n_out, n, n_out_over)
    nrm_all = c.normals.astype(np.float64)
    nrm = nrm_all if cfg.backface_cull else None            # drawing
    nrm_vis = nrm_all if cfg.facing_test else None          # visibility
    log.info("splat radii: median %.4g m (k=%d, scale %g)", float(np.median(radii)), cfg.splat_k, cfg.splat_scale)
    with t.step("viewpoints"):
        if cfg.viewpoints:
            eyes = np.asarray(cfg.viewpoints, dtype=np.float64).reshape(-1, 3)
            report["viewpoint_mode"] = "config"
            log.info("%d viewpoints from the config", len(eyes))
        else:
            eyes, info = choose_viewpoints(pts, radii, over, cfg, nrm_all, inliers=inl)
            report["viewpoint_mode"] = "automatic"
            report["automatic"] = info
            log.info("automatic viewpoints: %d of %d candidates (%d in free space, %d enclosed; probe coverage %s)",
                     len(eyes), info["candidates_grid"], info["candidates_free"], info.get("candidates_enclosed", 0), ", ".join(f"{x:.3f}" for x in info.get("probe_coverage_after_each", [])))
    cams = cube_cameras(eyes, cfg.size)
    oidx = np.nonzero(over)[0]
    covered = np.zeros(len(oidx), dtype=bool)
    gl_ctx = None
    if cfg.renderer == "gl":
        from .. import gl

        if cfg.backface_cull:
            raise ConfigError("--renderer gl has no back-face culling; use --no-backface-cull or --renderer numba")
        gl_ctx = gl.create_context()
        report["renderer"] = f"GL point sprites ({gl.context_info(gl_ctx)['renderer']})"
        log.info("rendering with GL point sprites on %s", gl.context_info(gl_ctx)["renderer"])
    per_view = []
    crosses = []
    for vi, eye in progress(list(enumerate(eyes)), total=len(eyes), desc="cube maps"):
        with t.step("splat"):
            faces, vc = render_cube_map(pts, c.colors, radii, eye, cfg.size, cfg.near, cfg.max_splat_px, nrm, gl_ctx)
        with t.step("coverage"):
            before = int(covered.sum())
            for f in range(6):
                seen, _, _ = seen_in_face(pts[oidx], vc["K"][f], vc["world_to_camera"][f], faces[f, :, :, 4],
                                            faces[f, :, :, 3], cfg.depth_tol, None if nrm_vis is None else nrm_vis[oidx],
                                            cfg.radius_tol * radii[oidx])
                covered |= seen
        with t.step("write"):
            write_faces(folder, faces, vi * 6, ["R", "G", "B", "A", "Z"])
        per_view.append({"eye": eye.tolist(), "new_overexposed_seen": int(covered.sum()) - before,
                         "pixel_coverage": float(faces[..., 3].mean())})
        if preview is not None:  # at most 256 px a face in the preview
            step = max(1, cfg.size // 256)
            crosses.append(cross_layout(faces[:, ::step, ::step, :4]))
    if gl_ctx is not None:
        gl_ctx.release()
    coverage = float(covered.mean())
    log.info("%d cube maps (%d faces, %d²): %.1f%% of the overexposed points seen", len(eyes), 6 * len(eyes),
             cfg.size, 100 * coverage)
    if coverage < cfg.coverage:
        log.warning("only %.1f%% of the overexposed points are seen by the cube maps (target %.1f%%, %s); "
                    "Poisson will fill the rest", 100 * coverage, 100 * cfg.coverage,
                    f"{len(eyes)} viewpoint(s) from the config" if cfg.viewpoints else f"max_views={cfg.max_views}")
    io.write_npz(folder.cameras, "pcrelight.cameras/1", **cams, **visibility_params(cfg))
    drop_stale(6 * len(eyes))
    if preview is not None:
        img = np.concatenate(crosses, axis=0)
        io.write_preview(preview, img)
    report.update({"views": int(len(eyes)), "faces": int(6 * len(eyes)), "viewpoints": eyes.tolist(),
                   "coverage": coverage, "per_view": per_view, "timings": t.as_dict(),
                   "seconds": time.perf_counter() - t0})
    io.write_json(folder.report, report)
    log.info("render-cubemaps done in %.2f s", time.perf_counter() - t0)
    return report
