"""Why the HDR expansion misses on a ground-truth scene (issue 14): separates the error sources.

Runs the CI-sized expansion (render-cubemaps 128², patchmatch 2 iterations, as
tests/test_regression_expansion.py) twice — with expose-match's α (Eq. 1) and with α forced to
``alpha_true`` — each with ``--transfer lum`` and ``rgb`` (poisson in the same mode), and measures:

* ``bins``: on the overexposed points within the photo's range that were projected, the ratio
  (sum of the expanded luminance / sum of the true one, LDR units) per bin of true luminance;
* ``nnf``: how many PatchMatch correspondences are geometric — the face pixel's 3-D point (from the
  face's depth) projected with the photo's true camera (truth.npz, never given to the pipeline) lands
  within 3 / 10 photo pixels of the matched photo position (among those whose projection lies in
  the photo's frame);
* ``relight``: the object relit (hybrid, relight's default preset, Lambert 0.8; :mod:`end_to_end`) with each cloud against the
  path-traced ``gather_<view>_lambert`` reference (cloud in LDR units ÷ e): per-channel mean ratio,
  per-pixel and 4×4 block-mean relative RMS; the exact cloud (cloud_gt) gives PBGI's own error.

Run: ``.venv/bin/python -m bench.expansion.diagnose_expansion [--scene data_samples] [--out bench/_work/diagnose]``
→ ``<out>/diagnosis.json`` and a Markdown summary on stdout (about 10 minutes on 2 cores for small).
"""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np


from pipeline.expansion import expose_match, itmo, patchmatch, poisson, render_cubemaps, reproject
from pipeline import io  # noqa: E402
from pipeline.config import resolve  # noqa: E402

BINS = ((1, 2), (2, 4), (4, 8), (8, 1e9))


def chain(scene: Path, out: Path, alpha: float | None, seed: int = 0) -> dict[str, Path]:
    """expose-match (or α forced) → patchmatch (2 iterations) → reproject + poisson, lum and rgb."""
    s = {"seed": seed}
    photo, ldr = scene / "photo.exr", scene / "cloud_ldr.ply"
    out.mkdir(parents=True, exist_ok=True)
    expose_match.run_expose_match(photo, ldr, out / "exposure.npz", out / "photo_ldr.exr",
                                  resolve(expose_match.ExposeMatchConfig, None, "expose-match", s))
    if alpha is not None:  # the same file with α replaced, and Eq. 1 at that α
        ex = {k: v for k, v in io.read_npz(out / "exposure.npz", "pcrelight.exposure/1").items() if k != "schema"}
        ex.update(alpha=np.float64(alpha), log2_alpha=np.float64(np.log2(alpha)))
        io.write_npz(out / "exposure.npz", "pcrelight.exposure/1", **ex)
        io.write_image(out / "photo_ldr.exr", expose_match.apply_exposure(io.read_image(photo)[..., :3], alpha))
    patchmatch.run_patchmatch(out.parent / "cubemaps", photo, out / "photo_ldr.exr", out / "exposure.npz",
                              out / "faces", resolve(patchmatch.PatchmatchConfig, None, "patchmatch",
                                                     {**s, "iterations": 2}))
    res = {}
    for tf in ("lum", "rgb"):
        reproject.run_reproject(ldr, out.parent / "cubemaps", out / "faces", out / f"proj_{tf}.ply",
                                resolve(reproject.ReprojectConfig, None, "reproject", {**s, "transfer": tf}))
        poisson.run_poisson(out / f"proj_{tf}.ply", out / f"hdr_{tf}.ply",
                            resolve(poisson.PoissonConfig, None, "poisson", {**s, "mode": tf}), ldr=ldr)
        res[tf] = out / f"hdr_{tf}.ply"
    return res


def bin_ratios(scene: Path, proj: Path, hdr: Path) -> dict:
    tr = io.read_npz(scene / "truth" / "truth.npz", "pcrelight.truth/1")
    e, k = float(tr["e"]), float(tr["k"])
    truth = io.read_cloud(scene / "cloud_gt.ply").colors.astype(np.float64) * e
    peak = float(io.luminance(io.read_image(scene / "photo.exr")[..., :3]).max()) / k * e
    yt = io.luminance(truth)
    sel = tr["overexposed"].astype(bool) & (yt <= peak) & (io.read_cloud(proj).source == 1)
    yh = io.luminance(io.read_cloud(hdr).colors.astype(np.float64))
    out = {"projected_in_range": int(sel.sum()),
           "rgb_sum_ratio": (io.read_cloud(hdr).colors[sel].sum(0) / truth[sel].sum(0)).round(4).tolist()}
    for lo, hi in BINS:
        b = sel & (yt > lo) & (yt <= hi)
        out[f"Y_true_in_({lo},{hi:g}]"] = {"n": int(b.sum()),
                                           "ratio": round(float(yh[b].sum() / yt[b].sum()), 4) if b.any() else None}
    return out


def nnf_geometry(scene: Path, cub: Path, alpha: float, seed: int = 0) -> dict:
    """Share of PatchMatch correspondences that agree with the photo's true camera."""
    tr = io.read_npz(scene / "truth" / "truth.npz", "pcrelight.truth/1")
    Kp, Wp = tr["photo_K"], tr["photo_world_to_camera"]
    P = io.read_image(scene / "photo.exr")[..., :3].astype(np.float64)
    H, W = P.shape[:2]
    cams = io.read_npz(cub / "cameras.npz", "pcrelight.cameras/1")
    cfg = patchmatch.PatchmatchConfig(iterations=2, seed=seed)
    cfg.check()
    T = patchmatch.to_space(np.clip(P * alpha, 0, 1), cfg.space)
    err, sat = [], []
    for i in range(len(cams["K"])):
        img = io.read_image(cub / f"face_{i:03d}.exr")
        rgb, cov, Z = img[..., :3].astype(np.float64), img[..., 3], img[..., 4].astype(np.float64)
        if not ((cov > 0) & (itmo.luminance(rgb) > cfg.t_l)).any():
            continue
        _, q, _, nnf = patchmatch.expand_face_pmatch(rgb, cov, T, P, alpha, cfg, seed * 1000003 + i)
        r, c = np.nonzero(q < patchmatch.Q_NONE)
        K, w2c = cams["K"][i], cams["world_to_camera"][i]
        d = Z[r, c]
        pc = np.stack([(c + 0.5 - K[0, 2]) * d / K[0, 0], (r + 0.5 - K[1, 2]) * d / K[1, 1], -d], 1)
        X = (pc - w2c[:3, 3]) @ w2c[:3, :3]
        qc = X @ Wp[:3, :3].T + Wp[:3, 3]
        uv = qc @ Kp.T
        uv = uv[:, :2] / uv[:, 2:3]
        inside = (qc[:, 2] > 0) & (uv[:, 0] > 0) & (uv[:, 0] < W) & (uv[:, 1] > 0) & (uv[:, 1] < H)
        err.append(np.where(inside, np.hypot(*(uv - nnf[r, c, :2]).T), np.nan))
        sat.append(itmo.luminance(rgb[r, c]) > cfg.t_l)
    e, s = np.concatenate(err), np.concatenate(sat)
    inf = np.isfinite(e)
    return {"matched": int(len(e)), "true_projection_in_photo": int(inf.sum()),
            "within_3px": round(float(np.mean(e[inf] < 3)), 4), "within_10px": round(float(np.mean(e[inf] < 10)), 4),
            "median_error_px": round(float(np.median(e[inf])), 1),
            "within_3px_overexposed_pixels": round(float(np.mean(e[inf & s] < 3)), 4)}


def relight_vs_reference(scene: Path, cloud: Path, units: str, block: int = 4) -> dict:
    """:func:`end_to_end.relight_vs_reference` (hybrid, Lambert 0.8, both views) in a scratch folder:
    per view the per-channel ratio, pixel and block RMS."""
    from end_to_end import relight_vs_reference as e2e

    with tempfile.TemporaryDirectory(prefix="pcrelight-diag-") as td:
        res = e2e(scene, cloud, Path(td), "hybrid", block=block, units=units)
    return {view: {"ratio_rgb": [round(float(r[f"ratio_{c}"]), 4) for c in "rgb"], "pixel_rms": round(float(r["rms"]), 4),
                   f"block{block}_rms": round(float(r["rms_block"]), 4)} for (view, _), r in res.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="data_samples")
    ap.add_argument("--out", default="bench/_work/diagnose")
    a = ap.parse_args()
    scene, out = Path(a.scene), Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    tr = io.read_npz(scene / "truth" / "truth.npz", "pcrelight.truth/1")
    at = float(tr["alpha_true"])
    render_cubemaps.run_render_cubemaps(scene / "cloud_ldr.ply", out / "cubemaps",
                                        resolve(render_cubemaps.RenderCubemapsConfig, None, "render-cubemaps",
                                                {"seed": 0, "size": 128}))
    res: dict = {"scene": str(scene), "alpha_true": at, "runs": {}}
    clouds = {"gt": (scene / "cloud_gt.ply", "scene"), "ldr": (scene / "cloud_ldr.ply", "ldr")}
    for name, forced in (("alpha_eq1", None), ("alpha_true", at)):
        d = out / name
        hdr = chain(scene, d, forced)
        alpha = float(io.read_npz(d / "exposure.npz", "pcrelight.exposure/1")["alpha"])
        run = {"alpha": alpha, "alpha_rel_error": alpha / at - 1, "nnf": nnf_geometry(scene, out / "cubemaps", alpha)}
        for tf, p in hdr.items():
            run[tf] = bin_ratios(scene, d / f"proj_{tf}.ply", p)
            clouds[f"{name}_{tf}"] = (p, "ldr")
        res["runs"][name] = run
    res["relight"] = {k: relight_vs_reference(scene, p, u) for k, (p, u) in clouds.items()}
    io.write_json(out / "diagnosis.json", res)
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
