"""adaptive.upsample on a real 512² G-buffer: the pixels-to-fill-only version against the every-pixel one it
replaced (issue 23, item 2: shade fewer pixels, cheaper).

    .venv/bin/python -m bench.speed.bench_upsample [SCENE_DIR] [--view view1] [--size 512x512] [--reps 3]
        [--out bench/speed/upsample_512.csv]

The G-buffer of the scene's object from ``--view`` (relight's camera and placement); radiance = a smooth function
of position and normal on the covered pixels. Cases: k random covered pixels left unshaded (k = 1, 50, 2000: what
relight's adaptive shading leaves to ``upsample`` when a block's corners cannot fill a pixel — 0 on the shipped
views at 512²), and the 4×4 grid alone shaded (the worst case: 15/16 of the covered pixels to fill). Per case the
process CPU seconds of each version (the fastest of ``--reps``), their ratio, and whether the outputs are the same
bytes. The every-pixel version is the reference kept in ``tests/test_adaptive.py``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]

from bench.benchlib import write_rows
from pipeline.relight.adaptive import upsample_reference

from pipeline import gl, io  # noqa: E402
from pipeline.relight.adaptive import upsample  # noqa: E402
from pipeline.relight.gbuffer import place_parts, render_gbuffer  # noqa: E402
from pipeline.relight.relight import RelightConfig
from pipeline.relight.inputs import camera_for, objects_for  # noqa: E402


def cpu_best(fn, reps: int) -> tuple[float, np.ndarray]:
    """(fastest process CPU seconds of ``reps`` calls, the last result)."""
    best, out = np.inf, None
    for _ in range(reps):
        t0 = time.process_time()
        out = fn()
        best = min(best, time.process_time() - t0)
    return best, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path, nargs="?", default=ROOT / "data_samples")
    ap.add_argument("--view", default="view1")
    ap.add_argument("--size", default="512x512")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--out", type=Path, default=HERE / "upsample_512.csv")
    a = ap.parse_args()
    scene_path = a.scene / "scene.json"
    scene = io.read_json(scene_path)
    cfg = RelightConfig(size=a.size)
    cam = camera_for(cfg, scene, scene_path, a.view)
    parts = [q for p, w in objects_for(None, scene, scene_path) for q in place_parts(io.read_object(p), w)]
    ctx = gl.create_context()
    gl.bind_dummy_framebuffer(ctx)
    gb = render_gbuffer(ctx, parts, cam)
    ctx.release()
    mask, nrm, pos = gb["mask"], gb["normal"], gb["position"]
    rad = ((0.5 + 0.4 * np.sin(7 * pos) + 0.3 * nrm) * mask[..., None]).astype(np.float32)
    rng = np.random.default_rng(0)
    cov = np.flatnonzero(mask.reshape(-1))
    grid = np.zeros_like(mask)
    grid[::4, ::4] = True
    cases = {f"{k} random pixels": k for k in (1, 50, 2000)}
    cases["4x4 grid only shaded"] = -1
    rows = []
    for name, k in cases.items():
        if k > 0:
            shaded = mask.copy()
            shaded.reshape(-1)[rng.choice(cov, k, replace=False)] = False
        else:
            shaded = mask & grid
        img = np.where(shaded[..., None], rad, 0).astype(np.float32)
        t_old, old = cpu_best(lambda: upsample_reference(img, shaded, mask, nrm, pos, radius=4), a.reps)
        t_new, new = cpu_best(lambda: upsample(img, shaded, mask, nrm, pos, radius=4), a.reps)
        row = {"view": a.view, "size": a.size, "covered": int(mask.sum()), "case": name,
               "to_fill": int((mask & ~shaded).sum()), "every_pixel_cpu_s": round(t_old, 4),
               "to_fill_only_cpu_s": round(t_new, 4), "speedup": round(t_old / max(t_new, 1e-9), 1),
               "same_bytes": old.tobytes() == new.tobytes()}
        rows.append(row)
        print(row, flush=True)
    write_rows(a.out, rows)


if __name__ == "__main__":
    main()
