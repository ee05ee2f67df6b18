"""relight's fixed costs before and after (issue 23 item 3): CPU seconds per step of whole relight processes.

    .venv/bin/python -m bench.speed.bench_fixed_costs --before <tree before> --lamp-dir /tmp/s26/L512 --lamp-bsh bshL \
        --sample-bsh bshS.npz [--cases L2,L1,S2,S2g] [--out bench/speed/relight_fixed_costs.csv]

Cases (relight's defaults, the material of ``bench_relight_truth.material_kw``): ``L2``/``L1`` the lamp room's view2 /
view1 at 512² (Lambert 0.8), ``S2``/``S2g`` the shipped scene's view2 at 128² (Lambert 0.8 / GGX 0.25). Each case runs,
one after the other, one process of each configuration:

- ``before``: the ``--before`` tree (``OMP_WAIT_POLICY`` and ``PCRELIGHT_CACHE_DIR`` unset);
- ``cold``: this tree with an empty cache folder (the object's first relight: numba's kernels load for its surfel BSH,
  its bounce passes and the room shadow walk, and both are written to the cache);
- ``warm``: this tree with the cache that a relight of the case's other view filled (same object, room and
  material, not timed): the object's BSH and its lit surfels and room shadow are read.

Per configuration a :mod:`bench_relight_steps` worker (stats.json ``time_s`` steps in process CPU seconds, ``startup`` =
the process's CPU less relight's, ``process`` = the whole process) and, with ``--cli``, the ``cli.py relight -q``
process timed from outside (``cli`` row: wall and CPU, as ``bench_vs_pathtracer.py`` times relight). One row per
configuration and step; the printed table sums the bounce passes.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]

from bench.speed import bench_relight_steps as steps
from bench.benchlib import material_args

CASES = {"L2": ("lamp", "view2", "512x512", "lambert"), "L1": ("lamp", "view1", "512x512", "lambert"),
         "S2": ("sample", "view2", "128x128", "lambert"), "S2g": ("sample", "view2", "128x128", "ggx0.25")}
OTHER_VIEW = {"view1": "view2", "view2": "view1"}


def env_for(config: str, cache: Path | None) -> dict:
    """The worker's environment: ``before`` without this tree's settings, else the cache folder ``cache``."""
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "PCRELIGHT_CACHE_DIR")}
    if config != "before":
        env["PCRELIGHT_CACHE_DIR"] = str(cache)
    return env


def cli_row(root: str, bsh: str, scene: str, view: str, size: str, mat: str, out: Path, env: dict) -> dict:
    """``cli.py relight -q`` of ``root`` timed from outside: wall and CPU seconds (the child's rusage)."""
    cmd = [sys.executable, str(Path(root) / "cli.py"), "relight", "--bsh", bsh, "--scene", str(Path(scene) / "scene.json"),
           "--view", view, "--size", size, "--out", str(out), "-q", *material_args(mat)]
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=root, env=env)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if res.returncode:
        raise SystemExit(f"relight failed ({res.returncode}):\n{res.stderr[-3000:]}")
    return {"step": "cli", "wall_s": round(wall, 3), "cpu_s": round(r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime, 3)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--before", required=True, help="the tree before (a checkout or `git archive` of it)")
    ap.add_argument("--lamp-dir", required=True, help="the lamp room's scene folder (views at 512²)")
    ap.add_argument("--lamp-bsh", required=True)
    ap.add_argument("--sample-dir", default=str(ROOT / "data_samples"))
    ap.add_argument("--sample-bsh", required=True)
    ap.add_argument("--cases", default="L2,L1,S2,S2g")
    ap.add_argument("--configs", default="before,cold,warm")
    ap.add_argument("--cli", action="store_true", help="also time cli.py relight as a whole process")
    ap.add_argument("--work", default="/tmp/relight_fixed_costs")
    ap.add_argument("--out", type=Path, default=HERE / "relight_fixed_costs.csv")
    a = ap.parse_args()
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    for case in a.cases.split(","):
        where, view, size, mat = CASES[case]
        scene, bsh = (a.lamp_dir, a.lamp_bsh) if where == "lamp" else (a.sample_dir, a.sample_bsh)
        scene, bsh = str(Path(scene).resolve()), str(Path(bsh).resolve())
        warm = Path(tempfile.mkdtemp(prefix=f"warm_{case}_", dir=work))
        for config in a.configs.split(","):
            root = str(Path(a.before).resolve()) if config == "before" else str(ROOT)
            cache = warm if config == "warm" else Path(tempfile.mkdtemp(prefix=f"cold_{case}_", dir=work))
            env = env_for(config, cache)
            ns = argparse.Namespace(root=root, bsh=bsh, scene=scene, view=view, size=size, lambert=False,
                                    material=mat, work=str(work / f"{case}_{config}"))
            if config == "warm":   # the other view fills the cache (not timed)
                prime = argparse.Namespace(**{**vars(ns), "view": OTHER_VIEW[view], "work": str(work / f"{case}_prime")})
                steps.run_worker(prime, 0, env)
            got = steps.run_worker(ns, 0, env)
            if a.cli:
                cache2 = warm if config == "warm" else Path(tempfile.mkdtemp(prefix=f"cold_{case}_cli_", dir=work))
                got.append({**got[0], **cli_row(root, bsh, scene, view, size, mat, work / f"{case}_{config}_cli",
                                                env_for(config, cache2))})
            for r in got:
                rows.append({"case": case, "config": config, "material": mat, **r})
            print(f"{case} {config}: " + ", ".join(f"{r['step']} {r['cpu_s']}" for r in got), flush=True)
    from bench.benchlib import write_rows   # (here: the workers are other processes)

    write_rows(a.out, rows)
    table(rows)


def table(rows: list[dict]) -> None:
    """Markdown table: step → CPU s per case and configuration (the bounce passes summed)."""
    def key(step: str) -> str:
        return "bounces" if step.startswith("bounce") else step

    cols = list(dict.fromkeys((r["case"], r["config"]) for r in rows))
    steps_ = list(dict.fromkeys(key(r["step"]) for r in rows))
    val: dict = {}
    for r in rows:
        if r["cpu_s"] not in ("", None):
            k = (key(r["step"]), r["case"], r["config"])
            val[k] = val.get(k, 0.0) + float(r["cpu_s"])
    print("| step | " + " | ".join(f"{c} {g}" for c, g in cols) + " |")
    print("|---|" + "---|" * len(cols))
    for s in steps_:
        print(f"| {s} | " + " | ".join(f"{val[(s, c, g)]:.2f}" if (s, c, g) in val else "" for c, g in cols) + " |")


if __name__ == "__main__":
    os.environ.setdefault("PYTHONDONTWRITEBYTECODE", "1")
    main()
