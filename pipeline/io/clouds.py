"""Point clouds: the pipeline's PLY (:class:`Cloud`, :func:`read_cloud` — the one PLY reader —,
:func:`write_cloud`) and the scans users bring (:func:`read_scan`, by suffix through :data:`CLOUD_READERS`).

Colours in a :class:`Cloud` are linear RGB radiance, float32. uchar colours read from a PLY
are sRGB-encoded LDR and are decoded with colour-science's sRGB EOTF (:mod:`pipeline.color`).

Scan readers (by suffix; no parser of our own): ``.ply`` through :func:`read_cloud` (uchar colours are sRGB
and decoded, float colours are linear as the cloud contract says); ``.pcd``, ``.xyz``, ``.xyzn``, ``.xyzrgb``,
``.pts`` through Open3D (its colours are sRGB-encoded in [0, 1]: 8-bit values / 255); ``.e57`` through pye57
(every scan of the file, each with its pose; colours scaled by the file's ``colorLimits``; ASTM E2807 stores
metres); ``.las``/``.laz`` through laspy (+ lazrs for LAZ; 16-bit colours, or 8-bit values stored in 16 bits
when none exceeds 255). Colours end linear in [0, 1]: sRGB-encoded values are decoded (colour-science,
:mod:`pipeline.color`); float colours that are whole numbers up to 255 are 8-bit values. What a scan then
becomes (outliers, units, up axis, normals) is :mod:`pipeline.ingest.import_scan`'s.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from ..camera import quat_matrix
from ..color import srgb_decode, srgb_encode
from ..errors import InputError, MissingPackage, PcrelightError
from .common import PathLike, atomic_path, log, must_exist


@dataclass
class Cloud:
    """A point cloud: positions (metres), unit normals and linear-radiance colours, all (N,3) float32.

    Optional per-point properties carried through the stages: ``valid`` (uint8, 1 = has an HDR
    colour), ``quality`` (float32, PatchMatch SSD / standard error), ``source`` (uint8: 0 kept
    LDR, 1 projected, 2 Poisson).
    """

    points: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    valid: np.ndarray | None = None
    quality: np.ndarray | None = None
    source: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def validate(self, where: PathLike | str = "<cloud>") -> "Cloud":
        """Check shapes, counts and finiteness; raise InputError naming ``where``."""
        n = self.points.shape[0] if self.points.ndim == 2 else -1
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            raise InputError(where, f"points must be (N,3), got {self.points.shape}")
        if n == 0:
            raise InputError(where, "empty point cloud (0 points)")
        for name in ("normals", "colors"):
            a = getattr(self, name)
            if a.shape != (n, 3):
                raise InputError(where, f"{name} count {a.shape[0] if a.ndim else 0} != point count {n}")
        for name in ("valid", "quality", "source"):
            a = getattr(self, name)
            if a is not None and a.shape != (n,):
                raise InputError(where, f"'{name}' has {a.shape[0] if a.ndim else 0} values for {n} points")
        for name in ("points", "normals", "colors", "quality"):
            a = getattr(self, name)
            if a is not None and not np.all(np.isfinite(a)):
                bad = int(np.count_nonzero(~np.isfinite(a).reshape(n, -1).all(axis=1)))
                raise InputError(where, f"{bad} points have non-finite {name} (NaN or Inf)")
        if np.any(self.colors < 0):
            raise InputError(where, f"{int(np.count_nonzero((self.colors < 0).any(axis=1)))} points have negative colours")
        return self

    def subset(self, idx: np.ndarray) -> "Cloud":
        kw = {f.name: (None if getattr(self, f.name) is None else getattr(self, f.name)[idx])
              for f in dataclasses.fields(self)}
        return Cloud(**kw)


def estimate_normals(points: np.ndarray, k: int = 16) -> np.ndarray:
    """Unit normals from a k-NN PCA (Open3D), oriented towards the cloud's centroid.

    Orientation rule: a scan of a room is seen from inside, so normals face the centroid
    (``orient_normals_towards_camera_location``). Degenerate neighbourhoods get +Y.
    """
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=min(k, max(len(points) - 1, 1))))
    pc.orient_normals_towards_camera_location(points.mean(axis=0).astype(np.float64))
    n = np.asarray(pc.normals, dtype=np.float64)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    bad = ~(ln[:, 0] > 1e-12)
    n[bad] = (0.0, 1.0, 0.0)
    ln[bad] = 1.0
    return (n / ln).astype(np.float32)


def read_cloud(path: PathLike, estimate_missing_normals: bool = True) -> Cloud:
    """Read a PLY point cloud (binary or ASCII) into a validated :class:`Cloud`.

    Colours: float properties are linear radiance as stored; uchar properties are sRGB-encoded
    8-bit and are decoded to linear. Missing normals are estimated (logged). Zero-length
    normals are an error.
    """
    from plyfile import PlyData, PlyParseError

    p = must_exist(path)
    _check_ply_sizes(p)
    try:
        with warnings.catch_warnings():  # (out-of-range ASCII values warn before they fail: one line only)
            warnings.simplefilter("ignore")
            ply = PlyData.read(str(p))
    except (PlyParseError, ValueError, EOFError, IndexError, KeyError, UnicodeDecodeError, OSError,
            OverflowError, TypeError, MemoryError, StopIteration) as e:  # plyfile raises many kinds (fuzzed)
        raise InputError(p, f"not a readable PLY file ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else 'truncated'})") from None
    if "vertex" not in ply:
        raise InputError(p, "PLY has no 'vertex' element")
    v = ply["vertex"].data
    names = set(v.dtype.names or ())
    n = len(v)
    if n == 0:
        raise InputError(p, "empty point cloud (0 points)")
    for c in "xyz":
        if c not in names:
            raise InputError(p, f"PLY vertex element has no '{c}' property")
    pts = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float32)
    cols = None
    for cn in (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue")):
        if all(c in names for c in cn):
            raw = np.stack([v[c] for c in cn], axis=1)
            if raw.dtype.kind in "ui":
                if raw.dtype.itemsize != 1:
                    raise InputError(p, f"integer colours must be uchar, got {raw.dtype}")
                cols = srgb_decode(raw.astype(np.float64) / 255.0)
            else:
                cols = raw.astype(np.float32)
            break
    if cols is None:
        raise InputError(p, "PLY has no colours (red green blue)")
    normals = None
    if all(c in names for c in ("nx", "ny", "nz")):
        normals = np.stack([v["nx"], v["ny"], v["nz"]], axis=1).astype(np.float32)
    opt = {}
    for key, dt in (("valid", np.uint8), ("quality", np.float32), ("source", np.uint8)):
        if key in names:
            opt[key] = np.asarray(v[key]).astype(dt)
    if not np.all(np.isfinite(pts)):
        raise InputError(p, f"{int(np.count_nonzero(~np.isfinite(pts).all(axis=1)))} points have non-finite positions (NaN or Inf)")
    if normals is None:
        if not estimate_missing_normals:
            raise InputError(p, "PLY has no normals (nx ny nz)")
        normals = estimate_normals(pts)
        log.info("%s: no normals; estimated them for %d points (k-NN PCA, oriented towards the centroid)", p, n)
    else:
        if not np.all(np.isfinite(normals)):
            raise InputError(p, f"{int(np.count_nonzero(~np.isfinite(normals).all(axis=1)))} points have non-finite normals (NaN or Inf)")
        n64 = normals.astype(np.float64)  # (float32 squares overflow from ~1e19 and vanish below ~1e-23)
        ln = np.linalg.norm(n64, axis=1)
        if np.any(ln < 1e-6):
            raise InputError(p, f"{int(np.count_nonzero(ln < 1e-6))} points have zero-length normals")
        normals = (n64 / ln[:, None]).astype(np.float32)
    cloud = Cloud(pts, normals, cols, **opt).validate(p)
    log.info("read %s: %d points", p, n)
    return cloud


_PLY_SIZES = {"char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
              "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


def _check_ply_sizes(p: Path) -> None:
    """Refuse a PLY whose header declares more elements than its body can hold, before a reader
    allocates for them (a fuzzed count of 2^31 vertices made plyfile allocate gigabytes)."""
    with open(p, "rb") as f:
        head = f.read(1 << 16)
        end = head.find(b"end_header")
        if not head.startswith(b"ply") or end < 0:
            return  # not a PLY header we can size: the PLY reader says what is wrong
        nl = head.find(b"\n", end)
        body_start = (nl + 1) if nl >= 0 else len(head)
        size = os.fstat(f.fileno()).st_size
        ascii_fmt, need_bytes, need_rows, elem = False, 0, 0, None  # elem: the current element's count
        for line in head[:end].decode("ascii", "replace").splitlines():
            w = line.split()
            if not w:
                continue
            if w[0] == "format" and len(w) > 1:
                ascii_fmt = w[1] == "ascii"
            elif w[0] == "element" and len(w) >= 3:
                try:
                    count = int(w[2])
                except ValueError:
                    raise InputError(p, f"PLY header: element '{w[1]}' has a count that is not an integer ({w[2]!r})") from None
                if count < 0:
                    raise InputError(p, f"PLY header: element '{w[1]}' has a negative count ({count})")
                elem = count
                need_rows += count
            elif w[0] == "property" and elem is not None and len(w) >= 3:
                # a list holds at least its length
                need_bytes += elem * _PLY_SIZES.get(w[2] if w[1] == "list" else w[1], 1)
        body = size - body_start
        if ascii_fmt:
            if need_rows > max(body, 0) // 2 + 1:  # an ASCII row is at least a digit and a newline
                raise InputError(p, f"not a readable PLY file (its header declares {need_rows} rows but only {body} bytes "
                                    "follow it: truncated, or a wrong count)")
        elif need_bytes > body:
            raise InputError(p, f"not a readable PLY file (its header declares {need_bytes} bytes of elements but only "
                                f"{body} follow it: truncated, or a wrong count)")


def write_cloud(path: PathLike, cloud: Cloud, uchar_colors: bool = False) -> None:
    """Write a binary little-endian PLY: ``x y z nx ny nz`` float32, colours float32 linear
    radiance (exact round trip) — or sRGB-encoded uchar when ``uchar_colors`` (LDR, values > 1
    clip) — plus ``valid``/``quality``/``source`` when present."""
    from plyfile import PlyData, PlyElement

    cloud.validate(path)
    n = len(cloud)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    cdt = "u1" if uchar_colors else "<f4"
    fields += [("red", cdt), ("green", cdt), ("blue", cdt)]
    extra = [(k, dt) for k, dt in (("valid", "u1"), ("quality", "<f4"), ("source", "u1")) if getattr(cloud, k) is not None]
    arr = np.empty(n, dtype=fields + extra)
    for i, c in enumerate("xyz"):
        arr[c] = cloud.points[:, i]
        arr["n" + c] = cloud.normals[:, i]
    cols = cloud.colors
    if uchar_colors:
        cols = np.round(srgb_encode(cols) * 255.0).astype(np.uint8)
    for i, c in enumerate(("red", "green", "blue")):
        arr[c] = cols[:, i]
    for k, _ in extra:
        arr[k] = getattr(cloud, k)
    el = PlyElement.describe(arr, "vertex")
    with atomic_path(path) as tmp:
        PlyData([el], text=False, byte_order="<").write(str(tmp))


@dataclass
class Scan:
    """What a reader gives: positions in file units (float64), linear colours in [0, 1] (float32),
    normals or None, and what it found (for the report)."""

    points: np.ndarray
    colors: np.ndarray
    normals: np.ndarray | None
    info: dict[str, Any]


@contextlib.contextmanager
def _c_stderr_captured() -> Iterator[list[str]]:
    """Capture what C/C++ code writes to file descriptor 2 (libE57 prints its exceptions there), so that
    an error stays one line; yields a list that holds the captured text afterwards."""
    import sys

    out: list[str] = []
    with contextlib.suppress(Exception):
        sys.stderr.flush()
    try:
        saved = os.dup(2)
    except OSError:  # no fd 2 (an embedded interpreter): nothing to capture
        yield out
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield out
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            out.append(tmp.read().decode("utf-8", "replace"))


def _first(e: BaseException) -> str:
    s = str(e).strip()
    return s.splitlines()[0][:200] if s else type(e).__name__


def _from_srgb(v: np.ndarray) -> np.ndarray:
    return srgb_decode(np.clip(v, 0.0, 1.0))


def _whole_8bit(c: np.ndarray) -> bool:
    """Float colours above 1 that are whole numbers up to 255: 8-bit values written as floats."""
    return bool(c.max() > 1.0 and c.max() <= 255.0 and np.all(c == np.round(c)))


# 3D Gaussian splats (Kerbl et al. 2023, .ply as the reference trainer writes it): colour from the DC term of the
# spherical harmonics, RGB = 0.5 + SH_C0 · f_dc (sRGB-encoded LDR, as the pipeline's other LDR clouds)
SH_C0 = 0.28209479177387814
GS_MIN_OPACITY = 0.1       # splats more transparent than this (sigmoid of the stored opacity) are dropped, counted
GS_MAX_SHARE = 0.05        # … and splats whose 3σ radius exceeds this share of the room's diagonal (floaters, sky)
GS_PROPS = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3")


def _ply_header_words(p: Path) -> list[list[str]]:
    """The PLY header's lines, split into words (the first 64 KiB up to ``end_header``; plyfile reads the rest)."""
    with open(p, "rb") as f:
        head = f.read(1 << 16)
    end = head.find(b"end_header")
    return [ln.split() for ln in head[:max(end, 0)].decode("ascii", "replace").splitlines()]


def _ply_properties(p: Path) -> set[str]:
    """The property names the PLY header declares."""
    return {w[-1] for w in _ply_header_words(p) if len(w) >= 3 and w[0] == "property"}


def read_gaussian_splats(p: Path) -> Scan:
    """A 3D Gaussian splat scene (.ply with ``f_dc_*``, ``opacity``, ``scale_*``, ``rot_*``) as a scan: each splat's
    centre, its colour from the DC term (RGB = 0.5 + :data:`SH_C0` · f_dc, clipped to [0, 1], sRGB-decoded to
    linear; the view-dependent ``f_rest_*`` terms dropped and counted), its normal the rotation's shortest axis
    (scales stored as ln σ, rotation as a quaternion w, x, y, z, normalised as the trainers do). Splats below
    :data:`GS_MIN_OPACITY` (opacity stored as a logit) or with a 3σ radius above :data:`GS_MAX_SHARE` of the
    robust room diagonal are dropped and counted. A missing property, a non-finite value or a zero quaternion is
    one InputError line naming the file. The report (``info``) holds the counts and the 3σ radii's median [file
    units] (the splat radius is not carried into the cloud's later stages: they use the points' spacing)."""
    from plyfile import PlyData, PlyParseError

    _check_ply_sizes(p)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ply = PlyData.read(str(p))
    except (PlyParseError, ValueError, EOFError, IndexError, KeyError, UnicodeDecodeError, OSError,
            OverflowError, TypeError, MemoryError, StopIteration) as e:
        raise InputError(p, f"not a readable PLY file ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else 'truncated'})") from None
    if "vertex" not in ply:
        raise InputError(p, "PLY has no 'vertex' element")
    v = ply["vertex"].data
    names = set(v.dtype.names or ())
    missing = [k for k in GS_PROPS if k not in names]
    if missing:
        raise InputError(p, f"a Gaussian splat PLY (it has f_dc_0) without {', '.join(missing)}")
    if len(v) == 0:
        raise InputError(p, "empty point cloud (0 points)")
    a = {k: np.asarray(v[k], np.float64) for k in GS_PROPS}
    for k, x in a.items():
        if not np.all(np.isfinite(x)):
            raise InputError(p, f"{int(np.count_nonzero(~np.isfinite(x)))} splats have a non-finite '{k}'")
    q = np.stack([a["rot_0"], a["rot_1"], a["rot_2"], a["rot_3"]], 1)
    qn = np.linalg.norm(q, axis=1)
    if np.any(qn < 1e-12):
        raise InputError(p, f"{int(np.count_nonzero(qn < 1e-12))} splats have a zero rotation quaternion")
    R = quat_matrix(q)                                           # (N, 3, 3): the splat's axes as columns
    ln_s = np.stack([a["scale_0"], a["scale_1"], a["scale_2"]], 1)
    shortest = np.argmin(ln_s, axis=1)
    normals = R[np.arange(len(v)), :, shortest]                  # the rotation's column of the shortest axis
    sigma = np.exp(np.clip(ln_s, -50.0, 50.0))
    radius = 3.0 * sigma.max(axis=1)
    pts = np.stack([a["x"], a["y"], a["z"]], 1)
    opacity = 1.0 / (1.0 + np.exp(-np.clip(a["opacity"], -50.0, 50.0)))
    lo, hi = np.percentile(pts, [0.5, 99.5], axis=0)
    diag = float(np.linalg.norm(hi - lo)) or 1.0
    keep_op = opacity >= GS_MIN_OPACITY
    keep = keep_op & (radius <= GS_MAX_SHARE * diag)
    if not keep.any():
        raise InputError(p, f"no splat left: {int(np.count_nonzero(~keep_op))} below opacity {GS_MIN_OPACITY:g}, "
                            f"{int(np.count_nonzero(keep_op & ~keep))} larger than {GS_MAX_SHARE:g} of the room")
    rgb = np.clip(0.5 + SH_C0 * np.stack([a["f_dc_0"], a["f_dc_1"], a["f_dc_2"]], 1), 0.0, 1.0)
    n_rest = sum(1 for k in names if k.startswith("f_rest_"))
    info: dict[str, Any] = {
        "format": "PLY (3D Gaussian splats)",
        "colours": f"the DC term of the spherical harmonics, 0.5 + {SH_C0:.5f} · f_dc, sRGB-decoded; "
                   f"{n_rest} view-dependent coefficients a splat dropped",
        "splats": int(len(v)), "dropped_transparent": int(np.count_nonzero(~keep_op)),
        "dropped_large": int(np.count_nonzero(keep_op & ~keep)), "sh_rest_dropped": n_rest,
        "min_opacity": GS_MIN_OPACITY, "max_share": GS_MAX_SHARE,
        "radius_3sigma_median": float(np.median(radius[keep])),
        "normals": "each splat's shortest axis",
    }
    log.info("read %s: %d Gaussian splats, %d dropped (opacity < %g), %d dropped (3σ radius > %g of the room's "
             "%.3g diagonal); colours from the DC term (%d view-dependent coefficients dropped)", p, len(v),
             info["dropped_transparent"], GS_MIN_OPACITY, info["dropped_large"], GS_MAX_SHARE, diag, n_rest)
    return Scan(pts[keep], srgb_decode(rgb[keep]).astype(np.float32), normals[keep].astype(np.float32), info)


def write_gaussian_splats(path: PathLike, pos: np.ndarray, sigma: np.ndarray, quat: np.ndarray, opacity: np.ndarray,
                          srgb: np.ndarray, n_rest: int = 45) -> None:
    """A 3D Gaussian splat scene as the reference trainer writes it (the inverse of :func:`read_gaussian_splats`):
    binary PLY, float32 ``x y z``, ``nx ny nz`` = 0, ``f_dc_*`` = (sRGB − 0.5) / :data:`SH_C0`, ``n_rest`` zero
    ``f_rest_*``, ``opacity`` as a logit, ``scale_*`` = ln σ [m], ``rot_0…3`` the quaternion (w, x, y, z)."""
    from plyfile import PlyData, PlyElement

    n = len(pos)
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", *[f"f_rest_{i}" for i in range(n_rest)],
             "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    arr = np.zeros(n, dtype=[(k, "<f4") for k in names])
    op = np.clip(np.asarray(opacity, np.float64), 1e-7, 1 - 1e-7)
    for i, k in enumerate("xyz"):
        arr[k] = np.asarray(pos)[:, i]
    for i in range(3):
        arr[f"f_dc_{i}"] = (np.asarray(srgb, np.float64)[:, i] - 0.5) / SH_C0
        arr[f"scale_{i}"] = np.log(np.asarray(sigma, np.float64)[:, i])
    for i in range(4):
        arr[f"rot_{i}"] = np.asarray(quat)[:, i]
    arr["opacity"] = np.log(op / (1 - op))
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(arr, "vertex")], text=False, byte_order="<").write(str(tmp))


def read_ply_scan(p: Path) -> Scan:
    if "f_dc_0" in _ply_properties(p):            # a 3D Gaussian splat scene
        return read_gaussian_splats(p)
    c = read_cloud(p, estimate_missing_normals=False) if _ply_has_normals(p) else None
    given = c is not None
    if c is None:  # the one PLY reader estimates missing normals; we estimate them after cleaning instead
        c = read_cloud(p, estimate_missing_normals=True)
    cols = c.colors.astype(np.float64)
    info: dict[str, Any] = {"format": "PLY", "colours": "as the PLY reader gives them (uchar: sRGB decoded; float: linear)"}
    if _whole_8bit(cols):
        info["colours"] = f"float colours up to {cols.max():g}, whole numbers: 8-bit sRGB values, decoded"
        cols = _from_srgb(cols / 255.0)
    return Scan(c.points.astype(np.float64), cols.astype(np.float32), c.normals if given else None, info)


def _ply_has_normals(p: Path) -> bool:
    """Whether the PLY header declares nx ny nz."""
    return {"nx", "ny", "nz"} <= _ply_properties(p)


PCD_DATA = ("ascii", "binary", "binary_compressed")


def check_pcd_header(p: Path) -> None:
    """Refuse a PCD whose header Open3D would misread: Open3D sizes its arrays from header fields it does not
    check, so a header without FIELDS/SIZE/TYPE/WIDTH/HEIGHT/POINTS/DATA, with lists of different lengths, WIDTH ×
    HEIGHT ≠ POINTS, or (binary) fewer data bytes than POINTS records gave std::bad_alloc or a point of garbage
    (found by ``make fuzz``). PCD 0.7 header: one ``KEY values`` line each, ``#`` comments, DATA last."""
    head: dict[str, list[str]] = {}
    with open(p, "rb") as f:
        raw = f.read(1 << 16)
    pos = 0
    for line in raw.split(b"\n"):
        pos += len(line) + 1
        text = line.decode("ascii", "replace").strip()
        if not text or text.startswith("#"):
            continue
        key, *vals = text.split()
        head[key.upper()] = vals
        if key.upper() == "DATA":
            break
    else:
        raise InputError(p, "not a readable PCD point cloud (its header has no DATA line)")
    need = ("FIELDS", "SIZE", "TYPE", "WIDTH", "HEIGHT", "POINTS", "DATA")
    missing = [k for k in need if not head.get(k)]
    if missing:
        raise InputError(p, f"not a readable PCD point cloud: header without {', '.join(missing)}")
    n = len(head["FIELDS"])
    count = head.get("COUNT") or ["1"] * n
    if not (len(head["SIZE"]) == len(head["TYPE"]) == len(count) == n):
        raise InputError(p, "not a readable PCD point cloud: header: FIELDS, SIZE, TYPE and COUNT list different "
                            "numbers of fields")
    try:
        size = [int(x) for x in head["SIZE"]]
        cnt = [int(x) for x in count]
        w, h, npts = int(head["WIDTH"][0]), int(head["HEIGHT"][0]), int(head["POINTS"][0])
    except ValueError:
        raise InputError(p, "not a readable PCD point cloud: header: SIZE, COUNT, WIDTH, HEIGHT and POINTS must be "
                            "integers") from None
    if any(x not in (1, 2, 4, 8) for x in size) or any(c < 1 for c in cnt) or any(t not in ("F", "I", "U")
                                                                                    for t in head["TYPE"]):
        raise InputError(p, "not a readable PCD point cloud: header: SIZE must be 1, 2, 4 or 8, COUNT ≥ 1, "
                            "TYPE F, I or U")
    if w < 1 or h < 1 or npts != w * h:
        raise InputError(p, f"not a readable PCD point cloud: header: POINTS {npts} is not WIDTH × HEIGHT "
                            f"({w} × {h})")
    data = head["DATA"][0].lower()
    if data not in PCD_DATA:
        raise InputError(p, f"not a readable PCD point cloud: header: DATA {data!r} is not one of "
                            f"{', '.join(PCD_DATA)}")
    if data == "binary" and p.stat().st_size - pos < npts * sum(a * b for a, b in zip(size, cnt)):
        raise InputError(p, f"not a readable PCD point cloud: file is cut short: {npts} binary points need "
                            f"{npts * sum(a * b for a, b in zip(size, cnt))} bytes after the header")


def read_open3d_scan(p: Path) -> Scan:
    import open3d as o3d

    fmt = p.suffix.lower().lstrip(".")
    if fmt == "pcd":
        check_pcd_header(p)
    prev = o3d.utility.get_verbosity_level()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    try:
        with _c_stderr_captured():
            pc = o3d.io.read_point_cloud(str(p), format=fmt, remove_nan_points=False, remove_infinite_points=False)
    except (RuntimeError, ValueError, UnicodeDecodeError) as e:
        raise InputError(p, f"not a readable {fmt.upper()} point cloud ({_first(e)})") from None
    finally:
        o3d.utility.set_verbosity_level(prev)
    pts = np.asarray(pc.points, dtype=np.float64)
    if len(pts) == 0:
        raise InputError(p, f"not a readable {fmt.upper()} point cloud (Open3D read 0 points)")
    if not pc.has_colors():
        raise InputError(p, f"{fmt.upper()} file has no colours (a .xyz holds positions only: use .xyzrgb, .pts, "
                            ".pcd, .ply, .e57 or .las with colours)")
    cols = np.asarray(pc.colors, dtype=np.float64)
    info: dict[str, Any] = {"format": fmt.upper(), "colours": "sRGB-encoded in [0, 1] (Open3D: 8-bit / 255), decoded"}
    if _whole_8bit(cols):
        info["colours"] = f"values up to {cols.max():g}, whole numbers: 8-bit sRGB, / 255 and decoded"
        cols = cols / 255.0
    normals = np.asarray(pc.normals, dtype=np.float32) if pc.has_normals() else None
    return Scan(pts, _from_srgb(cols), normals, info)


def _e57_colour_max(header: Any) -> float | None:
    import pye57

    try:
        node = header["colorLimits"]["colorRedMaximum"]
    except Exception:  # no limits in the file
        return None
    for kind in (pye57.libe57.IntegerNode, pye57.libe57.FloatNode, pye57.libe57.ScaledIntegerNode):
        with contextlib.suppress(Exception):
            return float(kind(node).value())
    return None


def read_e57_scan(p: Path) -> Scan:
    try:
        import pye57
    except ImportError:
        raise MissingPackage(f"{p}: reading E57 needs the Python package pye57 (pip install pye57)") from None
    pts, cols, info_scans = [], [], []
    try:
        with _c_stderr_captured() as msg:
            e = pye57.E57(str(p))
            try:
                for i in range(e.scan_count):
                    h = e.get_header(i)
                    d = e.read_scan(i, colors=True, transform=True, ignore_missing_fields=True)
                    if not all(k in d for k in ("colorRed", "colorGreen", "colorBlue")):
                        raise InputError(p, f"E57 scan {i} has no colours (colorRed colorGreen colorBlue)")
                    xyz = np.stack([d["cartesianX"], d["cartesianY"], d["cartesianZ"]], axis=1).astype(np.float64)
                    rgb = np.stack([d["colorRed"], d["colorGreen"], d["colorBlue"]], axis=1).astype(np.float64)
                    top = _e57_colour_max(h)
                    rule = "colorLimits"
                    if not top:
                        top, rule = (255.0 if rgb.max() <= 255 else 65535.0), "no colorLimits: 8 bits when ≤ 255"
                    pts.append(xyz)
                    cols.append(rgb / top)
                    info_scans.append({"points": len(xyz), "colour_max": top, "colour_rule": rule, "pose": bool(h.has_pose())})
            finally:
                e.close()
    except (InputError, MissingPackage):
        raise
    except Exception as ex:  # libE57's E57Exception and the like
        detail = _first(ex) if str(ex).strip() else (msg[0].strip().splitlines() or [type(ex).__name__])[0]
        raise InputError(p, f"not a readable E57 file ({detail})") from None
    if not pts:
        raise InputError(p, "E57 file holds no scan")
    info = {"format": "E57", "scans": info_scans,
            "colours": "integers / the file's colorLimits maximum: sRGB-encoded, decoded"}
    return Scan(np.concatenate(pts), _from_srgb(np.concatenate(cols)), None, info)


def read_las_scan(p: Path) -> Scan:
    try:
        import laspy
    except ImportError:
        raise MissingPackage(f"{p}: reading LAS/LAZ needs the Python package laspy (pip install 'laspy[lazrs]')") from None
    try:
        las = laspy.read(str(p))
    except Exception as ex:
        text = _first(ex)
        if "LazBackend" in text or "laz" in text.lower() and "backend" in text.lower():
            raise MissingPackage(f"{p}: reading LAZ needs a LAZ backend (pip install lazrs)") from None
        raise InputError(p, f"not a readable LAS/LAZ file ({text})") from None
    dims = set(las.point_format.dimension_names)
    if not {"red", "green", "blue"} <= dims:
        raise InputError(p, f"LAS point format {las.point_format.id} has no colours (formats 2, 3, 5, 7, 8, 10 have)")
    pts = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1).astype(np.float64)
    rgb = np.stack([np.asarray(las.red), np.asarray(las.green), np.asarray(las.blue)], axis=1).astype(np.float64)
    top = 255.0 if rgb.size and rgb.max() <= 255 else 65535.0
    info = {"format": "LAZ" if p.suffix.lower() == ".laz" else "LAS", "point_format": int(las.point_format.id),
            "colours": f"16-bit / {top:g} ({'every value ≤ 255: 8-bit values in 16 bits' if top == 255 else 'LAS 16-bit'})"
                       ": sRGB-encoded, decoded"}
    return Scan(pts, _from_srgb(rgb / top), None, info)


# the scan readers by file suffix (lower case): `pcrelight import` and `run --cloud` read every scan through
# read_scan and this table; a new format is one reader returning a Scan and one row here
CLOUD_READERS: dict[str, Callable[[Path], Scan]] = {
    ".ply": read_ply_scan, ".pcd": read_open3d_scan, ".xyz": read_open3d_scan, ".xyzn": read_open3d_scan,
    ".xyzrgb": read_open3d_scan, ".pts": read_open3d_scan, ".e57": read_e57_scan, ".las": read_las_scan,
    ".laz": read_las_scan,
}


def scan_reader(path: PathLike) -> Callable[[Path], Scan]:
    """The reader of a scan file by its suffix (:data:`CLOUD_READERS`), or one InputError line naming the file
    and the known suffixes (``run --cloud`` asks before anything is written)."""
    p = Path(path)
    reader = CLOUD_READERS.get(p.suffix.lower())
    if reader is None:
        raise InputError(p, f"unknown scan format '{p.suffix}' (known: {', '.join(CLOUD_READERS)})")
    return reader


def read_scan(path: PathLike) -> Scan:
    """Read a scan by its suffix (:data:`CLOUD_READERS`); a bad file is an InputError naming it."""
    p = Path(path)
    if not p.exists():
        raise InputError(p, "no such file")
    if p.is_dir():
        raise InputError(p, "is a directory, expected a scan file")
    reader = scan_reader(p)
    try:
        scan = reader(p)
    except (PcrelightError, MemoryError):
        raise
    except OSError as e:
        raise InputError(p, f"cannot read ({e.strerror or _first(e)})") from None
    if len(scan.points) == 0:
        raise InputError(p, "empty point cloud (0 points)")
    if not np.all(np.isfinite(scan.colors)):
        raise InputError(p, f"{int(np.count_nonzero(~np.isfinite(scan.colors).all(axis=1)))} points have non-finite colours")
    if np.any(scan.colors < 0):
        raise InputError(p, f"{int(np.count_nonzero((scan.colors < 0).any(axis=1)))} points have negative colours")
    return scan


def scan_point_count(path: PathLike) -> int | None:
    """The point count a scan's header declares, read without its points (PLY's ``element vertex``, E57's first
    scan, LAS's header), or None where the format's header does not hold it (PCD/XYZ/PTS: read on import) or it
    cannot be read (the import then says why)."""
    p = Path(path)
    suffix = p.suffix.lower()
    try:
        if suffix == ".ply":
            _check_ply_sizes(p)     # a count the body cannot hold is not a count (the reader then says so)
            return next((int(w[2]) for w in _ply_header_words(p) if len(w) >= 3 and w[:2] == ["element", "vertex"]),
                        None)
        if suffix == ".e57":
            import pye57

            e = pye57.E57(str(p))
            return int(sum(e.get_header(i).point_count for i in range(e.scan_count)))
        if suffix in (".las", ".laz"):
            import laspy

            with laspy.open(str(p)) as f:
                return int(f.header.point_count)
    except Exception:       # a header a reader cannot parse: the import says what is wrong
        return None
    return None
