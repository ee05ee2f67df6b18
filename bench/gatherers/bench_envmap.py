"""The envmap gatherer beside the PBGI gatherers on the shipped scene, against the path-traced references.

    .venv/bin/python -m bench.gatherers.bench_envmap [SCENE_DIR] [--bsh bsh.npz] [--methods envmap,classic,hybrid]
        [--sizes 256,512] [--views view1,view2] [--materials lambert] [--m 24] [--out bench/gatherers/envmap_small.csv]
    .venv/bin/python -m bench.gatherers.bench_envmap --diffuse [SCENE_DIR]     # irradiance map vs SH9 on the captured room

Each row is one ``run_relight`` call with relight's defaults (adaptive shading 0.3; the object's surfels, 2
bounces, for the PBGI methods — auto is off for envmap) but for the method, the material and the size: the
object is rendered at size² (a multiple of the references' 128²), box-averaged to 128² (pixels whose
sub-pixels are all on the object) and compared on 4×4 block means (``pipeline.metrics.compare_to_reference``,
blocks entirely on the object; 2×2 and 8×8 beside them) with ``truth/full_<view>_<material>`` (the knot in the room: all bounces, its
own shadows) and ``truth/gather_<view>_<material>`` (the room without the knot: the light arriving at its
surface — what an environment map and the paper's PBGI model see; a method written ``classic:paper`` runs
with ``--surfels -1``, that model). Seconds: the whole relight call (wall) and
the method's own share (stats.json ``time_s`` less read, G-buffer and write). Per view and material a side-by-side
PNG (``<out stem>_<view>_<material>.png``: the methods at the first size, box-averaged to 128², then the gather and
full references; one exposure). The BSH: build-bsh's defaults
on the exact HDR cloud (``cloud_gt.ply``), as bench_relight_truth.py.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]

from bench.benchlib import material_kw, truth_bsh, write_rows

from pipeline import io  # noqa: E402
from pipeline.metrics import compare_to_reference  # noqa: E402
from pipeline.relight.relight import RelightConfig, run_relight  # noqa: E402
from pipeline.runtime import setup_logging  # noqa: E402


def downsample(img: np.ndarray, s: int) -> np.ndarray:
    """(s·H, s·W, 4) → (H, W, 4): RGB box means, alpha 1 where every sub-pixel is covered."""
    H, W = img.shape[0] // s, img.shape[1] // s
    out = np.zeros((H, W, 4), np.float32)
    out[..., :3] = img[..., :3].reshape(H, s, W, s, 3).mean((1, 3))
    out[..., 3] = (img[..., 3] > 0.5).reshape(H, s, W, s).all((1, 3))
    return out


def side_by_side(path: Path, panels: list[tuple[str, np.ndarray]]) -> None:
    """One PNG of the (H, W, 4) images left to right (Reinhard at one exposure: the last panel's, on its object
    pixels), the labels in a text file beside it."""
    from pipeline import display

    io.write_png(path, display.side_by_side([img for _, img in panels], exposure_from=-1))
    path.with_suffix(".txt").write_text("left to right: " + ", ".join(n for n, _ in panels) + "\n")
    print(f"wrote {path}")


def diffuse_rows(scene: Path, bsh: Path) -> list[dict]:
    """Irradiance map (64×32, 002's 32×16) vs 3-band SH on the room captured at the object's centre and two other
    places, against the exact convolution of the 128² capture over 2000 random normals."""
    from pipeline import gl
    from pipeline.bsh.format import nodes_from_bsh
    from pipeline.gather import GatherParams
    from pipeline.gather.envmap import EnvmapGatherer, diffuse_error

    meta = io.read_json(scene / "scene.json")
    b = io.read_npz(bsh, "pcrelight.bsh/1")
    ctx = gl.create_context()
    gl.bind_dummy_framebuffer(ctx)
    rows = []
    places = {"object centre": meta["object"]["center"], "0.8 m above the floor": [1.5, 0.8, -0.5],
              "under a lamp": [-1.5, 3.3, 5.0]}
    for obj, c in places.items():
        g = EnvmapGatherer(ctx, nodes_from_bsh(b), GatherParams(16, object_center=tuple(c)), splat_radius=b.get("splat_radius"),
                           emitters=b.get("emitters"))
        faces = g.capture(np.asarray(c, np.float64))
        e = diffuse_error(faces[..., :3])
        rows.append({"place": obj, "center": c, **{k: round(v, 4) for k, v in e.items()},
                     "empty_share": round(g.info["empty_share"], 5)})
        print(rows[-1], flush=True)
        g.release()
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path, nargs="?", default=ROOT / "data_samples")
    ap.add_argument("--bsh", type=Path)
    ap.add_argument("--methods", default="envmap,classic,hybrid")
    ap.add_argument("--sizes", default="256,512")
    ap.add_argument("--views", default="view1,view2")
    ap.add_argument("--materials", default="lambert")
    ap.add_argument("--m", type=int, default=24)
    ap.add_argument("--adaptive", type=float, default=None, help="relight --adaptive for every method (default: relight's)")
    ap.add_argument("--out", type=Path, default=HERE / "envmap_small.csv")
    ap.add_argument("--work", type=Path, default=ROOT / "bench" / "_work" / "envmap")
    ap.add_argument("--diffuse", action="store_true", help="only the diffuse measurement (bench/gatherers/envmap_diffuse.csv)")
    a = ap.parse_args()
    setup_logging(-1)
    bsh = truth_bsh(a.scene, a.bsh, a.work)
    if a.diffuse:
        write_rows(a.out.with_name("envmap_diffuse.csv") if a.out.name == "envmap_small.csv" else a.out,
                   diffuse_rows(a.scene, bsh))
        return
    rows = []
    for view in a.views.split(","):
        for mat in a.materials.split(","):
            refs = {k: (io.read_image(a.scene / "truth" / f"{k}_{view}_{mat}.exr"),
                        io.read_image(a.scene / "truth" / f"{k}_{view}_{mat}_var.exr")) for k in ("full", "gather")}
            h, w = refs["full"][0].shape[:2]
            panels: list[tuple[str, np.ndarray]] = []
            for size in (int(s) for s in a.sizes.split(",")):
                s = size // w
                for method in a.methods.split(","):
                    kw = {} if a.adaptive is None else {"adaptive": a.adaptive}
                    name, _, model = method.partition(":")        # "classic:paper" = --surfels -1
                    if model == "paper":
                        kw["surfels"] = -1
                    elif model:
                        raise SystemExit(f"unknown model {model!r} in {method!r} (only :paper)")
                    cfg = RelightConfig(microbuffer=a.m, method=name, size=f"{w * s}x{h * s}", **kw, **material_kw(mat))
                    cfg.check()
                    out = a.work / f"{view}_{mat}_{size}_{name}_{model or 'default'}_{cfg.adaptive:g}"
                    t0 = time.perf_counter()
                    st = run_relight(bsh, out, cfg, scene_path=a.scene / "scene.json", view=view)
                    dt = time.perf_counter() - t0
                    img = downsample(io.read_image(out / "relit.exr"), s)
                    own = sum(v for k, v in st["time_s"].items() if k not in ("read", "gbuffer", "write"))
                    row = {"view": view, "material": mat, "size": size, "method": method, "m": a.m, "adaptive": cfg.adaptive,
                           "seconds": round(dt, 2), "method_seconds": round(own, 2),
                           "covered_pixels": st["covered_pixels"]}
                    for kind, (ref, var) in refs.items():
                        sel = (img[..., 3] > 0.5) & (ref[..., 3] > 0.5)
                        c = compare_to_reference(img, ref, sel, ref_var=var, block=4)
                        rgb = c["mean_ratio_rgb_block"]
                        row.update({f"{kind}_ratio": round(c["mean_ratio_block"], 4),
                                    **{f"{kind}_ratio_{ch}": round(float(v), 4) for ch, v in zip("rgb", rgb)},
                                    f"{kind}_block_rms": round(c["rms_block"], 4),
                                    f"{kind}_block_noise": round(c["ref_noise_block"], 4),
                                    f"{kind}_blocks": c["n_blocks"]})
                        for k in (2, 8):                          # per-pixel scale (bands, sparkles) and coarse
                            ck = compare_to_reference(img, ref, sel, ref_var=var, block=k)
                            row.update({f"{kind}_block{k}_rms": round(ck["rms_block"], 4),
                                        f"{kind}_block{k}_noise": round(ck["ref_noise_block"], 4)})
                    rows.append(row)
                    print(row, flush=True)
                    if size == int(a.sizes.split(",")[0]):
                        panels.append((f"{method} {size}²", img))
            panels += [(f"truth gather_{view}_{mat}", refs["gather"][0]), (f"truth full_{view}_{mat}", refs["full"][0])]
            side_by_side(a.out.with_name(f"{a.out.stem}_{view}_{mat}.png"), panels)
    write_rows(a.out, rows)


if __name__ == "__main__":
    main()
