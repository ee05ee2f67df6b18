"""Run the benches of bench/manifest.toml: the quick subset (``make bench``) or every run (``make bench FULL=1``).

    .venv/bin/python bench/run.py [--full] [--only NAME[,NAME…]] [--list] [--dry-run]

Each run is ``python -m bench.<topic>.<script> ARGS`` from the repository root (so ``bench.benchlib`` and
``pipeline`` import from this checkout). Quick runs write under bench/_work/quick/<name>/ (git-ignored: the
committed results stay as they are) and must leave their ``quick_outputs`` there; full runs write the committed
``outputs`` in the topic folders. Placeholders in the arguments:

- ``{quick}``, ``{work}``: bench/_work/quick/<name>, bench/_work/<name> (scratch);
- ``{scene:X}``: ``small`` = data_samples/ (shipped); any other a ``[scenes.X]`` of the manifest, made once by
  ``pcrelight make-scene`` into bench/_work/scenes/X (minutes to hours: only full runs name them);
- ``{bsh:X}``: ``pcrelight build-bsh`` (defaults) of scene X's exact cloud (cloud_gt.ply), made once;
- ``{checkout:REV}``: ``git archive REV`` of this repository into bench/_work/checkouts/REV (the "before" trees).

A run stops the whole at its first failure (its exit status is this script's).
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import subprocess
import sys
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MANIFEST = ROOT / "bench" / "manifest.toml"
WORK = ROOT / "bench" / "_work"


def load_manifest(path: Path = MANIFEST) -> dict:
    with open(path, "rb") as f:
        return tomllib.load(f)


def module(script: str) -> str:
    """bench/relight/bench_x.py → bench.relight.bench_x"""
    return script.removesuffix(".py").replace("/", ".")


class Places:
    """The placeholders' values, each made on first use."""

    def __init__(self, manifest: dict, dry: bool):
        self.scenes, self.dry = manifest.get("scenes", {}), dry

    def scene(self, name: str) -> Path:
        if name == "small":
            return ROOT / "data_samples"
        out = WORK / "scenes" / name
        if not (out / "scene.json").exists() and not self.dry:
            spec = self.scenes[name]
            self._run([str(Path(sys.executable).with_name("pcrelight")), "make-scene", *shlex.split(spec["args"]),
                       "--out", str(out)], f"make-scene {name}")
        return out

    def bsh(self, name: str) -> Path:
        out = WORK / "bsh" / f"{name}.npz"
        if not out.exists() and not self.dry:
            scene = self.scene(name)
            out.parent.mkdir(parents=True, exist_ok=True)
            self._run([sys.executable, str(ROOT / "cli.py"), "build-bsh", str(scene / "cloud_gt.ply"), "--out", str(out),
                       "-q"], f"build-bsh {name}")
        return out

    def checkout(self, rev: str) -> Path:
        out = WORK / "checkouts" / rev
        if not out.exists() and not self.dry:
            out.mkdir(parents=True)
            arch = subprocess.run(["git", "archive", rev], cwd=ROOT, capture_output=True, check=True).stdout
            subprocess.run(["tar", "-x", "-C", str(out)], input=arch, check=True)
        return out

    def _run(self, cmd: list[str], what: str) -> None:
        print(f"+ ({what}) {shlex.join(cmd)}", flush=True)
        subprocess.run(cmd, cwd=ROOT, check=True)

    def expand(self, text: str, name: str, quick: bool) -> str:
        def one(m: re.Match) -> str:
            kind, _, arg = m.group(1).partition(":")
            if kind == "quick":
                return str((WORK / "quick" / name).relative_to(ROOT))
            if kind == "work":
                return str((WORK / name).relative_to(ROOT))
            return str(getattr(self, kind)(arg))
        return re.sub(r"\{(quick|work|scene:\w+|bsh:\w+|checkout:[\w.~^-]+)\}", one, text)


def steps(run: dict, full: bool) -> list[str]:
    """The run's argument strings (one per step): quick_args, or full_args (a string or a list; [] = none)."""
    if not full:
        return [run["quick_args"]]
    fa = run.get("full_args", "")
    return [fa] if isinstance(fa, str) else list(fa)


def run_one(run: dict, places: Places, full: bool, dry: bool) -> float:
    """One manifest run, its steps in order; returns its wall seconds. A ``command`` (shell lines; full runs only)
    stands for the script's steps where the run is not one script (a verb, or two scripts in a row)."""
    name = run["name"]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    env.update({k: str(v) for k, v in run.get("env", {}).items()})
    env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])   # python, pcrelight
    if not full:
        (WORK / "quick" / name).mkdir(parents=True, exist_ok=True)
    (WORK / name).mkdir(parents=True, exist_ok=True)
    if full and "command" in run:
        cmds = [c for c in ([run["command"]] if isinstance(run["command"], str) else run["command"])]
        cmds = [places.expand(c, name, False) for c in cmds]
    else:
        cmds = [shlex.join([sys.executable, "-m", module(run["script"]), *shlex.split(places.expand(a, name, not full))])
                for a in steps(run, full)]
    envs = " ".join(f"{k}={v}" for k, v in run.get("env", {}).items())
    t0 = time.perf_counter()
    for cmd in cmds:
        print(f"\n+ [{name}] {envs + ' ' if envs else ''}{cmd}", flush=True)
        if dry:
            continue
        rc = subprocess.run(cmd, shell=True, cwd=ROOT, env=env).returncode
        if rc:
            print(f"bench/run.py: {name} failed (exit {rc}) after {time.perf_counter() - t0:.0f} s", file=sys.stderr)
            sys.exit(rc)
    dt = time.perf_counter() - t0
    want = run.get("outputs", []) if full else [places.expand(o, name, True) for o in run.get("quick_outputs", [])]
    missing = [o for o in want if not (ROOT / o).exists()]
    if missing and not dry:
        print(f"bench/run.py: {name} did not write {', '.join(missing)}", file=sys.stderr)
        sys.exit(1)
    return dt


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--full", action="store_true", help="every run with its full arguments (hours; makes scenes)")
    ap.add_argument("--only", default="", help="comma-separated run names (any of them, quick or not)")
    ap.add_argument("--list", action="store_true", help="the runs and their one-line descriptions, then stop")
    ap.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")
    a = ap.parse_args(argv)
    manifest = load_manifest()
    runs = manifest["run"]
    if a.only:
        names = a.only.split(",")
        unknown = sorted(set(names) - {r["name"] for r in runs})
        if unknown:
            ap.error(f"no run named {', '.join(unknown)} in {MANIFEST.relative_to(ROOT)}")
        runs = [r for r in runs if r["name"] in names]
    elif not a.full:
        runs = [r for r in runs if r.get("quick")]
    if a.list:
        for r in runs:
            print(f"{r['name']:28} {'quick' if r.get('quick') else '     '} {r['topic']:10} {r['description']}")
        return 0
    places = Places(manifest, a.dry_run)
    t0, times = time.perf_counter(), []
    for r in runs:
        if not a.full and "quick_args" not in r:
            sys.exit(f"bench/run.py: {r['name']} has no quick_args (run it with --full)")
        if a.full and not steps(r, True) and "command" not in r:
            continue                                  # a quick-only smoke run
        times.append((r["name"], run_one(r, places, a.full, a.dry_run)))
    print(f"\nbench/run.py: {len(times)} run(s) in {time.perf_counter() - t0:.0f} s "
          f"({'full' if a.full else 'quick'}; load {os.getloadavg()[0]:.2f})")
    for name, dt in times:
        print(f"  {dt:7.1f} s  {name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
