"""Scale invariance on a room (issue 45 §2): the room's exact cloud, its object and view1 × s, build-bsh and relight with
their defaults (or the options given), against the unscaled image.

    .venv/bin/python -m bench.relight.bench_scale SCENE [--size 128x128] [--scales 1e-3,…] [--bsh-opts=--emitters=none]
        [--out bench/relight/scale_lamps.csv]

Each row: s, the relative RMS of the RGB image over the pixels both cover, the mean ratio, whether the coverage is the
same, build-bsh's leaf / node / closed-object counts at that scale (the tree's own decisions)."""

from __future__ import annotations

import argparse
import json
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from bench.benchlib import ROOT, write_rows
from pipeline import io


def run_at(root: Path, c: io.Cloud, s: float, d: Path, size: str, bsh_opts: list[str], relight_opts: list[str]) -> tuple:
    """(relit.exr, build-bsh's counts) of the room × s in folder d."""
    d.mkdir(parents=True, exist_ok=True)
    io.write_cloud(d / "cloud.ply", io.Cloud((np.asarray(c.points, np.float64) * s).astype(np.float32), c.normals, c.colors))
    sc = json.loads((root / "scene.json").read_text())
    for k in ("object", "object2"):
        if k in sc:
            T = np.array(sc[k]["to_world"], np.float64)
            T[:3, :] *= s
            sc[k]["to_world"] = T.tolist()
    for v in sc["views"].values():
        v["eye"] = (np.array(v["eye"]) * s).tolist()
        v["target"] = (np.array(v["target"]) * s).tolist()
    shutil.copy(root / "object.glb", d / "object.glb")
    (d / "scene.json").write_text(json.dumps(sc))
    cli = [sys.executable, str(ROOT / "cli.py")]
    subprocess.run([*cli, "build-bsh", str(d / "cloud.ply"), "--out", str(d / "bsh.npz"), "-q", *bsh_opts], check=True)
    subprocess.run([*cli, "relight", "--bsh", str(d / "bsh.npz"), "--scene", str(d / "scene.json"), "--view", "view1",
                    "--size", size, "--out", str(d / "out"), "-q", *relight_opts], check=True)
    counts = json.loads((d / "bsh.json").read_text())["counts"]
    return io.read_image(d / "out" / "relit.exr"), counts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--size", default="128x128")
    ap.add_argument("--scales", default="1e-3,0.0009765625,1.1e-3,1.25e-3,1e3,1e4")
    ap.add_argument("--bsh-opts", default="", help="build-bsh options, one string")
    ap.add_argument("--relight-opts", default="", help="relight options, one string")
    ap.add_argument("--work", type=Path, default=ROOT / "bench" / "_work" / "scale")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "relight" / "scale.csv")
    a = ap.parse_args()
    c = io.read_cloud(a.scene / "cloud_gt.ply")
    bo, ro = shlex.split(a.bsh_opts), shlex.split(a.relight_opts)
    base, bc = run_at(a.scene, c, 1.0, a.work / "s1", a.size, bo, ro)
    rows = []
    for s in (float(x) for x in a.scales.split(",")):
        img, cnt = run_at(a.scene, c, s, a.work / f"s{s:g}", a.size, bo, ro)
        m = (img[..., 3] > 0) & (base[..., 3] > 0)
        x, y = img[..., :3][m], base[..., :3][m]
        rows.append({"scene": a.scene.name, "bsh_opts": a.bsh_opts, "s": s,
                     "rel_rms": float(f"{np.sqrt(((x - y) ** 2).mean() / (y ** 2).mean()):.3g}"),
                     "mean_ratio": round(float(x.sum() / y.sum()), 5),
                     "same_coverage": bool(np.array_equal(img[..., 3], base[..., 3])),
                     "n_leaves": cnt["n_leaves"], "n_leaves_s1": bc["n_leaves"], "n_nodes": cnt["n_nodes"],
                     "n_closed": cnt["n_closed"], "n_closed_s1": bc["n_closed"]})
        print(rows[-1], flush=True)
    write_rows(a.out, rows)


if __name__ == "__main__":
    main()
