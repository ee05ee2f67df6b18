"""Where a relit image's error against the full path trace is: its 4×4 blocks split by whether the object sees
itself there — the two path traces differ (|gather ÷ full − 1| > ``--self-threshold`` on the block's RGB mean:
``truth/gather_*`` leaves the object out of its own lighting) — with each part's share of the squared block error,
its mean ratio and its own block RMS (‖relit − full‖ / ‖full‖ over its blocks and channels, as
``metrics.compare_to_reference``'s rms_block).

    .venv/bin/python -m bench.relight.bowl_block_split SCENE_DIR VIEW MATERIAL RELIT.exr [RELIT.exr …]

e.g. the images bench_relight_cases.py leaves in bench/_work/cases/<out stem>_<i>/relit.exr.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]

from pipeline import io  # noqa: E402
from pipeline.metrics import block_means  # noqa: E402


def split(img: np.ndarray, full: np.ndarray, gather: np.ndarray, k: int = 4, threshold: float = 0.15) -> dict:
    """{"all"|"self"|"rest": {"blocks", "share", "mean", "rms"}} of ``img`` against ``full`` (RGBA images)."""
    mask = (img[..., 3] > 0.5) & (full[..., 3] > 0.5)
    a, b, g = (block_means(x[..., :3], mask, k) for x in (img, full, gather))
    sees = np.abs(g.mean(1) / np.maximum(b.mean(1), 1e-30) - 1) > threshold
    tot = float(((a - b) ** 2).sum())
    out = {}
    for name, sel in (("all", np.ones(len(a), bool)), ("self", sees), ("rest", ~sees)):
        d2 = float(((a[sel] - b[sel]) ** 2).sum())
        out[name] = {"blocks": int(sel.sum()), "share": d2 / max(tot, 1e-300), "mean": float(a[sel].sum() / b[sel].sum()),
                     "rms": float(np.sqrt(d2 / (b[sel] ** 2).sum()))}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path)
    ap.add_argument("view")
    ap.add_argument("material")
    ap.add_argument("relit", type=Path, nargs="+")
    ap.add_argument("--self-threshold", type=float, default=0.15)
    a = ap.parse_args()
    full = io.read_image(a.scene / "truth" / f"full_{a.view}_{a.material}.exr")
    gather = io.read_image(a.scene / "truth" / f"gather_{a.view}_{a.material}.exr")
    for f in a.relit:
        s = split(io.read_image(f), full, gather, threshold=a.self_threshold)
        print(f"{f}: " + " | ".join(f"{n}: {v['blocks']} blocks, {100 * v['share']:.0f} % of the squared error, mean "
                                    f"{v['mean']:.3f}, block RMS {100 * v['rms']:.1f} %" for n, v in s.items()))


if __name__ == "__main__":
    main()
