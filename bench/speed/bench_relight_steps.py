"""Where a whole relight process's time goes, step by step, in wall and process CPU seconds (issue 23, item 2).

    .venv/bin/python -m bench.speed.bench_relight_steps --bsh bsh.npz [--scene data_samples] [--view view1]
        [--size 512x512] [--reps 3] [--root <other checkout>] [--material lambert|ggx<r>] [--out bench/speed/relight_steps_512.csv]

Each repetition is one worker process (``relight`` with its defaults, the scene's material, the BSH given) of this
checkout (or ``--root``: a second checkout, e.g. the tree before a change). The worker times every relight step
(stats.json ``time_s``: read, G-buffer, surfels, bounces, upload, walk, Eq. 9 gather, read-back, write) in wall
seconds and in process CPU seconds (every thread: llvmpipe's too, so less sensitive to the other jobs on this
shared machine), plus ``startup`` (interpreter, imports and CLI before relight: stats.json
``startup_s.process_before_relight``, wall; its CPU = the process's less relight's) and ``untimed`` (relight's total less its steps: GL context, receivers,
the image's assembly; with a tree older than time_s ``gatherer``/``adaptive`` the gatherer's set-up and adaptive
shading's own work too). The parent times the whole process from outside (``process`` row, wall; its CPU
from the child's rusage). One row per repetition and step; ``load`` = /proc/loadavg when the worker ended.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]

from bench.benchlib import load


def worker(a: argparse.Namespace) -> None:
    """One relight in this process with the pipeline at ``--root``; prints one ``RESULT`` JSON line."""
    sys.path.insert(0, str(Path(a.root).resolve()))
    from pipeline import runtime
    from pipeline.relight.relight import RelightConfig, run_relight

    runtime.setup_logging(-1)
    cpus: list[dict[str, float]] = []    # per Timings instance (the bounce passes time their walks apart)

    @contextlib.contextmanager
    def step(self, name: str):           # Timings.step, with the process CPU seconds of the step beside
        if not hasattr(self, "_cpu"):
            self._cpu = {}
            cpus.append(self._cpu)
        c0, t0 = time.process_time(), time.perf_counter()
        try:
            yield
        finally:
            self._d[name] = self._d.get(name, 0.0) + time.perf_counter() - t0
            self._cpu[name] = self._cpu.get(name, 0.0) + time.process_time() - c0

    runtime.Timings.step = step
    from pipeline.relight import adaptive

    orig_sa, ad_cpu = adaptive.shade_adaptive, [0.0]

    def shade_adaptive(shade, *args, **kw):      # CPU of adaptive shading's own work (time_s "adaptive": its wall)
        inner = [0.0]

        def timed_shade(idx):
            c = time.process_time()
            try:
                return shade(idx)
            finally:
                inner[0] += time.process_time() - c

        c0 = time.process_time()
        try:
            return orig_sa(timed_shade, *args, **kw)
        finally:
            ad_cpu[0] += time.process_time() - c0 - inner[0]

    adaptive.shade_adaptive = shade_adaptive
    mat = a.material or ("lambert" if a.lambert else "")
    if mat:   # after pipeline is imported from --root: bench_relight_truth's own imports then reuse it
        from bench.benchlib import material_kw
    cfg = RelightConfig(size=a.size, **(material_kw(mat) if mat else {}))
    cfg.check()
    c0, t0 = time.process_time(), time.perf_counter()
    st = run_relight(Path(a.bsh), Path(a.outdir), cfg, scene_path=Path(a.scene) / "scene.json", view=a.view)
    wall, c = time.perf_counter() - t0, time.process_time() - c0
    cpu = next(d for d in cpus if "read" in d)                     # relight's own Timings
    if "adaptive" in st["time_s"]:
        cpu["adaptive"] = ad_cpu[0]
    print("RESULT " + json.dumps({"time_s": st["time_s"], "cpu_s": cpu, "relight_s": wall, "relight_cpu_s": c,
                                  "startup_s": st["startup_s"], "nodes_visited": int(st["nodes_visited"]),
                                  "covered": int(st["covered_pixels"]),
                                  "shaded": (st.get("adaptive") or {}).get("shaded", st["covered_pixels"])}), flush=True)


def run_worker(a: argparse.Namespace, rep: int, env: dict | None = None) -> list[dict]:
    """One worker process (``env``: its environment, default this one's); its rows (step, wall_s, cpu_s)."""
    outdir = Path(a.work) / f"rep{rep}"
    cmd = [sys.executable, "-m", __spec__.name, "--worker", "--root", a.root, "--bsh", a.bsh, "--scene", a.scene, "--view", a.view,
           "--size", a.size, "--outdir", str(outdir)] + (["--lambert"] if a.lambert else []) \
        + (["--material", a.material] if a.material else [])
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=a.root, env=env)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    line = next((x for x in res.stdout.splitlines() if x.startswith("RESULT ")), None)
    if res.returncode or line is None:
        raise SystemExit(f"worker failed ({res.returncode}):\n{res.stderr[-3000:]}")
    d = json.loads(line[7:])
    ld = load()
    base = {"rep": rep, "root": a.root, "view": a.view, "size": a.size, "covered": d["covered"], "shaded": d["shaded"],
            "nodes_visited": d["nodes_visited"], "load": ld}
    rows = [{**base, "step": k, "wall_s": round(v, 4), "cpu_s": round(d["cpu_s"].get(k, float("nan")), 4)}
            for k, v in d["time_s"].items()]
    untimed = d["relight_s"] - sum(d["time_s"].values())
    untimed_cpu = d["relight_cpu_s"] - sum(d["cpu_s"].values())
    rows.append({**base, "step": "untimed", "wall_s": round(untimed, 4), "cpu_s": round(untimed_cpu, 4)})
    proc_cpu = r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime
    rows.append({**base, "step": "startup", "wall_s": d["startup_s"].get("process_before_relight"),
                 "cpu_s": round(proc_cpu - d["relight_cpu_s"], 4)})     # the process's CPU before and after relight
    rows.append({**base, "step": "process", "wall_s": round(wall, 3), "cpu_s": round(proc_cpu, 3)})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--outdir", help=argparse.SUPPRESS)
    ap.add_argument("--bsh", required=True)
    ap.add_argument("--scene", default=str(ROOT / "data_samples"))
    ap.add_argument("--view", default="view1")
    ap.add_argument("--size", default="512x512")
    ap.add_argument("--lambert", action="store_true", help="--brdf lambert --albedo 0.8,0.8,0.8 (else the object's own)")
    ap.add_argument("--material", default="", help="lambert or ggx<roughness> (bench_relight_truth.material_kw: GGX "
                    "metallic, albedo 1); empty: --lambert or the object's own")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--root", default=str(ROOT))
    ap.add_argument("--work", default="/tmp/relight_steps")
    ap.add_argument("--out", type=Path, default=HERE / "relight_steps_512.csv")
    a = ap.parse_args()
    a.bsh, a.scene, a.root = (str(Path(x).resolve()) for x in (a.bsh, a.scene, a.root))
    if a.worker:
        worker(a)
        return
    rows: list[dict] = []
    for rep in range(a.reps):
        rs = run_worker(a, rep)
        rows += rs
        print(f"rep {rep}: " + ", ".join(f"{r['step']} {r['wall_s']}/{r['cpu_s']}" for r in rs), flush=True)
    from bench.benchlib import write_rows   # (here, not at the top: a worker imports no pipeline module it times)

    write_rows(a.out, rows)
    steps = list(dict.fromkeys(r["step"] for r in rows))
    proc = sorted(float(r["cpu_s"]) for r in rows if r["step"] == "process")
    print("median over reps (wall s, CPU s, share of the process's CPU):")
    for s in steps:
        ws = sorted(float(r["wall_s"]) for r in rows if r["step"] == s and r["wall_s"] not in ("", None))
        cs = sorted(float(r["cpu_s"]) for r in rows if r["step"] == s and r["cpu_s"] not in ("", None))
        wm = ws[len(ws) // 2] if ws else float("nan")
        cm = cs[len(cs) // 2] if cs else float("nan")
        print(f"  {s:10s} {wm:8.3f} {cm:8.3f} {100 * cm / proc[len(proc) // 2]:5.1f} %")


if __name__ == "__main__":
    os.environ.setdefault("PYTHONDONTWRITEBYTECODE", "1")
    main()
