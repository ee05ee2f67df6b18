"""merge-brackets (not in ``run``; it makes an input): a bracket set of LDR photos → one HDR photo.exr.

The photos are JPEG / PNG / TIFF shots of one view at several exposure times (EXIF ``ExposureTime``, read by
OpenImageIO, or ``--times``). The camera's response curve is recovered and the radiance merged by OpenCV's
``photo`` module (Debevec & Malik 1997: ``CalibrateDebevec`` + ``MergeDebevec``, the default; or Robertson et al.
2003: ``CalibrateRobertson`` + ``MergeRobertson``) — nothing of it is written here. OpenCV's response recovery
works on 8-bit values: a 16-bit TIFF is rounded to 8 bits (logged). The photos must be aligned (a tripod, or
aligned beforehand).

Output: ``--out`` (EXR, R,G,B float32, linear Rec.709 as the camera's primaries; relative radiance — its unit is
arbitrary, expose-match finds the cloud's α whatever it is), ``<out stem>.json`` (the times and where they came
from, the response curve, the share of pixels no bracket exposed well) and, with ``--preview``, a tone-mapped PNG.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..config import StageConfig
from ..errors import ConfigError, InputError
from ..runtime import get_logger

log = get_logger("merge-brackets")

METHODS = ("debevec", "robertson")


@dataclass
class MergeBracketsConfig(StageConfig):
    """Options of ``pcrelight merge-brackets``."""

    times: tuple[float, ...] = field(default=(), metadata={
        "help": "exposure time of each photo, in their order [s]; empty: each file's EXIF ExposureTime"})
    method: str = field(default="debevec", metadata={
        "help": "response recovery and merge (OpenCV): debevec (Debevec & Malik 1997) or robertson (Robertson et al. 2003)",
        "choices": METHODS})
    samples: int = field(default=70, metadata={"help": "debevec: pixels sampled for the response curve [pixels]"})
    smoothness: float = field(default=10.0, metadata={"help": "debevec: the response curve's smoothness term λ"})

    def check(self) -> None:
        self.check_choices()
        self._require(all(t > 0 for t in self.times), "times", "must all be > 0 [s]")
        self._require(self.samples >= 16, "samples", "must be ≥ 16")
        self._require(self.smoothness > 0, "smoothness", "must be > 0")


def merge(images: list[np.ndarray], times: np.ndarray, cfg: MergeBracketsConfig) -> tuple[np.ndarray, np.ndarray]:
    """Merge 8-bit RGB photos (H, W, 3) uint8 shot at ``times`` [s]: (HDR RGB (H, W, 3) float32, the recovered
    response (256, 3) float32: exposure E·t per 8-bit code, per channel R, G, B)."""
    import cv2

    bgr = [np.ascontiguousarray(im[..., ::-1]) for im in images]
    t = np.asarray(times, np.float32)
    if cfg.method == "debevec":
        cal = cv2.createCalibrateDebevec(cfg.samples, cfg.smoothness, False)   # a grid of samples: deterministic
        mrg = cv2.createMergeDebevec()
    else:
        cal = cv2.createCalibrateRobertson()
        mrg = cv2.createMergeRobertson()
    response = cal.process(bgr, t)
    hdr = mrg.process(bgr, t, response)
    return np.ascontiguousarray(hdr[..., ::-1]).astype(np.float32), response.reshape(256, 3)[:, ::-1].astype(np.float32)


def _to_uint8(px: np.ndarray) -> np.ndarray:
    return np.clip(np.round(px[..., :3] * 255.0), 0, 255).astype(np.uint8)


def run_merge_brackets(photos: list[str | Path], out: str | Path, cfg: MergeBracketsConfig,
                       preview: str | Path | None = None) -> dict[str, Any]:
    """Read the bracket set, merge it, write ``out`` (EXR) and ``<out stem>.json``; ``preview``: a PNG."""
    from .. import io

    cfg.check()
    t0 = time.perf_counter()
    if len(photos) < 2:
        raise ConfigError(f"merge-brackets needs two or more photos, got {len(photos)}")
    if cfg.times and len(cfg.times) != len(photos):
        raise ConfigError(f"--times gives {len(cfg.times)} exposure time(s) for {len(photos)} photos")
    images, times, bits = [], [], []
    for i, p in enumerate(photos):
        px = io.read_image(p)
        if px.shape[2] < 3:
            raise InputError(p, f"expected an RGB image, got {px.shape[2]} channel(s)")
        if images and px.shape[:2] != images[0].shape[:2]:
            raise InputError(p, f"size {px.shape[1]}x{px.shape[0]} differs from {photos[0]}'s "
                                f"{images[0].shape[1]}x{images[0].shape[0]} (a bracket set is one view)")
        meta = io.image_attributes(p, ("ExposureTime",))
        if float(px.max(initial=0.0)) > 1.0:
            raise InputError(p, f"values above 1 (max {float(px.max()):.4g}): an HDR image, not a bracket shot")
        if cfg.times:
            t = float(cfg.times[i])
        elif "ExposureTime" in meta and float(meta["ExposureTime"]) > 0:
            t = float(meta["ExposureTime"])
        else:
            raise InputError(p, "no exposure time in its EXIF (ExposureTime): give every photo's with --times")
        bits.append(meta.get("format", "?"))
        images.append(_to_uint8(px))
        times.append(t)
    if len(set(times)) < 2:
        raise InputError(photos[0], f"every photo has the same exposure time ({times[0]:g} s): nothing to merge")
    wide = [str(p) for p, b in zip(photos, bits) if b not in ("uint8", "?")]
    if wide:
        log.info("%d photo(s) stored with more than 8 bits (%s): rounded to 8 bits for OpenCV's response recovery",
                 len(wide), ", ".join(wide))
    log.info("read %d photos %dx%d, exposure times %s s (%s)", len(images), images[0].shape[1], images[0].shape[0],
             ", ".join(f"{t:g}" for t in times), "--times" if cfg.times else "EXIF")
    hdr, response = merge(images, np.asarray(times), cfg)
    if not np.all(np.isfinite(hdr)):
        raise InputError(photos[0], "the merge gave non-finite values (are the photos of one view, at the times given?)")
    stack = np.stack(images)
    unexposed = float(np.mean(((stack <= 5) | (stack >= 250)).all(axis=(0, 3))))
    y = io.luminance(hdr)
    log.info("merged (%s): radiance %.4g … %.4g (relative units); %.2f%% of the pixels well exposed in no photo",
             cfg.method, float(y.min()), float(y.max()), 100 * unexposed)
    io.write_image(out, hdr)
    if preview:
        io.write_preview(preview, hdr)
    report = dict(stage="merge-brackets", inputs=[str(p) for p in photos], output=str(out), config=cfg.as_dict(),
                  times=times, times_from="--times" if cfg.times else "EXIF ExposureTime", stored_as=bits,
                  size=[images[0].shape[1], images[0].shape[0]], response=response,
                  luminance_min=float(y.min()), luminance_max=float(y.max()), unexposed_fraction=unexposed,
                  seconds=round(time.perf_counter() - t0, 3))
    io.write_json(Path(out).with_suffix(".json"), report)
    log.info("wrote %s in %.2f s", out, report["seconds"])
    return report
