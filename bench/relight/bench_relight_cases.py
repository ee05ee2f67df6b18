"""relight on a make-scene folder for a list of option sets: error against the full path trace (``truth/full_*``)
and the gather-only trace (``truth/gather_*``) on 4×4 block means, and the wall time, one CSV row per case.

    .venv/bin/python -m bench.relight.bench_relight_cases SCENE_DIR --cases CASES.json [--bsh bsh.npz] --out bench/X.csv

CASES.json: a list of objects, each ``{"view": "view1", "material": "lambert"|"ggx<r>", <RelightConfig fields>…}``
(e.g. ``{"view": "view1", "material": "lambert", "surfels": -1, "adaptive": 0, "stop_multiple": 1.5}``), or a
shorthand ``{"grid": {field: [values…]}, "base": {…}}`` expanded to every combination. The BSH is build-bsh's
defaults on the scene's exact HDR cloud (cloud_gt.ply) unless ``--bsh`` is given: the rows measure relight, not
the expansion. Seconds are the relight call in this process (noisy on a shared machine: compare within a run); cpu_s
is stats.json's (the relight call's CPU seconds), bounce_s the bounce passes' wall seconds, lit_surfels and
self_visibility the bounce receivers' rule (pipeline/relight/surfels.py).
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]

from bench.benchlib import material_kw, measure, truth_bsh, write_rows

from pipeline import io  # noqa: E402
from pipeline.relight.relight import RelightConfig, run_relight  # noqa: E402
from pipeline.runtime import setup_logging  # noqa: E402


def expand(spec: list | dict) -> list[dict]:
    """The cases of CASES.json: a list as it is, or base × the grid's combinations."""
    if isinstance(spec, list):
        return [dict(c) for c in spec]
    keys = list(spec["grid"])
    return [{**spec.get("base", {}), **dict(zip(keys, vals))} for vals in itertools.product(*(spec["grid"][k] for k in keys))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--cases", type=Path, required=True)
    ap.add_argument("--bsh", type=Path, default=None)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()
    setup_logging(-1)
    cases = expand(json.loads(a.cases.read_text()))
    bsh = truth_bsh(a.scene, a.bsh, ROOT / "bench" / "_work" / "cases" / a.scene.name)
    rows = []
    for i, c in enumerate(cases):
        view, mat = c.pop("view"), c.pop("material")
        cfg = RelightConfig(**c, **material_kw(mat))
        cfg.check()
        out = ROOT / "bench" / "_work" / "cases" / f"{a.out.stem}_{i}"
        t0 = time.perf_counter()
        st = run_relight(bsh, out, cfg, scene_path=a.scene / "scene.json", view=view)
        dt = time.perf_counter() - t0
        img = io.read_image(out / "relit.exr")
        row = {"view": view, "material": mat, "options": json.dumps(c, sort_keys=True), "seconds": round(dt, 2),
               "cpu_s": st.get("cpu_s", ""), "room_shadow_s": st.get("time_s", {}).get("room_shadow", ""),
               "node_visits": st.get("nodes_visited", ""),
               "bounces": (st.get("object_surfels") or {}).get("bounces", ""),
               "bounce_tail": json.dumps((st.get("object_surfels") or {}).get("bounce_tail", [])),
               "cpu_s": st.get("cpu_s", ""), "bounce_s": json.dumps((st.get("object_surfels") or {}).get("bounce_s", [])),
               "lit_surfels": (st.get("object_surfels") or {}).get("lit_surfels", ""),
               "self_visibility": (st.get("object_surfels") or {}).get("self_visibility", "")}
        for kind in ("full", "gather"):
            row.update(measure(img, a.scene, view, mat, kind))
        rows.append(row)
        print(json.dumps(row), flush=True)
    write_rows(a.out, rows)


if __name__ == "__main__":
    main()
