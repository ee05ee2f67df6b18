"""The composite against its truth (issue 44): ``python -m bench.composite.composite_error COMPOSITE_DIR [SCENE]
[--csv OUT.csv] [--png OUT.png]``.

Reads COMPOSITE_DIR/composite.exr (relight --photo … --exposure …) and SCENE/truth/photo_{with,without}.exr
(:func:`pipeline.scene.make_scene.photo_references`, the photo's view path-traced with the Lambert object and
without). Reports, with :func:`pipeline.metrics.compare_to_reference` (the reference's own noise beside every
figure), on 2×2, 4×4 and 8×8 blocks:

- ``whole``: the composite against the path-traced photo with the object, over every pixel;
- ``shadow``: the same over the shadow region: 4×4 blocks where the truth's with / without differs from 1 by more
  than 5 % and by more than 3 × its noise, off the object (the object's own pixels are ``object``);
- ``object``: the object's pixels (coverage 1);
- ``floor``: the photo itself against the path-traced photo without the object (its own noise and sub-pixel
  jitter: what no composite can beat);
- the matte: the mean of shadow.G (P'/P) over the shadow region against the truth's mean with / without there.

The PNG: composite | truth with | photo (top), the matte | the truth's with / without | |error| ×4 (bottom).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from bench.benchlib import write_rows
from pipeline import display, io
from pipeline.metrics import compare_to_reference

SHADOW_MIN = 0.05   # the shadow region: |with / without − 1| above this ...
SHADOW_Z = 3.0      # ... and above this many σ of the truth's ratio noise (4×4 blocks)


def read_layers(path: Path) -> dict[str, np.ndarray]:
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(path))
    px = buf.get_pixels(oiio.FLOAT)
    return {n: px[..., i] for i, n in enumerate(buf.spec().channelnames)}


def shadow_region(with_: np.ndarray, with_var: np.ndarray, without: np.ndarray, without_var: np.ndarray,
                  off_object: np.ndarray, k: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) bool: the pixels of k×k blocks (off the object) whose truth ratio with / without (luminance) differs from
    1 by > SHADOW_MIN and > SHADOW_Z σ; and the block ratio image (H//k, W//k)."""
    lum = lambda a: a @ np.array([0.2126, 0.7152, 0.0722])  # noqa: E731
    H, W = off_object.shape
    Hb, Wb = H // k, W // k

    def bm(x: np.ndarray) -> np.ndarray:   # (Hb, Wb) block means over blocks wholly off the object, NaN elsewhere
        s = (x * off_object)[:Hb * k, :Wb * k].reshape(Hb, k, Wb, k).sum((1, 3))
        n = off_object[:Hb * k, :Wb * k].reshape(Hb, k, Wb, k).sum((1, 3))
        return np.where(n == k * k, s / (k * k), np.nan)

    bw, bo = bm(lum(with_)), bm(lum(without))
    vw, vo = bm(lum(with_var)) / (k * k), bm(lum(without_var)) / (k * k)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = bw / bo
        sig = np.abs(r) * np.sqrt(vw / np.maximum(bw, 1e-30) ** 2 + vo / np.maximum(bo, 1e-30) ** 2)
        sel = np.isfinite(r) & (np.abs(r - 1) > SHADOW_MIN) & (np.abs(r - 1) > SHADOW_Z * sig)
    full = np.zeros((H, W), bool)
    full[:Hb * k, :Wb * k] = np.repeat(np.repeat(sel, k, 0), k, 1)
    return full & off_object, r


def evaluate(composite: Path, scene: Path, photo: Path | None = None, label: str = "",
             png: Path | None = None) -> dict:
    """The module docstring's figures for COMPOSITE/composite.exr against SCENE/truth/photo_*.exr (``photo``: the
    plate it was composited into, default SCENE/photo.exr); with ``png`` the side-by-side figure."""
    L = read_layers(composite / "composite.exr")
    est = np.stack([L["R"], L["G"], L["B"]], -1)
    tr = scene / "truth"
    w_, wv = io.read_image(tr / "photo_with.exr")[..., :3], io.read_image(tr / "photo_with_var.exr")[..., :3]
    o_, ov = io.read_image(tr / "photo_without.exr")[..., :3], io.read_image(tr / "photo_without_var.exr")[..., :3]
    photo = io.read_image(photo or scene / "photo.exr")[..., :3]
    H, W = est.shape[:2]
    cover = L["A"]
    allpx = np.ones((H, W), bool)
    off = cover <= 0
    shadow, rb = shadow_region(w_, wv, o_, ov, off)
    rows = []
    for name, e, ref, var, m in (("whole", est, w_, wv, allpx), ("shadow", est, w_, wv, shadow),
                                 ("object", est, w_, wv, cover >= 1), ("floor", photo, o_, ov, allpx)):
        row = {"label": label, "region": name, "pixels": int(m.sum())}
        for k in (2, 4, 8):
            c = compare_to_reference(e, ref, m, var, block=k)
            row.update({f"rms_{k}x{k}": round(c["rms_block"], 5), f"ref_noise_{k}x{k}": round(c["ref_noise_block"], 5)})
            if k == 4:
                row.update(mean_ratio=round(c["mean_ratio"], 5),
                           mean_ratio_rgb=" ".join(f"{x:.4f}" for x in c["mean_ratio_rgb"]),
                           mean_ratio_noise=round(c["mean_ratio_noise"], 5))
        rows.append(row)
    matte = L["shadow.G"]
    lum = lambda x: x @ np.array([0.2126, 0.7152, 0.0722])  # noqa: E731
    truth_ratio = float(lum(w_)[shadow].sum() / lum(o_)[shadow].sum()) if shadow.any() else float("nan")
    est_ratio = float((matte[shadow] * lum(photo)[shadow]).sum() / lum(photo)[shadow].sum()) if shadow.any() else float("nan")
    for r in rows:
        r.update(matte_truth=round(truth_ratio, 5), matte_composite=round(est_ratio, 5))
    if png is not None:
        ex, _ = display.auto_exposure(photo)
        tm = lambda x: display.tonemap(x, exposure=ex)  # noqa: E731
        grey = lambda x: np.repeat(np.clip(x, 0, 1)[..., None], 3, 2)  # noqa: E731
        trr = np.ones((H, W))
        tr_ratio = np.nan_to_num(np.repeat(np.repeat(rb, 4, 0), 4, 1), nan=1.0)
        trr[:tr_ratio.shape[0], :tr_ratio.shape[1]] = tr_ratio
        err = np.abs(lum(est) - lum(w_)) / max(float(lum(w_).mean()), 1e-30) * 4
        edge = shadow ^ np.roll(shadow, 1, 0) | shadow ^ np.roll(shadow, 1, 1)
        e_img = grey(err)
        e_img[edge] = [1.0, 0.2, 0.2]
        top = np.concatenate([tm(est), tm(w_), tm(photo)], 1)
        bot = np.concatenate([grey(np.where(off, (matte - 0.5) * 2, 1)), grey((np.where(off, trr, 1) - 0.5) * 2), e_img], 1)
        io.write_png(png, np.concatenate([top, bot], 0))
    return {"rows": rows, "matte": {"shadow_pixels": int(shadow.sum()), "truth_ratio": truth_ratio,
                                    "composite_ratio": est_ratio}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("composite", type=Path)
    ap.add_argument("scene", type=Path, nargs="?", default=Path("data_samples"))
    ap.add_argument("--photo", type=Path, default=None, help="the plate (default SCENE/photo.exr)")
    ap.add_argument("--csv", type=Path, default=None)
    ap.add_argument("--png", type=Path, default=None)
    ap.add_argument("--label", default="")
    a = ap.parse_args()
    summary = evaluate(a.composite, a.scene, a.photo, a.label, a.png)
    print(json.dumps(summary, indent=1))
    if a.csv:
        write_rows(a.csv, summary["rows"])


if __name__ == "__main__":
    main()
