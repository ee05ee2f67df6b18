"""All file reading and writing of pcrelight: point clouds (PLY), images (EXR/HDR/PNG),
stage files (NPZ with a schema), JSON reports and figures.

Every writer is atomic: it writes a temp file in the target folder, fsyncs it and renames it
over the target, so an interrupted stage leaves the previous output intact. Every reader turns
a bad file into :class:`~pipeline.errors.InputError` (``<file>: <problem>``).

Colours in a :class:`Cloud` are linear RGB radiance, float32. uchar colours read from a PLY
are sRGB-encoded LDR and are decoded with colour-science's sRGB EOTF (:mod:`pipeline.color`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import io as _io
import json
import math
import os
import struct
import tempfile
import warnings
import zipfile
from dataclasses import dataclass
from glob import escape as glob_escape
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from .color import luminance, srgb_decode, srgb_encode  # noqa: F401  (re-exported: io.luminance etc. are used widely)
from .errors import InputError, OutputError
from .runtime import check_interrupt, get_logger

log = get_logger("io")
PathLike = str | os.PathLike


# --------------------------------------------------------------------------- atomic writes
@contextlib.contextmanager
def atomic_path(path: PathLike) -> Iterator[Path]:
    """Yield a temp path beside ``path`` (same extension); on success fsync + rename over ``path``.

    On any exception (including SIGINT/SIGTERM) the temp file is removed and ``path`` is untouched.
    An OSError while making, writing or renaming the temp file (disk full, read-only folder, no
    permission) becomes :class:`~pipeline.errors.OutputError` naming ``path``.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        _remove_orphan_temps(path)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.{os.getpid()}.", suffix=f".tmp{path.suffix}", dir=path.parent)
        os.close(fd)
    except OSError as e:
        raise OutputError(path, f"cannot write ({_os_problem(e)})") from None
    tmp_path = Path(tmp)
    umask = os.umask(0)
    os.umask(umask)
    try:
        os.chmod(tmp_path, 0o666 & ~umask)  # mkstemp makes 0600; outputs get the usual permissions
        yield tmp_path
        with open(tmp_path, "rb+") as f:
            os.fsync(f.fileno())
        check_interrupt()  # a stop request that arrived while writing: the previous file stays
        os.replace(tmp_path, path)
        try:  # make the rename durable
            dfd = os.open(path.parent, os.O_RDONLY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)
        except OSError:
            pass
    except BaseException as e:
        with contextlib.suppress(OSError):
            tmp_path.unlink()
        if isinstance(e, OSError):
            raise OutputError(path, f"cannot write ({_os_problem(e)}); nothing written, "
                                    "the previous file (if any) is as it was") from None
        raise


def _remove_orphan_temps(path: Path) -> None:
    """Remove the temp files of earlier writes of ``path`` whose process is gone (a kill -9 cannot clean up
    after itself): ``.<stem>.<pid>.<random>.tmp<ext>`` with no process ``pid``."""
    for f in path.parent.glob(f".{glob_escape(path.stem)}.*.tmp{glob_escape(path.suffix)}"):
        pid = f.name[len(path.stem) + 2:].split(".", 1)[0]
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            with contextlib.suppress(OSError):
                f.unlink()
                log.info("removed %s, left by an interrupted write (process %s is gone)", f, pid)
        except (PermissionError, OverflowError, ValueError):
            pass  # another user's live process, or not a pid


def _os_problem(e: OSError) -> str:
    """'no space left on device', 'read-only file system', … from an OSError."""
    if e.strerror:
        return e.strerror[0].lower() + e.strerror[1:]
    return str(e).strip().splitlines()[0][:200] if str(e).strip() else type(e).__name__


def _must_exist(path: PathLike) -> Path:
    p = Path(path)
    if not p.exists():
        raise InputError(p, "no such file")
    if p.is_dir():
        raise InputError(p, "is a directory, expected a file")
    return p


# --------------------------------------------------------------------------- point clouds
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

    p = _must_exist(path)
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


# --------------------------------------------------------------------------- images
def read_image(path: PathLike) -> np.ndarray:
    """Read an EXR / Radiance HDR / PNG image as float32 (H, W, C), linear as stored.

    (PNG and other 8-bit formats are returned as stored, in [0,1], not decoded.)
    """
    p = _must_exist(path)
    inp = _open_image(p)
    try:
        spec = inp.spec()
        h, w, c = int(spec.height), int(spec.width), int(spec.nchannels)
        if min(h, w, c) < 1:
            raise InputError(p, f"corrupt image header ({w}×{h} pixels, {c} channels)")
        if h * w * c > MAX_IMAGE_VALUES:
            raise InputError(p, f"image header declares {w}×{h}×{c} values, more than {MAX_IMAGE_VALUES} "
                                f"({MAX_IMAGE_VALUES * 4 / 2 ** 30:.0f} GiB as float32)")
        px = inp.read_image(0, 0, 0, c, "float")
        err = _oiio_error(inp)
    except (UnicodeDecodeError, ValueError, RuntimeError, TypeError, OverflowError, MemoryError) as e:
        raise InputError(p, f"corrupt or truncated image ({type(e).__name__}: {_first_line(e)})") from None
    finally:
        inp.close()
    if px is None or (isinstance(px, np.ndarray) and px.size == 0) or err:
        raise InputError(p, f"corrupt or truncated image ({(err or 'no pixels').strip().splitlines()[0]})")
    px = np.asarray(px, dtype=np.float32)
    if px.size != h * w * c:
        raise InputError(p, f"corrupt or truncated image ({px.size} values for {w}×{h}×{c})")
    px = px.reshape(h, w, c)
    finite = np.isfinite(px)
    if not finite.all():  # (a half EXR stores Inf/NaN, a float one too; no stage means them)
        bad = ~finite.all(axis=2)
        y, x = np.argwhere(bad)[0]
        kinds = " and ".join(k for k, m in (("NaN", np.isnan(px).any()), ("Inf", np.isinf(px).any())) if m)
        raise InputError(p, f"{int(bad.sum())} of {w}×{h} pixels hold non-finite values ({kinds}; the first at x={x}, y={y})")
    return px


def _open_image(p: Path) -> Any:
    """OpenImageIO's reader for the image file ``p`` (the caller closes it), or one InputError line."""
    import OpenImageIO as oiio

    try:
        inp = oiio.ImageInput.open(str(p))
    except (UnicodeDecodeError, ValueError, RuntimeError, TypeError) as e:  # OIIO decodes header strings (fuzzed)
        raise InputError(p, f"not a readable image ({type(e).__name__}: {_first_line(e)})") from None
    if inp is None:
        err = (_oiio_error(oiio).strip() or "unknown format").splitlines()[0]
        raise InputError(p, f"not a readable image ({err})")
    return inp


MAX_IMAGE_VALUES = 2 ** 30  # pixels × channels an image may declare (4 GiB of float32)


def _oiio_error(obj: Any) -> str:
    """OpenImageIO's last error message; it quotes the file's bytes, which need not be UTF-8 (fuzzed
    EXR headers made ``geterror()`` itself raise UnicodeDecodeError)."""
    try:
        return obj.geterror() or ""
    except UnicodeDecodeError as e:
        return f"an error message that is not UTF-8 ({e.reason})"


def image_attributes(path: PathLike, names: tuple[str, ...]) -> dict[str, Any]:
    """Metadata of an image file (OpenImageIO's names: ``ExposureTime`` [s] and the other EXIF tags,
    ``oiio:BitsPerSample``…): the ones ``names`` asks for that the file holds."""
    p = _must_exist(path)
    inp = _open_image(p)
    try:
        spec = inp.spec()
        out = {n: spec.getattribute(n) for n in names}
        out["format"] = str(spec.format)
        return {k: v for k, v in out.items() if v is not None}
    except (UnicodeDecodeError, ValueError, RuntimeError) as e:
        raise InputError(p, f"not a readable image ({type(e).__name__}: {_first_line(e)})") from None
    finally:
        inp.close()


def image_channels(path: PathLike) -> list[str]:
    """The channel names stored in an image file."""
    p = _must_exist(path)
    inp = _open_image(p)
    try:
        return list(inp.spec().channelnames)
    except (UnicodeDecodeError, ValueError, RuntimeError) as e:
        raise InputError(p, f"not a readable image ({type(e).__name__}: {_first_line(e)})") from None
    finally:
        inp.close()


def write_image(path: PathLike, img: np.ndarray, half: bool = False, channels: list[str] | None = None) -> None:
    """Write float (H, W, C) as EXR (float32 or half) or Radiance HDR; channel names default to
    Y / Y,A / R,G,B / R,G,B,A / R,G,B,A,Z… . Half refuses values beyond 65504 (no silent Inf)."""
    import OpenImageIO as oiio

    a = np.asarray(img, dtype=np.float32)
    if a.ndim == 2:
        a = a[:, :, None]
    h, w, c = a.shape
    if channels is None:
        channels = {1: ["Y"], 2: ["Y", "A"], 3: ["R", "G", "B"], 4: ["R", "G", "B", "A"]}.get(c) or \
            ["R", "G", "B", "A"] + [f"C{i}" for i in range(4, c)]
    if len(channels) != c:
        raise ValueError(f"{len(channels)} channel names for {c} channels")
    if half and np.nanmax(np.abs(a)) > 65504.0:
        raise ValueError(f"{path}: values up to {np.nanmax(np.abs(a)):.4g} overflow half floats (65504); write float32")
    spec = oiio.ImageSpec(w, h, c, "half" if half else "float")
    spec.channelnames = tuple(channels)
    if "A" in channels:
        spec.alpha_channel = channels.index("A")
    if "Z" in channels:
        spec.z_channel = channels.index("Z")
    spec.attribute("compression", "zip")
    spec.attribute("DateTime", "1980:01:01 00:00:00")  # fixed, else OIIO stamps the clock: same pixels, same bytes
    with atomic_path(path) as tmp:
        _oiio_write(path, tmp, spec, np.ascontiguousarray(a))


def write_png(path: PathLike, rgb: np.ndarray) -> None:
    """Write an 8-bit PNG from uint8 or float in [0,1] (already display-encoded)."""
    import OpenImageIO as oiio

    a = np.asarray(rgb)
    if a.dtype != np.uint8:
        a = np.round(np.clip(a, 0, 1) * 255.0).astype(np.uint8)
    if a.ndim == 2:
        a = a[:, :, None]
    spec = oiio.ImageSpec(a.shape[1], a.shape[0], a.shape[2], "uint8")
    with atomic_path(path) as tmp:
        _oiio_write(path, tmp, spec, np.ascontiguousarray(a))


def _oiio_write(path: PathLike, tmp: Path, spec: Any, pixels: np.ndarray) -> None:
    """Write one image with OpenImageIO, checking open, write and close (a full disk fails in any of
    them; unchecked, a truncated PNG was renamed into place)."""
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(str(tmp))
    if out is None:
        raise OutputError(path, f"cannot write ({(_oiio_error(oiio).strip() or 'no writer for this format').splitlines()[0]})")
    ok = out.open(str(tmp), spec)
    if ok:
        ok = out.write_image(pixels)
        ok = out.close() and ok
    else:
        out.close()
    if not ok:
        err = (_oiio_error(out).strip() or _oiio_error(oiio).strip() or "the image library gave no reason").splitlines()[0]
        raise OutputError(path, f"cannot write ({err}); nothing written, the previous file (if any) is as it was")
    # OIIO's PNG writer does not report a failed write (a full disk left a truncated PNG, or 0 bytes, that
    # was renamed into place): a complete PNG ends with its IEND chunk.
    size = tmp.stat().st_size
    complete = size > 0
    if complete and tmp.suffix.lower() == ".png":
        with open(tmp, "rb") as f:
            f.seek(max(0, size - 12))
            complete = f.read(12) == b"\x00\x00\x00\x00IEND\xaeB`\x82"
    if not complete:
        try:
            full = os.statvfs(tmp.parent).f_bavail == 0
        except OSError:
            full = False
        why = "no space left on device" if full else "the image library wrote an incomplete file"
        raise OutputError(path, f"cannot write ({why}); nothing written, the previous file (if any) is as it was")


def write_preview(path: PathLike, hdr: np.ndarray, **tonemap: Any) -> None:
    """Tone-map linear HDR (Reinhard with automatic exposure, DESIGN "Display") to an sRGB PNG.

    An alpha channel (4th) is kept as coverage: pixels with alpha 0 are left black.
    """
    from .display import tonemap as _tonemap

    a = np.asarray(hdr, dtype=np.float32)
    if a.ndim == 2:
        a = np.repeat(a[:, :, None], 3, axis=2)
    if a.shape[2] == 1:
        a = np.repeat(a, 3, axis=2)
    mask = a[:, :, 3] > 0 if a.shape[2] >= 4 else None
    rgb = np.nan_to_num(a[:, :, :3], nan=0.0, posinf=0.0, neginf=0.0)
    out = _tonemap(rgb, mask=mask, **tonemap)
    if mask is not None:
        out = np.concatenate([out, mask[:, :, None].astype(np.float32)], axis=2)
    write_png(path, out)


def save_figure(path: PathLike, fig: Any, dpi: int = 110) -> None:
    """Save a matplotlib figure atomically (PNG) and close it."""
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(str(tmp), dpi=dpi, format=Path(path).suffix.lstrip(".") or "png",
                    metadata={"Software": None} if Path(path).suffix.lower() == ".png" else None)
    plt.close(fig)


# --------------------------------------------------------------------------- NPZ with schemas
def check_arrays(where: PathLike, schema: str, arrays: dict[str, np.ndarray]) -> None:
    from .schemas import SCHEMAS

    if schema not in SCHEMAS:
        raise InputError(where, f"unknown schema '{schema}'")
    spec = SCHEMAS[schema]
    sizes: dict[str, int] = {}
    extra = sorted(set(arrays) - set(spec) - {"schema"})
    if extra:
        raise InputError(where, f"schema {schema}: unexpected key(s) {', '.join(extra)}")
    for key, entry in spec.items():
        dtype, shape = entry[0], entry[1]
        optional = len(entry) > 2 and entry[2] == "optional"
        if key not in arrays:
            if optional:
                continue
            raise InputError(where, f"schema {schema}: missing key '{key}'")
        a = np.asarray(arrays[key])
        if dtype == "str":
            ok = a.dtype.kind == "U"
        elif dtype.startswith("void"):
            ok = a.dtype.kind == "V" and a.dtype.itemsize == int(dtype[4:])
        else:
            ok = a.dtype == np.dtype(dtype)
        if not ok:
            raise InputError(where, f"schema {schema}: '{key}' has dtype {a.dtype}, expected {dtype}")
        if len(shape) != a.ndim:
            raise InputError(where, f"schema {schema}: '{key}' has shape {a.shape}, expected {shape}")
        for dim, s in zip(shape, a.shape):
            if dim is None:
                continue
            if isinstance(dim, int):
                if dim != s:
                    raise InputError(where, f"schema {schema}: '{key}' has shape {a.shape}, expected {shape}")
            elif sizes.setdefault(dim, s) != s:
                raise InputError(where, f"schema {schema}: '{key}' has {dim}={s}, but another key has {dim}={sizes[dim]}")


def write_npz(path: PathLike, schema: str, **arrays: Any) -> None:
    """Write a compressed NPZ holding ``schema`` and the arrays, validated against the registry.

    Byte-deterministic (fixed zip timestamps, sorted keys), unlike ``numpy.savez``.
    """
    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    check_arrays(path, schema, arrays)
    arrays["schema"] = np.asarray(schema)
    with atomic_path(path) as tmp:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as zf:
            for key in sorted(arrays):
                buf = _io.BytesIO()
                a = arrays[key]  # (np.ascontiguousarray would turn a 0-d array into shape (1,))
                np.lib.format.write_array(buf, a if a.flags.c_contiguous else a.copy(order="C"), allow_pickle=False)
                info = zipfile.ZipInfo(key + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.compress_type = zipfile.ZIP_DEFLATED
                info.external_attr = 0o644 << 16
                zf.writestr(info, buf.getvalue())


def _load_npz(p: Path) -> dict[str, np.ndarray]:
    """Every ``.npy`` member of an NPZ, refusing pickles and arrays whose header declares more bytes than
    the member holds (before allocating them); any fault of the archive is an InputError."""
    import zlib

    fmt = np.lib.format
    arrays: dict[str, np.ndarray] = {}
    try:
        with zipfile.ZipFile(p) as zf:
            for info in zf.infolist():
                if not info.filename.endswith(".npy"):
                    raise InputError(p, f"not a readable NPZ file (member '{info.filename[:80]}' is not a .npy array)")
                with zf.open(info) as fh:
                    version = fmt.read_magic(fh)
                    if version not in ((1, 0), (2, 0), (3, 0)):
                        raise InputError(p, f"not a readable NPZ file ('{info.filename[:80]}': .npy version {version})")
                    shape, _, dtype = (fmt.read_array_header_1_0(fh) if version == (1, 0) else fmt.read_array_header_2_0(fh))
                if dtype.hasobject:
                    raise InputError(p, f"'{info.filename[:-4]}' holds Python objects (pickles are not read)")
                need = int(np.prod(shape, dtype=object)) * dtype.itemsize
                if need > info.file_size:
                    raise InputError(p, f"not a readable NPZ file ('{info.filename[:-4]}' declares {need} bytes, "
                                        f"holds {info.file_size})")
                with zf.open(info) as fh:
                    arrays[info.filename[:-4]] = fmt.read_array(fh, allow_pickle=False)
    except InputError:
        raise
    except (zipfile.BadZipFile, zlib.error, ValueError, OSError, EOFError, KeyError, NotImplementedError, RuntimeError,
            OverflowError, TypeError, struct.error, UnicodeDecodeError, MemoryError) as e:  # zipfile/numpy raise many kinds
        raise InputError(p, f"not a readable NPZ file ({type(e).__name__}: {_first_line(e)})") from None
    return arrays


def read_npz(path: PathLike, schema: str) -> dict[str, np.ndarray]:
    """Read an NPZ and validate its ``schema`` string, keys, dtypes and shapes."""
    p = _must_exist(path)
    arrays = _load_npz(p)
    if "schema" not in arrays:
        raise InputError(p, f"no 'schema' key (expected '{schema}')")
    got = str(arrays.pop("schema"))
    if got != schema:
        raise InputError(p, f"schema is '{got}', expected '{schema}'")
    check_arrays(p, schema, arrays)
    return arrays


# --------------------------------------------------------------------------- file references
def sha256_of(path: PathLike) -> str:
    """The SHA-256 of a file's bytes (hex)."""
    import hashlib

    p = _must_exist(path)
    h = hashlib.sha256()
    try:
        with open(p, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    except OSError as e:
        raise InputError(p, _os_problem(e)) from None
    return h.hexdigest()


def file_ref(path: PathLike, folder: PathLike) -> tuple[str, str]:
    """How a stage file records an input it used: the input's path relative to ``folder`` (the folder the
    record is written in, so that a workspace moved with its inputs still resolves) and its SHA-256."""
    rel = os.path.relpath(Path(path).resolve(), Path(folder).resolve())
    return rel, sha256_of(path)


def follow_ref(folder: PathLike, rel: str, digest: str, what: str) -> Path:
    """The input a stage file recorded with :func:`file_ref` (``rel`` relative to ``folder``), checked to be
    the same bytes; else an InputError naming it (``what``: how to say which input it is)."""
    p = Path(os.path.normpath(Path(folder) / rel))
    if not p.is_file():
        raise InputError(p, f"no such file ({what}, recorded in {Path(folder)}): pass it on the command line")
    if sha256_of(p) != digest:
        raise InputError(p, f"changed since it was read ({what}; its SHA-256 differs from the one recorded in "
                            f"{Path(folder)}): rerun that stage, or pass the file on the command line to use it as it is")
    return p


# --------------------------------------------------------------------------- JSON
def _jsonable(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    if dataclasses.is_dataclass(o):
        return dataclasses.asdict(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def write_json(path: PathLike, obj: Any) -> None:
    """Write pretty, key-sorted JSON atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=2, sort_keys=True, default=_jsonable) + "\n")


def read_json(path: PathLike) -> Any:
    """Read a JSON file. A scene (a file named ``scene.json``, or an object with a ``views`` table) is
    checked by :func:`validate_scene`, so every reader of a scene gets only sound values."""
    p = _must_exist(path)
    try:
        obj = json.loads(p.read_text())
    except (ValueError, UnicodeDecodeError) as e:  # JSONDecodeError, and ints over Python's digit limit
        raise InputError(p, f"not valid JSON ({str(e).splitlines()[0][:200]})") from None
    except RecursionError:
        raise InputError(p, "not valid JSON (nested too deeply)") from None
    if p.name == "scene.json" or (isinstance(obj, dict) and isinstance(obj.get("views"), dict)):
        validate_scene(obj, p)
    return obj


def read_scene(path: PathLike) -> dict[str, Any]:
    """Read a scene.json (any file name) and check its values (:func:`validate_scene`)."""
    p = _must_exist(path)
    obj = read_json(p)
    return validate_scene(obj, p)


def _json_numbers(o: Any, at: str) -> Iterator[tuple[str, float]]:
    if isinstance(o, bool) or o is None or isinstance(o, str):
        return
    if isinstance(o, (int, float)):
        yield at, float(o) if not isinstance(o, int) or abs(o) < 2 ** 1000 else math.inf
    elif isinstance(o, dict):
        for k, v in o.items():
            yield from _json_numbers(v, f"{at}.{k}" if at else str(k))
    elif isinstance(o, list):
        for i, v in enumerate(o):
            yield from _json_numbers(v, f"{at}[{i}]")


def _vec(p: Path, obj: Any, at: str, n: int) -> np.ndarray:
    """``n`` numbers (not booleans) at ``at``, as float64, or InputError."""
    if not (isinstance(obj, list) and len(obj) == n and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                            for x in obj)):
        raise InputError(p, f"{at} must be {n} numbers, got {json.dumps(obj)[:80]}")
    return np.asarray(obj, np.float64)


def validate_scene(obj: Any, path: PathLike) -> dict[str, Any]:
    """Check the values of a scene.json that the stages use; raise InputError naming the entry.

    Every number finite (but make-scene's ``precision`` reports); each view's ``eye``/``target``/``up`` present, three numbers, eye ≠ target, ``up`` not
    zero, ``fov_deg`` in (0, 180), ``size`` two integers in 1..16384; the
    objects' ``file`` a name, ``to_world`` an invertible 4×4 matrix, ``radius`` > 0; meshes' ``albedo`` in
    [0, 1] and ``emission`` ≥ 0; materials' ``roughness`` in [0, 1]; lamps' and the sun's radiance ≥ 0.
    """
    p = Path(path)
    if not isinstance(obj, dict):
        raise InputError(p, f"not a scene.json object (the file holds a JSON {type(obj).__name__})")
    for at, x in _json_numbers(obj, ""):
        if "precision" in at.replace("[", ".").split("."):
            continue        # make-scene's sampling report (rel_se_max is inf where no target was set): not an input
        if not math.isfinite(x):
            raise InputError(p, f"{at} is {x} (every number must be finite)")
    views = obj.get("views", {})
    if not isinstance(views, dict):
        raise InputError(p, "views must be an object of named views")
    for name, v in views.items():
        at = f"views.{name}"
        if not isinstance(v, dict):
            raise InputError(p, f"{at} must be an object with eye, target, up")
        missing = [k for k in ("eye", "target", "up") if k not in v]
        if missing:
            raise InputError(p, f"{at} has no {', '.join(missing)} (a view is a camera: eye, target, up)")
        vecs = {k: _vec(p, v[k], f"{at}.{k}", 3) for k in ("eye", "target", "up")}
        with np.errstate(all="ignore"):  # (huge finite values overflow the norm: still not zero)
            same_point = "eye" in vecs and "target" in vecs and not np.linalg.norm(vecs["target"] - vecs["eye"]) > 0
            up_zero = "up" in vecs and not np.linalg.norm(vecs["up"]) > 0
        if same_point:
            raise InputError(p, f"{at}: eye and target are the same point")
        if up_zero:
            raise InputError(p, f"{at}.up must be a non-zero vector")
        if "fov_deg" in v:
            f = v["fov_deg"]
            if isinstance(f, bool) or not isinstance(f, (int, float)) or not 0 < f < 180:
                raise InputError(p, f"{at}.fov_deg must be in (0, 180) degrees, got {f!r}")
        if "size" in v:
            sz = v["size"]
            if not (isinstance(sz, list) and len(sz) == 2 and all(type(x) is int and 1 <= x <= 16384 for x in sz)):
                raise InputError(p, f"{at}.size must be two integers in 1..16384 (width, height), got {json.dumps(sz)[:80]}")
    for key in ("object", "object2"):
        o = obj.get(key)
        if o is None:
            continue
        if not isinstance(o, dict):
            raise InputError(p, f"{key} must be an object")
        for k in ("file", "obj", "ply"):
            if k in o and not (isinstance(o[k], str) and o[k].strip()):
                raise InputError(p, f"{key}.{k} must be a file name, got {json.dumps(o[k])[:80]}")
        if "to_world" in o:
            m = o["to_world"]
            if not (isinstance(m, list) and len(m) == 4):
                raise InputError(p, f"{key}.to_world must be a 4×4 matrix (4 rows of 4 numbers)")
            M = np.stack([_vec(p, r, f"{key}.to_world[{i}]", 4) for i, r in enumerate(m)])
            if not abs(np.linalg.det(M[:3, :3])) > 1e-12:
                raise InputError(p, f"{key}.to_world is singular (a zero scale flattens the object)")
        if "radius" in o and not (isinstance(o["radius"], (int, float)) and o["radius"] > 0):
            raise InputError(p, f"{key}.radius must be > 0, got {o['radius']!r}")
        if "center" in o:
            _vec(p, o["center"], f"{key}.center", 3)
    meshes = obj.get("meshes", [])
    for i, m in enumerate(meshes if isinstance(meshes, list) else []):
        if not isinstance(m, dict):
            continue
        if "albedo" in m:
            a = _vec(p, m["albedo"], f"meshes[{i}].albedo", 3)
            if not np.all((a >= 0) & (a <= 1)):
                raise InputError(p, f"meshes[{i}].albedo must be in [0, 1] per channel (energy conservation), "
                                    f"got {m['albedo']}")
        if "emission" in m and not np.all(_vec(p, m["emission"], f"meshes[{i}].emission", 3) >= 0):
            raise InputError(p, f"meshes[{i}].emission must be ≥ 0, got {m['emission']}")
    mats = obj.get("materials", {})
    for name, m in (mats.items() if isinstance(mats, dict) else []):
        r = m.get("roughness") if isinstance(m, dict) else None
        if r is not None and (isinstance(r, bool) or not isinstance(r, (int, float)) or not 0 <= r <= 1):
            raise InputError(p, f"materials.{name}.roughness must be in [0, 1], got {r!r}")
    for key in ("lamps", "sun"):
        o = obj.get(key)
        if isinstance(o, dict):
            if "radiance" in o and not np.all(_vec(p, o["radiance"], f"{key}.radiance", 3) >= 0):
                raise InputError(p, f"{key}.radiance must be ≥ 0, got {o['radiance']}")
            if "radius" in o and not (isinstance(o["radius"], (int, float)) and o["radius"] > 0):
                raise InputError(p, f"{key}.radius must be > 0, got {o['radius']!r}")
    return obj


# --------------------------------------------------------------------------- triangle meshes (make-scene)
def write_mesh(path: PathLike, vertices: np.ndarray, faces: np.ndarray | None = None,
               normals: np.ndarray | None = None, base_color: tuple | None = None,
               metallic: float = 0.0, roughness: float = 1.0) -> None:
    """Write a triangle mesh, format from the extension: ``.ply`` (binary little-endian, float32
    ``x y z`` [+ ``nx ny nz``], int32 ``vertex_indices``), ``.obj`` (text, ``v``/``vn``/``f``) or
    ``.glb`` (glTF 2.0 binary with one metallic-roughness material: ``base_color`` linear RGB,
    ``metallic``, ``roughness``). ``faces=None`` means a triangle soup (3 vertices a face).
    Byte-deterministic for the same arrays."""
    v = np.ascontiguousarray(vertices, dtype=np.float32)
    f = (np.arange(len(v), dtype=np.int32).reshape(-1, 3) if faces is None
         else np.ascontiguousarray(faces, dtype=np.int32))
    n = None if normals is None else np.ascontiguousarray(normals, dtype=np.float32)
    ext = Path(path).suffix.lower()
    with atomic_path(path) as tmp:
        if ext == ".ply":
            from plyfile import PlyData, PlyElement

            fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
            if n is not None:
                fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
            va = np.empty(len(v), dtype=fields)
            for i, c in enumerate("xyz"):
                va[c] = v[:, i]
                if n is not None:
                    va["n" + c] = n[:, i]
            fa = np.empty(len(f), dtype=[("vertex_indices", "<i4", (3,))])
            fa["vertex_indices"] = f
            PlyData([PlyElement.describe(va, "vertex"), PlyElement.describe(fa, "face")],
                    text=False, byte_order="<").write(str(tmp))
        elif ext == ".obj":
            lines = [f"v {a:.7g} {b:.7g} {c:.7g}" for a, b, c in v.tolist()]
            if n is not None:
                lines += [f"vn {a:.7g} {b:.7g} {c:.7g}" for a, b, c in n.tolist()]
                lines += [f"f {a}//{a} {b}//{b} {c}//{c}" for a, b, c in (f + 1).tolist()]
            else:
                lines += [f"f {a} {b} {c}" for a, b, c in (f + 1).tolist()]
            tmp.write_text("\n".join(lines) + "\n")
        elif ext == ".glb":
            import trimesh

            mat = trimesh.visual.material.PBRMaterial(
                baseColorFactor=[*(base_color if base_color is not None else (0.8, 0.8, 0.8)), 1.0],
                metallicFactor=float(metallic), roughnessFactor=float(roughness))
            tm = trimesh.Trimesh(vertices=v, faces=f, vertex_normals=n, process=False,
                                 visual=trimesh.visual.TextureVisuals(material=mat))
            tmp.write_bytes(tm.export(file_type="glb"))
        else:
            raise ValueError(f"{path}: unknown mesh format '{ext}' (use .ply, .obj or .glb)")


def read_mesh(path: PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a triangle mesh (PLY, OBJ, glTF/GLB; several meshes are merged in world space):
    ``(vertices (V,3) float32, faces (F,3) int32, vertex normals (V,3) float32)`` — normals from
    the file when present, else area-weighted from the faces."""
    import trimesh

    p = _must_exist(path)
    try:
        m = trimesh.load(str(p), force="mesh", process=False)
    except Exception as e:  # trimesh raises many kinds
        raise InputError(p, f"not a readable mesh ({type(e).__name__}: {e})") from None
    if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
        raise InputError(p, "no triangles in the mesh")
    v = np.asarray(m.vertices, dtype=np.float32)
    if not np.all(np.isfinite(v)):
        raise InputError(p, "non-finite vertex positions")
    return v, np.asarray(m.faces, dtype=np.int32), np.asarray(m.vertex_normals, dtype=np.float32)


def read_object(path: PathLike) -> list[dict[str, Any]]:
    """Read a renderable object (glTF/GLB, OBJ, PLY) as a list of parts in the file's world space
    (scene-graph transforms applied), one per mesh × material. Each part: ``positions`` (V,3) f32,
    ``normals`` (V,3) f32 or None (file normals only), ``faces`` (F,3) u32, ``uv`` (V,2) f32 or None
    (as trimesh gives it: OpenGL convention, v = 0 at the image's bottom row), ``vertex_color`` (V,3) linear f32 or None
    (uchar PLY colours are sRGB-decoded), ``base_color`` (3,) linear, ``metallic``, ``roughness``
    (glTF metallic-roughness factors; OBJ: Kd, metallic 0, roughness 1; PLY: 0.8 grey),
    ``base_color_tex`` (H,W,3) linear f32 or None (sRGB-decoded), ``mr_tex`` (H,W,3) f32 or None
    (glTF: G = roughness, B = metallic, linear), ``double_sided`` bool, ``pbr`` bool (a glTF
    metallic-roughness material was present)."""
    import trimesh

    p = _must_exist(path)
    check_materials(p)  # trimesh clips out-of-range colours silently: check the file's own values first
    try:
        loaded = trimesh.load(str(p), process=False)
    except Exception as e:  # trimesh raises many kinds
        raise InputError(p, f"not a readable mesh ({type(e).__name__}: {_first_line(e)})") from None
    except RecursionError:
        raise InputError(p, "not a readable mesh (nested too deeply)") from None
    if isinstance(loaded, trimesh.Trimesh):
        items = [(np.eye(4), loaded)]
    elif isinstance(loaded, trimesh.Scene):
        items = []
        for node in loaded.graph.nodes_geometry:
            T, gname = loaded.graph[node]
            g = loaded.geometry.get(gname)
            if isinstance(g, trimesh.Trimesh):
                items.append((np.asarray(T, np.float64), g))
    else:
        items = []
    parts: list[dict[str, Any]] = []
    ignored: dict[str, list[str]] = {}          # glTF material features the renderer does not apply yet (issue 24)

    def img(im: Any, srgb: bool) -> np.ndarray | None:
        if im is None:
            return None
        try:
            a = np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
        except Exception as e:  # PIL raises many kinds on a broken embedded image
            raise InputError(p, f"unreadable texture image ({type(e).__name__}: {_first_line(e)})") from None
        if a.ndim != 3 or a.shape[0] == 0 or a.shape[1] == 0:
            raise InputError(p, "empty texture image")
        return srgb_decode(a).astype(np.float32) if srgb else a

    for T, g in items:
        if len(g.faces) == 0:
            continue
        if not np.all(np.isfinite(T)) or not abs(np.linalg.det(T[:3, :3])) > 1e-12:
            raise InputError(p, "a node's transform is singular or not finite (a zero scale flattens the mesh)")
        if np.asarray(g.vertices).ndim != 2 or np.asarray(g.vertices).shape[1] != 3:
            raise InputError(p, f"vertices are not (x, y, z) triples (shape {np.asarray(g.vertices).shape})")
        with np.errstate(all="ignore"):
            v = np.asarray(g.vertices, np.float64)
            v = (v @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
        if not np.all(np.isfinite(v)):
            raise InputError(p, "non-finite vertex positions")
        faces = np.asarray(g.faces)
        if faces.ndim != 2 or faces.shape[1] != 3 or faces.min() < 0 or faces.max() >= len(v):
            raise InputError(p, f"faces index vertices outside 0..{len(v) - 1}")
        nrm = None
        with np.errstate(all="ignore"):
            raw = np.asarray(g.vertex_normals, np.float64)  # the file's, else trimesh's from the faces
        if raw.shape == v.shape:
            if not np.all(np.isfinite(raw)):
                raise InputError(p, f"{int(np.count_nonzero(~np.isfinite(raw).all(axis=1)))} vertex normals are not finite")
            nrm = (raw @ np.linalg.inv(T[:3, :3])).astype(np.float32)  # inverse-transpose, row vectors
        part: dict[str, Any] = {"positions": v, "normals": nrm, "faces": np.asarray(g.faces, np.uint32),
                                "uv": None, "vertex_color": None, "base_color": np.array([0.8, 0.8, 0.8], np.float32),
                                "metallic": 0.0, "roughness": 1.0, "base_color_tex": None, "mr_tex": None,
                                "double_sided": False, "pbr": False}
        vis = g.visual
        if isinstance(vis, trimesh.visual.TextureVisuals):
            mat = vis.material
            if vis.uv is not None and len(vis.uv) == len(v):
                part["uv"] = np.asarray(vis.uv, np.float32)
                if part["uv"].ndim != 2 or part["uv"].shape[1] != 2 or not np.all(np.isfinite(part["uv"])):
                    raise InputError(p, "texture coordinates are not finite (u, v) pairs")
            if isinstance(mat, trimesh.visual.material.PBRMaterial):
                part["pbr"] = True
                bc = mat.baseColorFactor
                if bc is not None:
                    part["base_color"] = (np.asarray(bc, np.float32)[:3] / 255.0).astype(np.float32)
                else:
                    part["base_color"] = np.ones(3, np.float32)
                part["metallic"] = float(1.0 if mat.metallicFactor is None else mat.metallicFactor)
                part["roughness"] = float(1.0 if mat.roughnessFactor is None else mat.roughnessFactor)
                part["double_sided"] = bool(getattr(mat, "doubleSided", False))
                part["base_color_tex"] = img(mat.baseColorTexture, True) if part["uv"] is not None else None
                part["mr_tex"] = img(mat.metallicRoughnessTexture, False) if part["uv"] is not None else None
                for attr, what in (("normalTexture", "normal map"), ("occlusionTexture", "occlusion map"),
                                   ("emissiveTexture", "emissive texture")):
                    if getattr(mat, attr, None) is not None:
                        ignored.setdefault(f"{what} ({attr})", []).append(getattr(mat, "name", None) or f"#{len(parts)}")
                ef = getattr(mat, "emissiveFactor", None)
                if ef is not None and np.any(np.asarray(ef, np.float64) > 0):
                    ignored.setdefault("emission (emissiveFactor)", []).append(getattr(mat, "name", None) or f"#{len(parts)}")
            elif mat is not None:  # OBJ/MTL SimpleMaterial
                d = getattr(mat, "diffuse", None)
                if d is not None:
                    part["base_color"] = (np.asarray(d, np.float32)[:3] / 255.0).astype(np.float32)
                im = getattr(mat, "image", None)
                part["base_color_tex"] = img(im, True) if part["uv"] is not None else None
        elif isinstance(vis, trimesh.visual.ColorVisuals) and vis.kind == "vertex":
            vc = np.asarray(vis.vertex_colors, np.float32)[:, :3] / 255.0
            part["vertex_color"] = srgb_decode(vc).astype(np.float32)
        _check_part_material(p, part, len(parts))
        parts.append(part)
    if not parts:
        raise InputError(p, "no triangles in the mesh")
    for what, mats in ignored.items():
        log.warning("%s: %s ignored (not applied yet) in material(s) %s", p, what, ", ".join(sorted(set(mats))))
    if p.suffix.lower() in (".glb", ".gltf"):
        used = (_gltf_json(p) or {}).get("extensionsUsed") or []
        for ext in sorted(e for e in used if isinstance(e, str) and e in GLTF_IGNORED_EXTENSIONS):
            log.warning("%s: glTF extension %s ignored (not applied yet: %s)", p, ext, GLTF_IGNORED_EXTENSIONS[ext])
    return parts


# glTF extensions the object reader does not apply yet (issue 24), with what that changes
GLTF_IGNORED_EXTENSIONS = {
    "KHR_texture_transform": "textures are read without their offset, rotation and scale",
    "KHR_materials_emissive_strength": "no emission is applied at all",
    "KHR_materials_clearcoat": "no clear coat layer", "KHR_materials_transmission": "rendered opaque",
    "KHR_materials_sheen": "no sheen", "KHR_materials_specular": "the default specular",
    "KHR_materials_ior": "the default IOR 1.5", "KHR_materials_volume": "no volume",
    "KHR_materials_iridescence": "no iridescence", "KHR_materials_anisotropy": "isotropic roughness",
}


def _first_line(e: BaseException) -> str:
    t = str(e).strip()
    return t.splitlines()[0][:200] if t else "no detail"


def _check_part_material(p: Path, part: dict[str, Any], i: int) -> None:
    """The values a part's material ends up with: finite, colours and factors in [0, 1]."""
    bc = np.asarray(part["base_color"], np.float64)
    if bc.shape != (3,) or not np.all(np.isfinite(bc)) or not np.all((bc >= 0) & (bc <= 1)):
        raise InputError(p, f"part {i}: base colour {np.round(bc, 4).tolist()} is outside [0, 1] (energy conservation)")
    for k in ("metallic", "roughness"):
        x = part[k]
        if not (math.isfinite(x) and 0 <= x <= 1):
            raise InputError(p, f"part {i}: {k} {x!r} is outside [0, 1]")


def _unit(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and 0 <= x <= 1


def _gltf_json(p: Path) -> Any:
    """The JSON of a .gltf, or of a .glb's first chunk; None when the file is not laid out as one (the
    mesh reader then says what is wrong with it)."""
    raw = p.read_bytes()
    if p.suffix.lower() == ".glb" or raw[:4] == b"glTF":
        if len(raw) < 20 or raw[:4] != b"glTF":
            return None
        clen, ctype = struct.unpack_from("<II", raw, 12)
        if ctype != 0x4E4F534A or 20 + clen > len(raw):
            return None
        raw = raw[20:20 + clen]
    try:
        return json.loads(raw)
    except (ValueError, UnicodeDecodeError, RecursionError):
        return None


def check_materials(path: PathLike) -> None:
    """Check the material values an object file states (trimesh clips some silently): glTF
    ``baseColorFactor``, ``metallicFactor``, ``roughnessFactor``, ``emissiveFactor`` and
    ``occlusionTexture.strength`` in [0, 1]; OBJ/MTL ``Kd``/``Ka``/``Ks`` and ``Pr``/``Pm`` (PBR
    roughness/metallic) and ``d`` in [0, 1], ``Ke``/``Ns`` ≥ 0. Raise InputError naming the material."""
    p = Path(path)
    ext = p.suffix.lower()
    if ext in (".glb", ".gltf"):
        doc = _gltf_json(p)
        mats = doc.get("materials", []) if isinstance(doc, dict) else []
        for i, m in enumerate(mats if isinstance(mats, list) else []):
            if not isinstance(m, dict):
                raise InputError(p, f"material {i} is not a JSON object")
            name = f"material {i}" + (f" ('{m['name']}')" if isinstance(m.get("name"), str) else "")
            pbr = m.get("pbrMetallicRoughness", {})
            if not isinstance(pbr, dict):
                raise InputError(p, f"{name}: pbrMetallicRoughness is not a JSON object")
            bc = pbr.get("baseColorFactor")
            if bc is not None and not (isinstance(bc, list) and len(bc) == 4 and all(_unit(x) for x in bc)):
                raise InputError(p, f"{name}: baseColorFactor {json.dumps(bc)[:80]} must be 4 numbers in [0, 1] "
                                    "(energy conservation: a surface reflects at most the light it receives)")
            for k in ("metallicFactor", "roughnessFactor"):
                if k in pbr and not _unit(pbr[k]):
                    raise InputError(p, f"{name}: {k} {json.dumps(pbr[k])[:40]} must be in [0, 1]")
            ef = m.get("emissiveFactor")
            if ef is not None and not (isinstance(ef, list) and len(ef) == 3 and all(_unit(x) for x in ef)):
                raise InputError(p, f"{name}: emissiveFactor {json.dumps(ef)[:80]} must be 3 numbers in [0, 1]")
            occ = m.get("occlusionTexture")
            if isinstance(occ, dict) and "strength" in occ and not _unit(occ["strength"]):
                raise InputError(p, f"{name}: occlusionTexture.strength must be in [0, 1]")
    elif ext == ".obj":
        try:
            text = p.read_text(errors="replace")
        except OSError as e:
            raise InputError(p, f"cannot read ({e.strerror})") from None
        for line in text.splitlines():
            w = line.split(None, 1)
            if len(w) == 2 and w[0] == "mtllib":
                for lib in w[1].split():
                    mtl = p.parent / lib
                    if mtl.is_file():
                        _check_mtl(mtl)


def _check_mtl(mtl: Path) -> None:
    rules = {"Kd": (0, 1, "diffuse colour"), "Ka": (0, 1, "ambient colour"), "Ks": (0, 1, "specular colour"),
             "Pr": (0, 1, "roughness"), "Pm": (0, 1, "metallic"), "d": (0, 1, "opacity"),
             "Ke": (0, math.inf, "emission"), "Ns": (0, math.inf, "specular exponent")}
    name = "?"
    for n, line in enumerate(mtl.read_text(errors="replace").splitlines(), 1):
        w = line.split()
        if not w:
            continue
        if w[0] == "newmtl":
            name = " ".join(w[1:])
            continue
        if w[0] not in rules or (len(w) > 1 and w[1] == "spectral") or (len(w) > 1 and w[1] == "xyz"):
            continue
        lo, hi, what = rules[w[0]]
        try:
            vals = [float(x) for x in w[1:]]
        except ValueError:
            raise InputError(mtl, f"line {n}: material '{name}': {w[0]} must be numbers, got {' '.join(w[1:])[:60]!r}") from None
        if not vals or not all(math.isfinite(x) and lo <= x <= hi for x in vals):
            rng = f"in [{lo}, {hi}]" if hi != math.inf else f"≥ {lo}"
            raise InputError(mtl, f"line {n}: material '{name}': {w[0]} ({what}) {' '.join(w[1:])[:60]} must be {rng}"
                                  + (" (energy conservation)" if w[0] in ("Kd", "Ka", "Ks") else ""))
