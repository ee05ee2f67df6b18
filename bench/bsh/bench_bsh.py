"""Benchmark of build-bsh (Table 1's BSH column): build time split by step and peak memory against
N, with the ratio to a bare ``numpy.argsort`` of the same N Morton codes (the floor of any LBVH
build), measured in the same process right before the build.

Cloud: points sampled uniformly by area on a closed 8 × 4 × 6 m room and three spheres inside it
(normals facing the inside of the room / out of the spheres), colour = smooth function of the
position per surface + 1 % noise (so pruning finds some clusters, as on a real scan).

Each N runs in a fresh subprocess so that its peak resident memory (``ru_maxrss``) is its own;
"peak_mb" = that peak minus the resident size just before the build (cloud and compiled code
loaded). Wall-clock and process CPU times (all threads) are both recorded, with the 1-minute
load average: on a shared machine the wall times swell with the load, the CPU times much less.
Writes bench/bsh/bsh.csv and bench/bsh.png. Usage: ``python -m bench.bsh.bench_bsh [--max-n N]``.

``--scale`` (issue 23 item 5, the paper's 3 M points): the same cloud at ``--scale-n`` points (3 M) written
as a PLY under a temporary folder and built by the command line, ``pcrelight build-bsh``, as a user runs it:
once with an empty numba cache (cold: the kernels compile) and ``--warm`` times (2) with it filled (warm), each
a fresh process; per-step times from its report, whole-process wall and CPU time (user + sys), peak RSS, and the
ratio of the build's core (morton … pack, without read and write) and of the whole process to a bare
``numpy.argsort`` of the same 3 M Morton codes timed in this process right before. ``--root DIR`` runs
another checkout's pipeline (the "before" rows). ``--before DIR --repeat K``: that checkout and ``--root``
alternated in one run (each cold once, then K warm runs of each, before first), and their last bsh.npz compared
array by array. CPU times and peak RSS are each build process's own (``os.wait4``; rows before 2026-12-06 05:30
UTC took ``ru_maxrss`` of RUSAGE_CHILDREN: the largest of the runs so far). Appends to bench/bsh_scale.csv.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent   # this topic's folder: the outputs
ROOT = HERE.parents[1]

STEPS = ["morton", "sort", "leaves", "spacing", "karras", "cones", "bottom_up", "prune_linearise", "pack"]
NS = [10_000, 30_000, 100_000, 300_000, 1_000_000, 3_000_000]


def surface_cloud(n: int, seed: int = 0, noise: float = 0.01) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Uniform-by-area samples of a room (box) and three spheres: points, unit normals, colours (a smooth pattern
    plus per-point Gaussian noise of σ ``noise``: 0.01 prunes to a few ten thousand nodes at 3 M points, 0.1 keeps
    most of the 2N − 1 nodes, as a scanned texture does)."""
    rng = np.random.default_rng(seed)
    size = np.array([8.0, 4.0, 6.0])
    spheres = [((2.0, 1.0, 2.0), 0.8), ((5.5, 1.5, 3.5), 1.2), ((4.0, 3.0, 1.5), 0.5)]
    box_areas = [np.prod(np.delete(size, ax)) for ax in range(3) for _ in (0, 1)]
    areas = np.array(box_areas + [4 * np.pi * r * r for _, r in spheres])
    which = rng.choice(len(areas), size=n, p=areas / areas.sum())
    p = np.empty((n, 3))
    nn = np.empty((n, 3))
    for k in range(len(areas)):
        m = which == k
        cnt = int(m.sum())
        if k < 6:
            ax, side = divmod(k, 2)
            q = rng.random((cnt, 3)) * size
            q[:, ax] = side * size[ax]
            d = np.zeros((cnt, 3))
            d[:, ax] = 1.0 if side == 0 else -1.0
        else:
            c, r = spheres[k - 6]
            d = rng.normal(size=(cnt, 3))
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            q = np.asarray(c) + r * d
        p[m] = q
        nn[m] = d
    base = 0.3 + 0.05 * which[:, None] * np.array([1.0, 0.6, 0.3]) % 1.0
    col = base * (1.0 + 0.3 * np.sin(p[:, [0]] * 0.7) * np.cos(p[:, [2]] * 0.5)) + rng.normal(0, noise, (n, 3))
    return p.astype(np.float32), nn.astype(np.float32), np.abs(col).astype(np.float32)


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20


def one(n: int) -> dict:
    from pipeline.bsh import tree as core
    from pipeline.bsh.builder import build_bsh, cube_box
    from pipeline.runtime import Timings

    p, nn, c = surface_cloud(n)
    build_bsh(*surface_cloud(64, seed=1))  # load / compile the kernels
    lo, side = cube_box(p)
    codes = core.morton_codes(p, lo, float(2 ** 21) / side, 21)
    reps = 3 if n <= 300_000 else 1  # builds: best of 3 where a run is short
    t_argsort = cpu_argsort = t_argsort_stable = np.inf
    for _ in range(3):  # the sort floor: always best of 3
        t0, c0 = time.perf_counter(), time.process_time()
        np.argsort(codes)
        t_argsort = min(t_argsort, time.perf_counter() - t0)
        cpu_argsort = min(cpu_argsort, time.process_time() - c0)
        t0 = time.perf_counter()
        np.argsort(codes, kind="stable")
        t_argsort_stable = min(t_argsort_stable, time.perf_counter() - t0)
    del codes
    base = rss_mb()
    total = cpu = np.inf
    r = None
    for _ in range(reps):
        r = None  # free the previous result: the peak is one build's
        tt = Timings()
        t0, c0 = time.perf_counter(), time.process_time()
        r = build_bsh(p, nn, c, timings=tt)
        wall = time.perf_counter() - t0
        cpu = min(cpu, time.process_time() - c0)
        if wall < total:
            total, t = wall, tt
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    st = r["stats"]
    row = {"n": n, "total_s": total, "argsort_s": t_argsort, "argsort_stable_s": t_argsort_stable,
           "ratio_to_argsort": total / t_argsort, "cpu_s": cpu, "argsort_cpu_s": cpu_argsort,
           "cpu_ratio_to_argsort": cpu / max(cpu_argsort, 1e-9), "peak_mb": peak - base,
           "numba_threads": __import__("numba").get_num_threads(),
           "n_voxels": st["n_voxels"], "n_nodes_full": st["n_nodes_full"], "n_nodes": st["n_nodes"],
           "n_clusters": st["n_clusters"], "depth": st["depth"], "load1": os.getloadavg()[0]}
    row.update({f"{k}_s": v for k, v in t.as_dict().items()})
    return row


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pipeline.io import save_figure

    n = np.array([r["n"] for r in rows], dtype=float)
    fig, axs = plt.subplots(1, 3, figsize=(16, 5))
    bottom = np.zeros(len(rows))
    for k in STEPS:
        v = np.array([r.get(f"{k}_s", 0.0) for r in rows])
        axs[0].bar(np.arange(len(rows)), v, bottom=bottom, label=k)
        bottom += v
    axs[0].plot(np.arange(len(rows)), [r["argsort_s"] for r in rows], "k*-", label="np.argsort (bare)")
    axs[0].set_xticks(np.arange(len(rows)), [f"{int(x):.0e}" for x in n])
    axs[0].set_xlabel("N points")
    axs[0].set_ylabel("seconds")
    axs[0].set_title("build time by step")
    axs[0].legend(fontsize=8)
    axs[1].loglog(n, [r["total_s"] for r in rows], "o-", label="build-bsh total")
    axs[1].loglog(n, [r["argsort_s"] for r in rows], "s--", label="np.argsort of the codes")
    axs[1].loglog(n, [r["cpu_s"] for r in rows], "o:", label="build-bsh CPU time (all threads)")
    axs[1].loglog(n, n * rows[-1]["total_s"] / n[-1], ":", color="grey", label="linear")
    ax2 = axs[1].twinx()
    ax2.loglog(n, [r["ratio_to_argsort"] for r in rows], "r^-", label="ratio to argsort (wall)")
    ax2.loglog(n, [r["cpu_ratio_to_argsort"] for r in rows], "rv:", label="ratio to argsort (CPU)")
    ax2.axhline(3.0, color="r", lw=0.5, ls="--")
    ax2.set_ylabel("build / argsort (goal ≤ 3, dashed)", color="r")
    ax2.legend(fontsize=8, loc="lower right")
    axs[1].set_xlabel("N points")
    axs[1].set_ylabel("seconds")
    axs[1].set_title(f"scaling (1-min load {min(r['load1'] for r in rows):.1f}–{max(r['load1'] for r in rows):.1f} on {os.cpu_count()} cores)")
    axs[1].legend(fontsize=8, loc="upper left")
    axs[2].loglog(n, [r["peak_mb"] for r in rows], "o-")
    axs[2].loglog(n, n * 400 / 2 ** 20, ":", color="grey", label="400 B / point")
    axs[2].set_xlabel("N points")
    axs[2].set_ylabel("peak extra RSS [MiB]")
    axs[2].set_title("peak memory of the build")
    axs[2].legend(fontsize=8)
    fig.tight_layout()
    save_figure(path, fig)


SCALE_STEPS = ["read", *STEPS, "write"]


def scale_rows(n: int, root: Path, label: str, runs: tuple[str, ...] = ("cold", "warm", "warm"),
               noise: float = 0.01, before: tuple[Path, str] | None = None, repeat: int = 0) -> list[dict]:
    """build-bsh from the command line on an n-point cloud: see the module docstring (``--scale``). With
    ``before`` (root, label) and ``repeat``: a cold run of each checkout, then ``repeat`` warm runs of each,
    alternated (before, after, before, …) in the same minutes, and the last files of the two compared array
    by array (``io.read_npz``: every member, the derived ones included)."""
    import shutil
    import tempfile

    from pipeline.bsh import tree as core
    from pipeline.bsh.builder import cube_box
    from pipeline.io import Cloud, read_json, write_cloud

    tmp = Path(tempfile.mkdtemp(prefix="bsh_scale_"))
    try:
        p, nn, c = surface_cloud(n, noise=noise)
        ply = tmp / "cloud.ply"
        write_cloud(ply, Cloud(p, nn, c))
        lo, side = cube_box(p)
        codes = core.morton_codes(p, lo, float(2 ** 21) / side, 21)
        t_argsort = np.inf
        for _ in range(3):
            t0 = time.perf_counter()
            np.argsort(codes)
            t_argsort = min(t_argsort, time.perf_counter() - t0)
        del codes, p, nn, c
        code = ("import sys; sys.path.insert(0, sys.argv.pop(1)); sys.argv[0] = 'pcrelight'; "
                "from cli import main; sys.exit(main())")
        rows = []
        plan = [(root, label, kind) for kind in runs]
        if before is not None:
            plan = [(before[0], before[1], "cold"), (root, label, "cold")] + \
                [(r, lb, "warm") for _ in range(repeat) for r, lb in (before, (root, label))]
        last: dict[str, Path] = {}
        for k, (run_root, run_label, kind) in enumerate(plan):
            out = tmp / f"bsh{k}.npz"
            cache = tmp / f"numba_cache_{run_label.replace('/', '_')}"
            env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
            err = tmp / "stderr.txt"
            with open(err, "w") as ef:          # os.wait4: this process's own CPU times and peak RSS
                t0 = time.perf_counter()
                proc = subprocess.Popen([sys.executable, "-c", code, str(run_root), "build-bsh", str(ply), "--out",
                                         str(out), "-q"], stdout=subprocess.DEVNULL, stderr=ef, env=env, cwd=tmp)
                _, status, ru = os.wait4(proc.pid, 0)
                wall = time.perf_counter() - t0
                proc.returncode = os.waitstatus_to_exitcode(status)
            if proc.returncode != 0:
                sys.stderr.write(err.read_text())
                raise SystemExit(f"bench_bsh --scale: build-bsh failed ({run_label}, {kind})")
            rep = read_json(out.with_suffix(".json"))
            tm = rep["timings_s"]
            core_s = sum(tm.get(s, 0.0) for s in STEPS)
            row = {"label": run_label, "n": n, "cache": kind, "wall_s": wall,
                   "cpu_s": ru.ru_utime + ru.ru_stime, "sys_s": ru.ru_stime, "core_s": core_s,
                   "startup_s": wall - sum(tm.values()), "argsort_s": t_argsort,
                   "core_ratio_to_argsort": core_s / t_argsort, "wall_ratio_to_argsort": wall / t_argsort,
                   "peak_rss_mb": ru.ru_maxrss / 1024.0, "npz_mb": out.stat().st_size / 2 ** 20,
                   "n_nodes": rep["counts"]["n_nodes"], "load1": os.getloadavg()[0], "cores": os.cpu_count()}
            row.update({f"{s}_s": tm.get(s, 0.0) for s in SCALE_STEPS})
            rows.append(row)
            if run_label in last:               # keep the latest file of each checkout only
                last[run_label].unlink(missing_ok=True)
            last[run_label] = out
            print(f"{run_label} {kind}: {wall:.2f} s wall, {row['cpu_s']:.2f} s CPU, core {core_s:.2f} s "
                  f"(×{row['core_ratio_to_argsort']:.1f} argsort {t_argsort:.3f} s), startup {row['startup_s']:.2f} s, "
                  + ", ".join(f"{s} {tm.get(s, 0.0):.2f}" for s in SCALE_STEPS) + f", load {row['load1']:.1f}", flush=True)
        if before is not None:
            from pipeline.io import read_npz

            a, b = (read_npz(last[lb], "pcrelight.bsh/1") for lb in (before[1], label))
            diff = sorted(k for k in set(a) | set(b) if k not in a or k not in b or a[k].dtype != b[k].dtype
                          or a[k].shape != b[k].shape or a[k].tobytes() != b[k].tobytes())
            print(f"bsh.npz of '{before[1]}' and '{label}': {len(a)} / {len(b)} arrays, "
                  + (f"DIFFERENT: {', '.join(diff)}" if diff else "every array equal (bytes)"), flush=True)
        return rows
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--max-n", type=int, default=NS[-1])
    ap.add_argument("--out", default=str(HERE))
    ap.add_argument("--plot-only", action="store_true", help="redraw bsh.png from bsh.csv")
    ap.add_argument("--scale", action="store_true", help="3 M points from the command line, cold and warm "
                    "numba cache: appends to bsh_scale.csv")
    ap.add_argument("--scale-n", type=int, default=NS[-1])
    ap.add_argument("--root", default=str(ROOT), help="--scale: the checkout whose pipeline runs")
    ap.add_argument("--label", default="after", help="--scale: the rows' label")
    ap.add_argument("--warm", type=int, default=2, help="--scale: runs with the numba cache filled (after one cold run)")
    ap.add_argument("--scale-noise", type=float, default=0.01, help="--scale: the colours' per-point noise σ "
                    "(0.01: few nodes survive the pruning; 0.1: most do, like a scanned texture)")
    ap.add_argument("--before", help="--scale: another checkout run alternately with --root (cold once each, "
                    "then --repeat warm runs each, before first); the two files are compared array by array")
    ap.add_argument("--before-label", default="before", help="--scale --before: its rows' label")
    ap.add_argument("--repeat", type=int, default=2, help="--scale --before: warm runs of each checkout")
    a = ap.parse_args()
    if a.scale:
        before = None if a.before is None else (Path(a.before).resolve(), a.before_label)
        rows = scale_rows(a.scale_n, Path(a.root).resolve(), a.label, ("cold",) + ("warm",) * a.warm, a.scale_noise,
                          before, a.repeat)
        path = Path(a.out) / "bsh_scale.csv"
        path.parent.mkdir(parents=True, exist_ok=True)
        new_file = not path.exists()
        with open(path, "a", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0].keys()))
            if new_file:
                w.writeheader()
            for r in rows:
                w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
        print(f"appended {len(rows)} rows to {path}")
        return
    if a.plot_only:
        with open(Path(a.out) / "bsh.csv") as f:
            rows = [{k: (float(v) if k != "n" else int(v)) for k, v in r.items()} for r in csv.DictReader(f)]
        plot(rows, Path(a.out) / "bsh.png")
        return
    if a.one:
        print(json.dumps(one(a.one)))
        return
    rows = []
    for n in [x for x in NS if x <= a.max_n]:
        res = subprocess.run([sys.executable, "-m", __spec__.name, "--one", str(n)], capture_output=True, text=True,
                             cwd=ROOT)
        if res.returncode != 0:
            sys.stderr.write(res.stderr)
            raise SystemExit(f"bench_bsh: N={n} failed")
        row = json.loads(res.stdout.strip().splitlines()[-1])
        rows.append(row)
        print(f"N={n:>8}: {row['total_s']:.3f} s wall, {row['cpu_s']:.3f} s CPU (argsort {row['argsort_s']:.3f} s, "
              f"×{row['ratio_to_argsort']:.1f} wall, ×{row['cpu_ratio_to_argsort']:.1f} CPU), "
              f"peak +{row['peak_mb']:.0f} MiB, {row['n_nodes_full']} → {row['n_nodes']} nodes, "
              f"{row['n_clusters']} clusters, load {row['load1']:.1f}", flush=True)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    keys = list(rows[0].keys())
    with open(out / "bsh.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    plot(rows, out / "bsh.png")
    print(f"wrote {out / 'bsh.csv'} and {out / 'bsh.png'}")


if __name__ == "__main__":
    main()
