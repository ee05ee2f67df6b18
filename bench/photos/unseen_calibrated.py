"""reproject --unseen calibrated vs poisson vs lookalike vs the oracle with one photo (issue 25), relit against the
path tracer and against relight on the exact cloud (:mod:`end_to_end`'s functions).

The photo's camera and α are taken from a set's exposure.npz (``photos_world_to_camera``/``photos_K`` of that
photo and its own registration's α, ``photos_alpha_register``: what expose-match writes for that photo alone —
the same registration on the same photo and cloud — without registering it again); the faces are rendered and
matched (``run --from render-cubemaps --to patchmatch --no-plan``: --unseen calibrated/lookalike need them).

Run: ``python -m bench.photos.unseen_calibrated CODE_DIR SCENE SET_WORKSPACE PHOTO_INDEX OUT MATERIALS`` (e.g. ``. data_samples
W/set_bright_lights_sun 0 W lambert`` after ``end_to_end.py --sets bright+lights+sun --out W``) →
OUT/calibrated_<photo>.csv and a line per row on stdout."""
import csv, subprocess, sys
from pathlib import Path
import numpy as np
code = Path(sys.argv[1]); sys.path.insert(0, str(code)); sys.path.insert(0, str(code / "bench"))
from pipeline import io
from pipeline.measure.evaluate import photo_truths, photo_view
import end_to_end as e2e

scene, set_ws, idx, out, mats = Path(sys.argv[2]), Path(sys.argv[3]), int(sys.argv[4]), Path(sys.argv[5]), sys.argv[6].split(",")
config = str(code / "configs" / "demo.toml")
ph = photo_truths(scene)[idx]
ws = out / f"single_{ph['name']}"
inputs = photo_view(scene, ph, ws / "inputs")
ex = io.read_npz(set_ws / "exposure.npz", "pcrelight.exposure/1")
single = {k: v for k, v in ex.items() if not k.startswith("photos")}
single.update(alpha=np.float64(ex["photos_alpha_register"][idx]), alpha_source=np.asarray("register"),
              log2_alpha=np.float64(np.log2(ex["photos_alpha_register"][idx])),
              photo_K=ex["photos_K"][idx], photo_world_to_camera=ex["photos_world_to_camera"][idx])
if not (ws / "exposure.npz").exists():
    io.write_npz(ws / "exposure.npz", "pcrelight.exposure/1", **single)
    io.write_image(ws / "photo_ldr.exr", np.clip(io.read_image(inputs / "photo.exr")[..., :3] * float(single["alpha"]), 0, 1).astype(np.float32))
if not (ws / "hdr_faces" / "renderings.npz").exists():
    subprocess.run([str(Path(sys.executable).with_name("pcrelight")), "run", config, "--inputs", str(inputs), "--workspace", str(ws),
                    "--from", "render-cubemaps", "--to", "patchmatch", "--no-plan", "--no-previews", "-q"], check=True)
at = float(io.read_npz(scene / ph["truth"], "pcrelight.truth/1")["alpha_true"])
exact, rows = {}, []
def rv(cloud, work, units="ldr", keep=None):
    return e2e.relight_vs_reference(scene, cloud, work, "hybrid", units=units, materials=mats, reuse=True,
                                    exact=None if keep is not None else exact, keep=keep)
def add(name, res):
    for (view, mat), r in res.items():
        rows.append({"photo": ph["name"], "cloud": name, "alpha_rel_error": float(single["alpha"]) / at - 1, "view": view,
                     "material": mat, **{k: r.get(k) for k in e2e.FIELDS if k in r}})
add("gt", rv(scene / "cloud_gt.ply", out / "base_gt", units="scene", keep=exact))
add("seen exact, rest LDR", rv(e2e.oracle_cloud(scene, ph, out, True), out / f"oracle_{ph['name']}"))
for mode in ("poisson", "calibrated", "lookalike"):
    hdr = ws / f"cloud_hdr_unseen_{mode}.ply"
    if not hdr.exists():
        hdr = e2e.unseen_variant(ws, inputs, config, mode)
    add(f"pipeline unseen={mode}", rv(hdr, ws / f"relit_unseen_{mode}"))
with open(out / f"calibrated_{ph['name']}.csv", "w", newline="") as fh:
    w = csv.DictWriter(fh, fieldnames=["photo", "cloud", "alpha_rel_error", "view", "material"] + [f for f in e2e.FIELDS if f not in ("scene", "photo", "cloud", "alpha_rel_error", "alpha_source", "view", "material")], extrasaction="ignore")
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.4f}" if isinstance(v, float) else v) for k, v in r.items()})
for r in rows:
    print(r["photo"], r["cloud"], r["view"], r["material"], *(f"{r[k]:.3f}" for k in ("ratio_r", "ratio_g", "ratio_b", "rms_block")),
          *(f"{r[k]:.3f}" for k in ("exact_ratio_r", "exact_ratio_g", "exact_ratio_b", "exact_rms_block") if r.get(k) is not None), flush=True)
