"""build-bsh (seed 000 §5.1, §5.4; DESIGN stage 6): the bounding sphere hierarchy of a point cloud.

Steps (timed separately):

1. **morton** — the points' bounding box is cubed (side = its largest extent, min corner kept) and
   cut into 2^bits cells an axis, cell k centred on the corner + k cells (:func:`pipeline.bsh.builder.grid_origin`:
   an axis-aligned wall at a round coordinate lies mid-cell, not on a boundary float32 rounding moves it across);
   each point gets the 64-bit Morton code of its cell (x in the highest bit of each triple).
2. **sort** — stable LSD radix argsort of the codes (numba), ties in input order.
3. **leaves**, **spacing** — one leaf per non-empty cell (voxel). A leaf holds the point-count-weighted
   (= equal-weight) means of its points' positions and colours; its normal cone is the exact
   minimum cone of its points' normals; its sphere is centred on the mean position with radius
   ``max(distance to its farthest point, splat radius)``. The splat radius is
   ``d4 / sqrt(2)``, d4 = the distance to the 4th-nearest other leaf centre among the 16 previous
   and 16 next leaves in Morton order (an upper bound of the true 4-NN distance): on a regular
   grid of spacing s, d4 = s and the discs of radius s/sqrt(2) cover the surface without gaps;
   on uniform random samples each splat covers about twice its share of area. Relight splats
   leaves with this radius, so a one-point leaf is not a zero-sized sphere. A cloud that is a
   single voxel has no neighbour: its radius is that of its points (0 if they coincide).
   **Isolated leaves** (``isolated``, default 2; :func:`pipeline.bsh.tree.shrink_isolated_leaves`, the same as
   :func:`pipeline.expansion.splats.shrink_isolated` on a grid of the leaves' codes): a leaf whose spacing
   exceeds 2 × the median spacing of its 16 nearest leaves samples an object smaller than the point
   spacing (a lamp) and takes that median / sqrt(2): its disc is its share of area, not the size of
   the far surface its 4th neighbour lies on (a lamp room's exact cloud relit 5.6× → 1.04×).
4. **karras** — inner nodes by Karras 2012 over the sorted leaf codes (one parallel task per
   inner node, common prefixes of (code, index) so duplicate codes are broken by index).
5. **bottom_up** — children before parents:
   * colour = mean of the node's points = children's colours weighted by their point counts.
     (The paper averages the two children plainly; as the cloud is sampled uniformly by area,
     the point-count weighting gives the area mean of the radiance, which a plain average of
     children of unequal size does not.)
   * sphere = the minimum sphere containing both children's spheres (closed form: the exact
     smallest enclosing ball of two balls, which is what Fischer–Gärtner 2003 returns for them).
     As the parent must contain its children, no conservative sphere is smaller. Centres are
     rounded to float32 first, then the radius is recomputed in float64 and rounded up to
     float32, so the *stored* parent contains the *stored* children exactly.
   * normal cone = the exact minimum cone (Welzl on the sphere) of the node's point normals on
     the first level above the leaves and for any node over at most ``exact_cone_max`` leaves
     (voxels: duplicated points change no cone); above, the exact minimum cone containing the
     two children's cones (its axis lies on the great circle through theirs), instead of the
     paper's four-border-vector approximation. A cone of half-angle ≥ π/2 culls nothing and is
     stored as the full sphere.
6. **prune_linearise** — depth-first pre-order (left child = next node); every top-most inner
   node passing §5.1's test becomes a leaf ("cluster") keeping its point range, mean colour,
   sphere (containing all its points) and cone (containing all its normals). Test: the mean
   (paper; ``prune_stat="max"``: the largest) linear-RGB distance of its points' colours to the
   node colour is < t_c, and the mean dot of its points' unit normals with the node's mean
   normal (their normalised sum) is > t_n. The command's ``--tc`` is a multiple of the cloud's median luminance
   (:func:`prune_threshold`: radiance × c builds the same tree); :func:`build_bsh` takes the absolute t_c.
7. **pack** — the 40-byte node of §5.4 with ``right`` and ``skip`` (stackless walk: visit i,
   go to i+1 to descend, to skip[i] to skip), the cone packed RGBA8 and widened so that the
   decoded cone contains the true one; and ``splat_radius`` (:func:`splat_radii`): the radius relight
   splats a node with, its sphere's radius capped at the area of its voxels' splats (sparse and mixed
   nodes and clusters shrink; the sphere stays the bound of the stop rule and the culls), that area
   taken at ``closed_share`` (1/8) for the part of a node whose normals point all round
   (:func:`closure_share`: a lamp shows a quarter of its area from any side, not its bounding sphere) when
   the node is brighter than ``closed_contrast`` (30) × the cloud's median luminance: a dark closed node (a
   roof beam) is an occluder first, and shrunk it let the sun through.
8. **emitters** (``emitters``, default compact; :func:`compact_bright`, :func:`split_emitters`) — the isolated
   voxel leaves that are leaves of the tree, and the leaves of small bright objects wherever they sit
   (brighter than ``closed_contrast`` × the median, within ``emitter_size`` typical splat radii of their
   centroid: a lamp of a few to twenty points, not the sun's disc or a sunlit floor), become ``emitters``
   (E, 12): relight's Eq. 9 adds each as its share of its object's area — a quarter of it from any side for
   the object's closed part, once to one side for its flat share |Σ n| / n (0 for isolated points) — where
   its micro-buffer holds nothing nearer; their leaves splat nothing and every node's colour counts their
   points black. A 4 cm lamp is far below a micro-buffer texel: splatted, it lit a whole texel or none, and
   receivers caught it or missed it. A compact object's emitter disc is its leaf's splat radius / sqrt(2)
   (the splat holds about twice a point's share, step 3). Lamp room (one lamp's 8 points were not
   isolated), exact cloud, view1 Lambert, m 24: mean 1.121 → 1.018, 4×4 block RMS 0.31 → 0.046
   (bench/README.md). Where a compact object's points and normals fit a sphere (:func:`sphere_fit`), its
   emitters share the sphere's area 4π r² (closed) instead, and a one-point object of the same radiance
   (nothing to fit) is taken for one more of those fixtures (lamp room 512²: bench/README.md).
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .builder import LEAF_SPLAT_K, LEAF_SPLAT_WINDOW, MAX_EMITTERS, SCHEMA, build_bsh, prune_threshold
from .format import DERIVED_KEYS
from ..config import StageConfig
from ..errors import InputError
from ..runtime import Timings, available_memory, get_logger

log = get_logger("build-bsh")


@dataclass
class BuildBshConfig(StageConfig):
    """Options of build-bsh (seed 000 §5.1)."""

    bits: int = field(default=21, metadata={"help": "Morton bits per axis (1..21); 2^bits cells an axis over the cubed bounding box"})
    tc: float = field(default=0.08, metadata={
        "help": "pruning colour threshold t_c [× the cloud's median luminance (color.radiance_scale): a linear RGB "
                "distance in the cloud's own radiance unit, so that the BSH does not depend on that unit]; 0.08 is the "
                "former absolute 0.01 on the shipped sample (median 0.119)"})
    tn: float = field(default=0.98, metadata={"help": "pruning normal threshold t_n [mean dot product, -1..1]"})
    prune: bool = field(default=True, metadata={"help": "prune sub-trees of similar colour and normal into clusters (§5.1)"})
    prune_stat: str = field(default="mean", metadata={"help": "colour statistic compared with t_c: mean (paper) or max distance to the node colour", "choices": ("mean", "max")})
    exact_cone_max: int = field(default=64, metadata={"help": "nodes over at most this many leaves (voxels) get the exact minimum normal cone of their points"})
    preview_depth: int = field(default=6, metadata={"help": "tree depth of the spheres drawn in the preview"})
    isolated: float = field(default=2.0, metadata={
        "help": "a leaf whose spacing exceeds this × the median spacing of its 16 nearest leaves samples an object "
                "smaller than the point spacing (a lamp): its spacing becomes that median / sqrt(2), so its disc is "
                "its share of area, not twice it (0: off). A lamp room's exact cloud relit went from 5.6× / 7.7× to "
                "1.04× / 1.07× the path tracer; the small sample moved by < 0.1 % (bench/README.md)"})
    closed_contrast: float = field(default=30.0, metadata={
        "help": "--closed-share applies to nodes brighter than this × the cloud's median luminance (a lamp; small "
                "sample: 3.6, its walls < 3, lamps 30–1000); darker closed nodes (roof beams, columns) keep their splat "
                "and hide what lies behind them — shrunk, the beams let the sun through (16², stop 1: per-pixel error "
                "0.08 → 0.54; 0 = every node)"})
    emitters: str = field(default="compact", metadata={
        "help": "isolated: the isolated leaves (--isolated; objects below the point spacing, a lamp) leave the splat "
                "walk and are added by the final gather as compact objects (a quarter of their disc's area from any "
                "side), visible where the micro-buffer's depth lies behind them (a sub-texel splat lit a whole texel "
                "or none: the lamp room's block RMS); compact: those and the leaves of every small bright object "
                "(brighter than --closed-contrast × the median, its bright points within --emitter-size splat "
                "radii of their centre: a lamp of a few points; where its points and normals fit a sphere, its "
                "emitters hold the sphere's area 4π r², and a one-point object of the same radiance takes that "
                "area); none: "
                "they are splatted like every leaf", "choices": ("compact", "isolated", "none")})
    emitter_size: float = field(default=2.0, metadata={
        "help": "--emitters compact: largest radius of a bright object made emitters [typical splat radii: the "
                "median leaf spacing / sqrt(2)]; its bright points are linked within 3 of them (small sample: lamps "
                "1.3–1.5, the sun's disc 4.7, the sunlit floor 46)"})
    closed_share: float = field(default=0.125, metadata={
        "help": "share of its voxels' splat area a closed node (a lamp, a knob: normals all round) splats with: it "
                "shows a quarter of its area from any side and the leaf splats hold twice it, 1/8; a node is split into "
                "a flat part (|Σ a·n| / Σ a) splatted whole and a closed part splatted at this share (1: off). The "
                "small sample's exact cloud relit, view1 Lambert m 24: 1.040 → 1.018 (bench/README.md)"})

    def check(self) -> None:
        self._require(1 <= self.bits <= 21, "bits", "must be in 1..21")
        self._require(not math.isnan(self.tc) and self.tc >= 0, "tc", "must be ≥ 0")
        self._require(-1.0 <= self.tn <= 1.0, "tn", "must be in [-1, 1]")
        self._require(self.prune_stat in ("mean", "max"), "prune_stat", "must be mean or max")
        self._require(self.exact_cone_max >= 2, "exact_cone_max", "must be ≥ 2")
        self._require(self.preview_depth >= 0, "preview_depth", "must be ≥ 0")
        self._require(self.isolated == 0 or self.isolated >= 1, "isolated", "must be 0 (off) or ≥ 1")
        self._require(0 < self.closed_share <= 1, "closed_share", "must be in (0, 1]")
        self._require(self.emitters in ("compact", "isolated", "none"), "emitters", "must be compact, isolated or none")
        self._require(self.emitter_size > 0, "emitter_size", "must be > 0")
        self._require(self.closed_contrast >= 0, "closed_contrast", "must be ≥ 0")


# ----------------------------------------------------------------------------- pure functions
STORED_KEYS = frozenset({"nodes", "splat_radius", "emitters"})


ZIP_LIMIT = 2 ** 31   # above this (a member's size or an offset) write_bsh falls back to zipfile (ZIP64)
_DOS_DATE = (0 << 9) | (1 << 5) | 1   # 1980-01-01, 00:00:00 (io.write_npz's fixed timestamp)


def _npy_header(a: np.ndarray) -> bytes:
    """The ``.npy`` header ``numpy.lib.format.write_array`` writes before the data of the array ``a`` (format
    1.0, or 2.0 when the header does not fit 1.0, as numpy chooses)."""
    import io as _io

    fmt = np.lib.format
    for write in (fmt.write_array_header_1_0, fmt.write_array_header_2_0):
        buf = _io.BytesIO()
        try:
            write(buf, fmt.header_data_from_array_1_0(a))
            return buf.getvalue()
        except ValueError:  # header too long for format 1.0
            continue
    raise ValueError(f"no .npy header format fits an array of shape {a.shape}")


def _npy_bytes(a: np.ndarray) -> np.ndarray:
    """The data bytes of the C-contiguous array ``a`` as a uint8 view (no copy; a 0-d array: a copy)."""
    return np.frombuffer(a.tobytes(), np.uint8) if a.ndim == 0 else a.reshape(-1).view(np.uint8)


def _deflate_member(a: np.ndarray) -> tuple[bytes, int, int]:
    """(raw deflate stream at level 1, CRC-32, uncompressed size) of ``a``'s ``.npy`` bytes; zlib and crc32 release
    the GIL on large buffers, so members compress in parallel threads."""
    import zlib

    head, data = _npy_header(a), _npy_bytes(a)
    comp = zlib.compressobj(1, zlib.DEFLATED, -15)
    out = comp.compress(head) + comp.compress(data) + comp.flush()
    return out, zlib.crc32(data, zlib.crc32(head)), len(head) + a.nbytes


def write_bsh(path: str | os.PathLike, arrays: dict[str, Any]) -> None:
    """Write bsh.npz (pcrelight.bsh/1): :func:`pipeline.io.write_npz` (same validation, atomic write, fixed
    timestamps, sorted keys: byte-deterministic) but without the members the node records hold
    (:data:`pipeline.bsh.format.DERIVED_KEYS`: ``io.read_npz`` puts them back, the same bytes), with deflate
    level 1 instead of 6 and the members of ``STORED_KEYS`` stored.

    The deflated members are compressed by a pool of threads (one per CPU, at most 4) while the stored ones are
    written; the zip is laid out here (local headers, central directory; what ``zipfile`` writes, without its
    data descriptors). A file that would pass 2 GiB is written by ``zipfile`` instead (ZIP64), one member at
    a time."""
    import struct
    import zlib
    from concurrent.futures import ThreadPoolExecutor

    from ..io import atomic_path, check_arrays

    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    check_arrays(path, SCHEMA, arrays)
    arrays["schema"] = np.asarray(SCHEMA)
    arrays = {k: (a if a.flags.c_contiguous else a.copy(order="C")) for k, a in arrays.items()
              if k not in DERIVED_KEYS}
    # (np.ascontiguousarray would turn a 0-d array into shape (1,))
    if sum(a.nbytes + 4096 for a in arrays.values()) >= ZIP_LIMIT:
        write_bsh_zipfile(path, arrays)
        return
    keys = sorted(arrays)
    with atomic_path(path) as tmp, ThreadPoolExecutor(max_workers=max(1, min(4, os.cpu_count() or 1))) as pool:
        jobs = {k: pool.submit(_deflate_member, arrays[k]) for k in keys if k not in STORED_KEYS}
        central = []
        with open(tmp, "wb") as f:
            for key in keys:
                name = (key + ".npy").encode()
                a = arrays[key]
                if key in STORED_KEYS:
                    head, data = _npy_header(a), _npy_bytes(a)
                    crc, size = zlib.crc32(data, zlib.crc32(head)), len(head) + a.nbytes
                    method, csize, parts = 0, size, (head, data)
                else:
                    comp, crc, size = jobs.pop(key).result()
                    method, csize, parts = 8, len(comp), (comp,)
                offset = f.tell()
                f.write(struct.pack("<4s5H3L2H", b"PK\x03\x04", 20, 0, method, 0, _DOS_DATE, crc, csize, size,
                                    len(name), 0) + name)
                for part in parts:
                    f.write(part)
                central.append(struct.pack("<4s6H3L5H2L", b"PK\x01\x02", 20 | 3 << 8, 20, 0, method, 0, _DOS_DATE,
                                           crc, csize, size, len(name), 0, 0, 0, 0, 0o644 << 16, offset) + name)
            cd_start = f.tell()
            cd = b"".join(central)
            f.write(cd + struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, len(keys), len(keys), len(cd), cd_start, 0))


def write_bsh_zipfile(path: str | os.PathLike, arrays: dict[str, np.ndarray]) -> None:
    """:func:`write_bsh` through ``zipfile`` (ZIP64 where needed), members streamed one after the other (those of
    ``DERIVED_KEYS`` left out)."""
    import zipfile

    from ..io import atomic_path

    with atomic_path(path) as tmp:
        with zipfile.ZipFile(tmp, "w", compresslevel=1) as zf:
            for key in sorted(set(arrays) - set(DERIVED_KEYS)):
                a = arrays[key]
                info = zipfile.ZipInfo(key + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.compress_type = zipfile.ZIP_STORED if key in STORED_KEYS else zipfile.ZIP_DEFLATED
                info.external_attr = 0o644 << 16
                # ZipFile.open takes the member's level, not the archive's (3.13 renamed the attribute)
                setattr(info, "compress_level" if hasattr(info, "compress_level") else "_compresslevel", 1)
                # streamed (write_array writes 16 MiB pieces): no copy of the array in memory
                with zf.open(info, "w", force_zip64=a.nbytes > 2 ** 30) as f:
                    np.lib.format.write_array(f, a, allow_pickle=False)


# ----------------------------------------------------------------------------- preview
def render_preview(path: str | os.PathLike, points: np.ndarray, colors: np.ndarray, bsh: dict[str, Any],
                   depth: int, max_points: int = 60000) -> int:
    """PNG: the cloud (tone-mapped colours, at most ``max_points`` shown) in front (XY) and top
    (XZ) orthographic views, with the spheres of the cut at ``depth`` (nodes of that depth plus
    the shallower leaves) drawn as circles. Returns the number of spheres drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Circle

    from ..display import tonemap
    from ..io import save_figure

    n = points.shape[0]
    sel = np.arange(n) if n <= max_points else np.linspace(0, n - 1, max_points).astype(np.int64)
    rgb = tonemap(colors[sel][None, :, :].astype(np.float32))[0]
    d = bsh["depth"]
    leaf = bsh["child"][:, 0] < 0
    cut = np.flatnonzero((d == depth) | (leaf & (d < depth)))
    fig, axs = plt.subplots(1, 2, figsize=(12, 6))
    for ax, (i, j, name) in zip(axs, ((0, 1, "front (x, y)"), (0, 2, "top (x, z)"))):
        ax.scatter(points[sel, i], points[sel, j], s=0.5, c=np.clip(rgb, 0, 1), linewidths=0)
        circles = [Circle((bsh["center"][k, i], bsh["center"][k, j]), bsh["radius"][k]) for k in cut]
        ax.add_collection(PatchCollection(circles, facecolor="none", edgecolor="tab:red", linewidth=0.6, alpha=0.8))
        ax.set_aspect("equal")
        ax.autoscale_view()
        ax.set_title(f"{name}: {len(cut)} spheres at depth {depth}")
        ax.set_xlabel("xyz"[i] + " [m]")
        ax.set_ylabel("xyz"[j] + " [m]")
    fig.tight_layout()
    save_figure(path, fig)
    return len(cut)


# peak resident memory of a build-bsh process: MEMORY_BASE + MEMORY_PER_POINT × N [bytes], an upper bound of the
# measured peaks (bench/relight/cloud_scale.csv, textured synthetic room, warm numba cache): 347 MB at 200 k points,
# 2 802 MB at 3 M, 8 803 MB at 10 M (≈ 860 B a point); cold (numba compiling) 3 238 MB at 3 M (bsh_scale.csv)
MEMORY_BASE = 512 * 2 ** 20
MEMORY_PER_POINT = 900


def memory_needed(n_points: int) -> int:
    """Bytes build-bsh needs for a cloud of ``n_points`` (peak RSS, the model above)."""
    return MEMORY_BASE + MEMORY_PER_POINT * int(n_points)


def check_memory(cloud_path: str | os.PathLike, available: int | None = None) -> None:
    """Refuse in one line, before reading it, a cloud whose header declares more points than this machine's free
    memory holds a build of (:func:`memory_needed` against :func:`pipeline.runtime.available_memory`): the
    never-fails-for-memory rule (Table 3) — a refusal naming what it needs instead of the kernel's OOM kill an hour in.
    Clouds whose header holds no count (PCD, XYZ) are not checked."""
    from ..io import scan_point_count

    n = scan_point_count(cloud_path)
    free = available_memory() if available is None else available
    if n is None or free is None or memory_needed(n) <= free:
        return
    gib = 2.0 ** 30
    fits = int((free - MEMORY_BASE) // MEMORY_PER_POINT)
    fix = (f"subsample it (pcrelight import --max-points {fits}) or build on a larger machine" if fits >= 1000
           else "free some memory or build on a larger machine")
    raise InputError(cloud_path, f"{n} points need about {memory_needed(n) / gib:.1f} GiB for build-bsh "
                     f"({MEMORY_PER_POINT} bytes a point), {free / gib:.1f} GiB is free: {fix}")


# ----------------------------------------------------------------------------- action
def run_build_bsh(cloud_path: str | os.PathLike, out_path: str | os.PathLike, cfg: BuildBshConfig,
                  preview: str | os.PathLike | None = None) -> dict[str, Any]:
    """Read the cloud, build the BSH, write ``out_path`` (pcrelight.bsh/1), ``<stem>.json`` beside
    it and the preview PNG when asked. Returns the report.

    Python's cyclic garbage collector is paused meanwhile: the build makes no reference cycles, and the
    collections that numba's cache loads set off walk every live object (0.1–0.2 CPU s at 3 M points)."""
    import gc

    enabled = gc.isenabled()
    gc.disable()
    try:
        return _run_build_bsh(cloud_path, out_path, cfg, preview)
    finally:
        if enabled:
            gc.enable()


def _run_build_bsh(cloud_path: str | os.PathLike, out_path: str | os.PathLike, cfg: BuildBshConfig,
                   preview: str | os.PathLike | None) -> dict[str, Any]:
    """:func:`run_build_bsh`'s body."""
    from ..io import read_cloud, write_json

    cfg.check()
    check_memory(cloud_path)
    t = Timings()
    t0 = time.perf_counter()
    with t.step("read"):
        cloud = read_cloud(cloud_path)
    tc, unit = prune_threshold(cloud.colors, cfg.tc)
    res = build_bsh(cloud.points, cloud.normals, cloud.colors, bits=cfg.bits, tc=tc, tn=cfg.tn,
                    prune=cfg.prune, prune_stat=cfg.prune_stat, exact_cone_max=cfg.exact_cone_max,
                    where=str(cloud_path), timings=t, isolated=cfg.isolated,
                    closed_share=cfg.closed_share, emitters=cfg.emitters, closed_contrast=cfg.closed_contrast,
                    emitter_size=cfg.emitter_size)
    st = res.pop("stats")
    log.info("%d points → %d voxels (%d with several points) at %d bits (voxel %.3g m)",
             st["n_points"], st["n_voxels"], st["n_multi_point_voxels"], cfg.bits, st["voxel_size"])
    st["tc_absolute"] = tc
    st["radiance_unit"] = unit
    if cfg.prune:
        log.info("pruning (t_c=%g%s, t_n=%g, %s colour distance): %d nodes → %d nodes, %d clusters",
                 tc, f" = {cfg.tc:g} × the median luminance {unit:.4g}", cfg.tn,
                 cfg.prune_stat, st["n_nodes_full"], st["n_nodes"], st["n_clusters"])
    else:
        log.info("pruning off: %d nodes", st["n_nodes"])
    log.info("%d of %d nodes are closed in part (a lamp, a knob): splat area × (flat share + "
             "%.3g × the rest)", st["n_closed"], st["n_nodes"], cfg.closed_share)
    if cfg.isolated > 0:
        log.info("%d of %d leaves isolated (spacing > %.2g × their 16 nearest leaves' median: objects below the point "
                 "spacing): disc = their share of area", st["n_isolated"], st["n_voxels"], cfg.isolated)
    log.info("%d emitters (--emitters %s; %d leaves of small bright objects among the candidates, %d of them on a "
             "fitted sphere: its area 4π r²): added by relight's final gather, not splatted", st["n_emitters"],
             cfg.emitters, st["n_compact"], st["n_sphere_fit"])
    if cfg.emitters != "none" and st["n_emitter_candidates"] > st["n_emitters"]:
        log.warning("%d emitter candidates, more than %d: the brightest %d are emitters, the others stay splatted "
                    "(a noisy scan? see --isolated, --emitters)", st["n_emitter_candidates"], MAX_EMITTERS, MAX_EMITTERS)
    log.info("splat radius capped at the area of the node's voxel splats for %d of %d nodes", st["n_splat_capped"],
             st["n_nodes"])
    log.info("depth %d, %d leaves; times %s", st["depth"], st["n_leaves"],
             ", ".join(f"{k} {v:.3f}s" for k, v in t.as_dict().items()))
    with t.step("write"):
        write_bsh(out_path, res)
    n_prev = None
    if preview is not None:
        with t.step("preview"):
            n_prev = render_preview(preview, cloud.points, cloud.colors, res, cfg.preview_depth)
        log.info("preview %s: %d spheres at depth %d", preview, n_prev, cfg.preview_depth)
    report = {
        "stage": "build-bsh", "inputs": {"cloud": str(cloud_path)}, "output": str(out_path),
        "preview": None if preview is None else str(preview), "config": cfg.as_dict(),
        "counts": st, "preview_spheres": n_prev,
        "decisions": {
            "leaf": "one leaf per non-empty voxel; equal-weight mean of position, colour; exact minimum normal cone",
            "leaf_radius": f"max(farthest point, d{LEAF_SPLAT_K}/sqrt(2)); d{LEAF_SPLAT_K} among ±{LEAF_SPLAT_WINDOW} Morton neighbours",
            "colour": "point-count-weighted mean of children (= mean of the node's points)",
            "sphere": "minimum sphere of the two children's spheres, float32-conservative",
            "splat_radius": "min(sphere radius, sqrt(sum of r^2 over the voxel leaves of the node's points))",
            "cone": f"exact minimum cone of point normals on level 1 and for nodes over ≤ {cfg.exact_cone_max} leaves, exact cone merge above (≥ π/2: the sphere)",
            "pruning": ("off" if not cfg.prune else
                        f"{cfg.prune_stat} colour distance < {tc:.6g}"
                        + f" ({cfg.tc:g} × the median luminance {unit:.6g})"
                        + f" and mean normal dot > {cfg.tn}"),
        },
        "timings_s": t.as_dict(),
    }
    write_json(Path(out_path).with_suffix(".json"), report)
    log.info("build-bsh done in %.2f s → %s", time.perf_counter() - t0, out_path)
    return report
