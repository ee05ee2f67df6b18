"""Images: EXR / Radiance HDR / PNG through OpenImageIO (read as float32, written atomically and
byte-deterministically), tone-mapped previews and matplotlib figures."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError, OutputError
from .common import PathLike, atomic_path, first_line, must_exist


def read_image(path: PathLike) -> np.ndarray:
    """Read an EXR / Radiance HDR / PNG image as float32 (H, W, C), linear as stored.

    (PNG and other 8-bit formats are returned as stored, in [0,1], not decoded.)
    """
    p = must_exist(path)
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
        raise InputError(p, f"corrupt or truncated image ({type(e).__name__}: {first_line(e)})") from None
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
        raise InputError(p, f"not a readable image ({type(e).__name__}: {first_line(e)})") from None
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
    p = must_exist(path)
    inp = _open_image(p)
    try:
        spec = inp.spec()
        out = {n: spec.getattribute(n) for n in names}
        out["format"] = str(spec.format)
        return {k: v for k, v in out.items() if v is not None}
    except (UnicodeDecodeError, ValueError, RuntimeError) as e:
        raise InputError(p, f"not a readable image ({type(e).__name__}: {first_line(e)})") from None
    finally:
        inp.close()


def image_channels(path: PathLike) -> list[str]:
    """The channel names stored in an image file."""
    p = must_exist(path)
    inp = _open_image(p)
    try:
        return list(inp.spec().channelnames)
    except (UnicodeDecodeError, ValueError, RuntimeError) as e:
        raise InputError(p, f"not a readable image ({type(e).__name__}: {first_line(e)})") from None
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
    from ..display import tonemap as _tonemap

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
