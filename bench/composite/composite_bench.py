"""The composite's error table and times (issue 44): ``python -m bench.composite.composite_bench [--ws out/demo]
[--out bench/composite]``.

Three runs of ``relight --photo … --exposure …`` on a demo workspace (``make demo``: its bsh.npz, exposure.npz),
each against data_samples/truth/photo_{with,without}.exr (:mod:`bench.composite.composite_error`); ``--scene`` another
room with its photo references (make-scene ``photo_ref_spp``, or ``bench.composite.photo_truth``), ``--bsh`` its BSH and
``--runs true_camera,clean_plate`` for a room without a demo workspace (the true camera's exposure from its truth):

- ``registered``: the shipped photo, the camera expose-match registered (the whole chain: what ``make demo`` shows);
- ``true_camera``: the shipped photo with its true camera and α (truth/truth.npz): the composite's own error, with
  the registration's taken out;
- ``clean_plate``: the true camera, the plate the 1024-path render of the room without the object
  (truth/photo_without.exr) instead of the 64-path photo: the composite's error with the plate's noise taken out.

Writes composite.csv (one row per run and region, with the differential pass's and the whole relight's seconds and
CPU seconds) and <csv stem>_<run>.png (composite | truth | plate; the matte | the truth's with/without | |error| ×4)."""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from bench.benchlib import ROOT, write_rows
from bench.composite.composite_error import evaluate


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ws", type=Path, default=ROOT / "out" / "demo")
    ap.add_argument("--scene", type=Path, default=ROOT / "data_samples")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "composite")
    ap.add_argument("--work", type=Path, default=ROOT / "bench" / "_work" / "composite")
    ap.add_argument("--bsh", type=Path, default=None, help="the room's BSH (default: the workspace's bsh.npz)")
    ap.add_argument("--runs", default="registered,true_camera,clean_plate")
    ap.add_argument("--csv", default="composite.csv", help="the table's file name in --out")
    ap.add_argument("--exact-cloud", action="store_true",
                    help="--bsh is the room's exact cloud (radiance units): the true exposure's α is 1 / the photo's scale k "
                         "(the expanded cloud's units are e × radiance: α_true = e / k)")
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    a.out.mkdir(parents=True, exist_ok=True)
    bsh = a.bsh or a.ws / "bsh.npz"
    tr = np.load(a.scene / "truth" / "truth.npz")
    alpha = 1.0 / float(json.loads((a.scene / "scene.json").read_text())["photo_scale_k"]) if a.exact_cloud \
        else float(tr["alpha_true"])
    if (a.ws / "exposure.npz").exists():
        ex = dict(np.load(a.ws / "exposure.npz"))
    else:   # no expose-match run: the schema's histogram-search record is one entry, the true α itself
        l2 = float(np.log2(alpha))
        ex = {"log2_alpha": np.float64(l2), "distance": np.float64(0.0), "tried_log2_alpha": np.array([l2]),
              "tried_distance": np.zeros(1), "tried_phase": np.zeros(1, np.int32), "cloud_hist": np.zeros(1),
              "photo_hist": np.zeros(1), "hist_space": np.array("linear"), "iterations": np.int32(0),
              "alpha_source": np.array("truth")}
    ex.update(photo_K=tr["photo_K"], photo_world_to_camera=tr["photo_world_to_camera"], alpha=np.float64(alpha))
    true_ex = a.work / "exposure_true.npz"
    from pipeline import io

    io.write_npz(true_ex, "pcrelight.exposure/1", **{k: v for k, v in ex.items() if k != "schema"})
    photo, clean = a.scene / "photo.exr", a.scene / "truth" / "photo_without.exr"
    runs = [r for r in [("registered", photo, a.ws / "exposure.npz"), ("true_camera", photo, true_ex),
                        ("clean_plate", clean, true_ex)] if r[0] in a.runs.split(",")]
    rows = []
    env = {**os.environ, "PCRELIGHT_CACHE_DIR": "off"}
    for name, plate, exposure in runs:
        out = a.work / name
        c0, t0 = _children_cpu(), time.perf_counter()
        subprocess.run([sys.executable, str(ROOT / "cli.py"), "relight", "--bsh", str(bsh), "--object",
                        str(a.scene / "object.glb"), "--scene", str(a.scene / "scene.json"), "--photo", str(plate),
                        "--exposure", str(exposure), "--config", str(ROOT / "configs" / "demo.toml"), "--out", str(out),
                        "-q"], check=True, env=env)
        wall, cpu = time.perf_counter() - t0, _children_cpu() - c0
        st = json.loads((out / "stats.json").read_text())
        comp = st["composite"]
        res = evaluate(out, a.scene, plate, name, a.out / f"{Path(a.csv).stem}_{name}.png")
        for r in res["rows"]:
            r.update(relight_wall_s=round(wall, 2), relight_cpu_s=round(cpu, 2),
                     differential_s=st["time_s"].get("differential"), composite_s=comp["seconds"],
                     composite_cpu_s=comp["cpu_s"], receivers_walked=comp.get("walked"),
                     load_1min=round(os.getloadavg()[0], 2))
        rows += res["rows"]
        print(name, json.dumps(res["matte"]), {r["region"]: (r["mean_ratio"], r["rms_4x4"]) for r in res["rows"]},
              f"relight {wall:.1f} s wall / {cpu:.1f} CPU s, differential {st['time_s'].get('differential')} s",
              flush=True)
    write_rows(a.out / a.csv, rows)


if __name__ == "__main__":
    main()
