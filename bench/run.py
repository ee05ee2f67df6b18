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


TOPICS = {   # folder: what it holds (bench/README.md's order)
    "relight": "relight's accuracy against the path-traced truth: bounces, cuts, self-shadow and self-reflection, "
               "room shadow, near field (bench_relight_cases.py grids in relight/cases/)",
    "gatherers": "the gatherers side by side: Table 3 (classic/mipmapped/hybrid), envmap, importance, all five",
    "speed": "relight's time at 512²: the walk, steps, fixed costs, upsample, adaptive shading",
    "composite": "the object in the photo: the composite against the path-traced photo with the object, the matte, times",
    "splats": "3D Gaussian splats as the room's picture: a splat room against the path-traced view, the import's colours, the renderer's speed",
    "peers": "relight against path-traced peers: Mitsuba 3, and Mitsuba on the scan's Poisson surface",
    "photos": "photos: end to end from the registered photo, photo sets, panoramas, what each photo buys",
    "expansion": "the expansion stages (time, PatchMatch trade, error diagnosis, α limits, 3 M points, splats/Poisson)",
    "bsh": "build-bsh: time and memory from 10 k to 3 M points",
    "batch": "pcrelight batch on Ray: throughput, faults, resume",
    "plan": "the planner's decisions and the trade (the presets' sweep) on the lamp room",
}


def made(path: str) -> str:
    """The date and commit the file's content was last written at (renames followed, so not the move's)."""
    out = subprocess.run(["git", "log", "-1", "--follow", "--diff-filter=AM", "--format=%cs %h", "--", path], cwd=ROOT,
                         capture_output=True, text=True).stdout.strip()
    return out or "not committed"


def command(run: dict) -> str:
    if "command" in run:
        return "<br>".join(f"`{c}`" for c in ([run["command"]] if isinstance(run["command"], str) else run["command"]))
    st = steps(run, True)
    mod = "python -m " + module(run["script"])
    return "<br>".join(f"`{mod} {s}`".replace(" `", "`") for s in st)


def index(manifest: dict) -> str:
    """bench/README.md: the layout, how to run, and per topic each result → command → date/commit → headline."""
    runs = manifest["run"]
    quick = [r["name"] for r in runs if r.get("quick")]
    head = f"""# Benchmarks

An index: each result in bench/ with the command that makes it, the date and commit it was made at (`git log -1
--follow --diff-filter=AM`: the last commit that wrote it, renames followed) and its headline number. The
measurement notes behind them are in [docs/bench/](../docs/bench/) (a page per topic); every command is in
[manifest.toml](manifest.toml), which `tests/test_bench_manifest.py` holds to this folder. This file is generated:
`python bench/run.py --index > bench/README.md`.

## Running

- `make bench`: the quick subset ({len(quick)} runs: {", ".join(quick)}), each with small arguments, into
  `bench/_work/quick/` (git-ignored); about 5 minutes on 2 shared cores from a fresh clone. A smoke test of every
  topic's code and a rough number, not the committed results.
- `make bench FULL=1`: every run with its full arguments, rewriting the committed results in the topic folders.
  Hours: it makes the rooms the runs name (`[scenes]` in the manifest: make-scene bowl, lamps, …), their BSHs and
  the "before" checkouts (`git archive`) once, under `bench/_work/`.
- One run: `python bench/run.py --only NAME [--full]`; one script by hand: `python -m bench.<topic>.<script> …`
  from the repository root (no script edits `sys.path`; `--root`/`--before` checkouts excepted).
- In the commands below `{{scene:X}}`, `{{bsh:X}}`, `{{checkout:REV}}` and `{{work}}` are bench/run.py's placeholders: a
  room (`small` = data_samples/, the others made by make-scene as the manifest says), build-bsh of its exact cloud,
  a `git archive` of that commit, the run's scratch folder.

## Layout

Folders by what is measured, in the terms of the pipeline's stages and of the questions the notes answer: a result
sits beside the script that makes it, and a topic's notes are one page. Shared code is `bench/benchlib.py` (CSV
writing, the reference materials, the exact cloud's BSH, block ratios against the truth, the synthetic rooms; the
few test fixtures a bench needs are copied there: benches never import tests, tests never import benches). The 3 M
point runs ("scale") sit with their stage (bsh/, expansion/) rather than apart. Superseded results are deleted (git
keeps them; the notes say what replaced what).

| folder | what | notes |
|---|---|---|
"""
    rows = [f"| [{k}/]({k}/) | {v} | [docs/bench/{k}.md](../docs/bench/{k}.md) |" for k, v in TOPICS.items()]
    body = []
    for k in TOPICS:
        body.append(f"\n## {k}/\n\n| result | command | made | headline |\n|---|---|---|---|")
        for r in runs:
            if r["topic"] != k or not (r["outputs"] or r.get("quick") or steps(r, True) or "command" in r):
                continue
            outs = r["outputs"]
            res = ", ".join(f"[{Path(o).name}]({Path(o).relative_to('bench').as_posix()})" for o in outs) or f"*({r['name']}: prints)*"
            dates = sorted({made(o) for o in outs}, reverse=True)
            when = "<br>".join(dates) if outs else "—"
            hl = r["headline"] + (f" *(quick: `{r['name']}`)*" if r.get("quick") else "")
            body.append(f"| {res} | {command(r)} | {when} | {hl} |")
    return head + "\n".join(rows) + "\n" + "\n".join(body) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--full", action="store_true", help="every run with its full arguments (hours; makes scenes)")
    ap.add_argument("--only", default="", help="comma-separated run names (any of them, quick or not)")
    ap.add_argument("--list", action="store_true", help="the runs and their one-line descriptions, then stop")
    ap.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")
    ap.add_argument("--index", action="store_true", help="print bench/README.md (the index of results) and stop")
    a = ap.parse_args(argv)
    manifest = load_manifest()
    if a.index:
        print(index(manifest), end="")
        return 0
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
