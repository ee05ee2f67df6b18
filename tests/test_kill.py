"""Stopping a stage (issue 30): SIGINT/SIGTERM exit 128 + signal with no temp file left and every output
the previous one or a complete new one (build-bsh, stopped before it writes: the previous outputs
byte-identical); kill -9 at random points of every stage (after it read its input: the work and the
writes) leaves every output either byte-identical to the previous one or byte-identical to a complete new
one (reports: equal but for their clock readings).

``PCRELIGHT_KILL_TRIALS`` sets the kill -9 trials a stage (3 in ``make test``, 50 under ``make fuzz``).
``make test`` kills build-bsh that often and every other stage — make-scene, import, expose-match,
render-cubemaps, patchmatch, reproject, poisson, relight, evaluate — ``PCRELIGHT_KILL_CI_TRIALS`` times (1, aimed
at the middle of the stage's work) and sends each stage one SIGTERM mid-stage; every stage's test asserts that a
kill (a signal) landed while the stage ran. ``PCRELIGHT_KILL_STAGES=all`` (``make fuzz``) kills every stage TRIALS
times and sends each ``PCRELIGHT_SIGNAL_TRIALS`` (TRIALS / 5) SIGTERMs/SIGINTs at random points.
``PCRELIGHT_KILL_REPORT=FILE`` writes the figures as JSON. A kill -9 cannot remove the temp file it
interrupts (``.<stem>.<pid>.*.tmp.<ext>``, ignored by git): those are counted, never take an output's
name, and the next write of that output removes them (their process is gone).
"""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from pipeline import io

ROOT = Path(__file__).resolve().parents[1]
TRIALS = int(os.environ.get("PCRELIGHT_KILL_TRIALS", "3"))
ALL_STAGES = os.environ.get("PCRELIGHT_KILL_STAGES", "") == "all"
N_POINTS = 12000   # build-bsh runs ~1 s after reading its input on 2 cores: room to land a signal in it

# make-scene at a size where one run is a few seconds (test_scene's MINI): every file of the ground truth
MINI_SCENE = ["--points", "3000", "--cloud-spp", "4", "--cloud-max-spp", "8", "--photo-size", "24,16", "--photo-spp", "2",
              "--ref-size", "12,12", "--ref-spp", "4", "--ref-max-spp", "8", "--ref-bg-spp", "2", "--materials", "lambert",
              "--pano-size", "32,16", "--pano-spp", "2"]

# stage → (arguments of the previous run, arguments of the new run); outputs are named relative to the
# output folder the process runs in. The two runs differ in one option, so their main outputs differ.
STAGE_ARGS = {
    "make-scene": (["make-scene", "--out", "ms", *MINI_SCENE, "--preview", "ms.png", "--seed", "1"],
                   ["make-scene", "--out", "ms", *MINI_SCENE, "--preview", "ms.png", "--seed", "2"]),
    "import": (["import", "{w}/c.ply", "--out", "cloud.ply", "--preview", "cloud.png", "--max-points", "6000"],
               ["import", "{w}/c.ply", "--out", "cloud.ply", "--preview", "cloud.png"]),
    "build-bsh": (["build-bsh", "{w}/c.ply", "--out", "bsh.npz", "--preview", "bsh.png", "--bits", "16"],
                  ["build-bsh", "{w}/c.ply", "--out", "bsh.npz", "--preview", "bsh.png"]),
    "poisson": (["poisson", "{w}/proj.ply", "--out", "hdr.ply", "--preview", "hdr.png", "--k", "8"],
                ["poisson", "{w}/proj.ply", "--out", "hdr.ply", "--preview", "hdr.png"]),
    "expose-match": (["expose-match", "{w}/photo.exr", "{w}/ldr.ply", "--out", "e.npz", "--photo-ldr", "pl.exr", "--preview",
                      "e.png", "--alpha-from", "histogram", "--bins", "32"],
                     ["expose-match", "{w}/photo.exr", "{w}/ldr.ply", "--out", "e.npz", "--photo-ldr", "pl.exr", "--preview",
                      "e.png", "--alpha-from", "histogram"]),
    "render-cubemaps": (["render-cubemaps", "{w}/ldr.ply", "--out", "cm", "--size", "32", "--probe-size", "16", "--preview", "cm.png"],
                        ["render-cubemaps", "{w}/ldr.ply", "--out", "cm", "--size", "48", "--probe-size", "16", "--preview", "cm.png"]),
    "patchmatch": (["patchmatch", "{w}/cm", "--photo", "{w}/photo.exr", "--photo-ldr", "{w}/pl.exr", "--exposure", "{w}/e.npz",
                    "--out", "hf", "--levels", "1", "--iterations", "1", "--preview", "hf.png"],
                   ["patchmatch", "{w}/cm", "--photo", "{w}/photo.exr", "--photo-ldr", "{w}/pl.exr", "--exposure", "{w}/e.npz",
                    "--out", "hf", "--levels", "1", "--iterations", "2", "--preview", "hf.png"]),
    "reproject": (["reproject", "{w}/ldr.ply", "{w}/cm", "{w}/hf", "--out", "proj.ply", "--photo", "{w}/photo.exr", "--exposure",
                   "{w}/e.npz", "--preview", "proj.png", "--transfer", "lum"],
                  ["reproject", "{w}/ldr.ply", "{w}/cm", "{w}/hf", "--out", "proj.ply", "--photo", "{w}/photo.exr", "--exposure",
                   "{w}/e.npz", "--preview", "proj.png"]),
    "relight": (["relight", "--bsh", "{w}/room.npz", "--object", "{w}/o.glb", "--eye", "0,0.2,1.5", "--target", "0,0.1,0",
                 "--size", "32x24", "--microbuffer", "8", "--out", "relit"],
                ["relight", "--bsh", "{w}/room.npz", "--object", "{w}/o.glb", "--eye", "0,0.2,1.5", "--target", "0,0.1,0",
                 "--size", "32x24", "--microbuffer", "16", "--out", "relit"]),
    # (--no-render: the rendering columns relight in a system temp folder, which a kill -9 leaves behind; see README)
    "evaluate": (["evaluate", "--truth", "{w}/truth", "{w}/truth/cloud_ldr.ply", "--no-render", "--json", "t.json", "--md", "t.md",
                  "--preview", "t.png"],
                 ["evaluate", "--truth", "{w}/truth", "{w}/truth/cloud_ldr.ply", "{w}/truth/cloud_gt.ply", "--no-render",
                  "--json", "t.json", "--md", "t.md", "--preview", "t.png"]),
}
# the log line after which a stage is under way (it read its input); make-scene reads no input file: its first line
MARK = {"make-scene": "pcrelight.make-scene: Mitsuba "}
# ``make test`` kills build-bsh (TRIALS times) and, CI_TRIALS times each, the stages named here (default: every
# stage); ``make fuzz`` kills and signals every stage, TRIALS times each
CI_STAGES = os.environ.get("PCRELIGHT_KILL_CI_STAGES", ",".join(STAGE_ARGS)).split(",")
CI_TRIALS = int(os.environ.get("PCRELIGHT_KILL_CI_TRIALS", "1"))


def _args(stage: str, w: Path, new: bool) -> list[str]:
    return [a.replace("{w}", str(w)) for a in STAGE_ARGS[stage][int(new)]]


def _pcrelight(cwd: Path, *args: str) -> subprocess.Popen:
    """The CLI in a fresh process, run in ``cwd`` (outputs named relative to it: every run's report reads the same)."""
    code = f"import sys; sys.path.insert(0, {str(ROOT)!r}); import cli; sys.argv[0] = 'pcrelight'; cli.main()"
    return subprocess.Popen([sys.executable, "-c", code, *args], cwd=str(cwd),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _wait_for_read(p: subprocess.Popen, stage: str = "build-bsh") -> tuple[float, list[str]]:
    """Block until the stage logged that it read an input (imports done, the stage under way)."""
    lines = []
    mark = MARK.get(stage, ": read ")
    for line in p.stderr:
        lines.append(line)
        if mark in line:
            return time.perf_counter(), lines
    raise AssertionError(f"the stage never logged {mark!r}: " + "".join(lines))


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    d = tmp_path_factory.mktemp("kill")
    rng = np.random.default_rng(7)
    p = rng.uniform(-1, 1, (N_POINTS, 3)).astype(np.float32)
    nr = (-p / np.linalg.norm(p, axis=1, keepdims=True)).astype(np.float32)
    io.write_cloud(d / "c.ply", io.Cloud(p, nr, rng.uniform(0, 2, (N_POINTS, 3)).astype(np.float32)))
    return d


NEEDS = {"import": [], "build-bsh": [], "poisson": ["proj"], "expose-match": ["room"], "render-cubemaps": ["room"],
         "patchmatch": ["room", "cm", "exposure"], "reproject": ["room", "cm", "exposure", "hf"], "relight": ["room", "bsh"],
         "make-scene": [], "evaluate": ["truth"]}


def _prepare(stage: str, d: Path) -> None:
    """Write the inputs ``stage`` reads into the work folder ``d`` (once each)."""
    from test_reliability import _box_room

    for need in NEEDS[stage]:
        if (d / f".{need}.done").exists():
            continue
        if need == "proj":
            rng = np.random.default_rng(7)
            p = rng.uniform(-1, 1, (N_POINTS, 3)).astype(np.float32)[:3000]
            nr = (-p / np.linalg.norm(p, axis=1, keepdims=True)).astype(np.float32)
            rng = np.random.default_rng(8)
            io.write_cloud(d / "proj.ply", io.Cloud(p, nr, rng.uniform(0, 1, (3000, 3)).astype(np.float32),
                                                    valid=(rng.uniform(size=3000) > 0.1).astype(np.uint8),
                                                    quality=np.zeros(3000, np.float32), source=np.zeros(3000, np.uint8)))
        elif need == "room":
            _box_room(d / "ldr.ply")
            io.write_image(d / "photo.exr", np.random.default_rng(7).uniform(0, 6, (48, 64, 3)).astype(np.float32))
        elif need == "bsh":
            io.write_mesh(d / "o.glb", np.array([[0, 0, 0], [0.5, 0, 0], [0, 0.5, 0], [0, 0, 0.5]], np.float32),
                          np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]]))
            _run_in_process(["build-bsh", str(d / "ldr.ply"), "--out", "room.npz"], d)
        elif need == "exposure":
            _run_in_process(["expose-match", str(d / "photo.exr"), str(d / "ldr.ply"), "--out", "e.npz", "--photo-ldr", "pl.exr",
                             "--alpha-from", "histogram"], d)
        elif need == "cm":
            _run_in_process(["render-cubemaps", str(d / "ldr.ply"), "--out", "cm", "--size", "32", "--probe-size", "16"], d)
        elif need == "hf":
            _run_in_process(["patchmatch", str(d / "cm"), "--photo", str(d / "photo.exr"), "--photo-ldr", str(d / "pl.exr"),
                             "--exposure", str(d / "e.npz"), "--out", "hf", "--levels", "1", "--iterations", "2"], d)
        elif need == "truth":  # a ground truth for evaluate: make-scene's new reference output when it ran, else its like
            made = d / "make-scene" / "new" / "ms"
            if (made / "report.json").exists():
                shutil.copytree(made, d / "truth")
            else:
                _run_in_process(["make-scene", "--out", "truth", *MINI_SCENE, "--no-references", "--seed", "2"], d)
        (d / f".{need}.done").touch()


def _outputs(out: Path) -> dict[str, bytes]:
    return {str(f.relative_to(out)): f.read_bytes() for f in sorted(out.rglob("*"))
            if f.is_file() and not f.name.startswith(".")}


def _temps(out: Path) -> list[str]:
    return sorted(f.name for f in out.rglob(".*") if f.is_file() and ".tmp." in f.name)


def _strip(o):
    if isinstance(o, dict):
        # clock readings, and whether a cache entry was read (the run's history, like its clock: the bytes agree)
        return {k: _strip(v) for k, v in o.items()
                if not ("timing" in k or "seconds" in k or k.endswith("_s") or k.endswith("_cache"))}
    return [_strip(v) for v in o] if isinstance(o, list) else o


def _same(name: str, a: bytes, b: bytes) -> bool:
    """Bytes equal; a JSON report: equal but for its clock readings."""
    return _strip(json.loads(a)) == _strip(json.loads(b)) if name.endswith(".json") else a == b


def _run_in_process(args: list[str], cwd: Path) -> None:
    from click.testing import CliRunner

    import cli

    cwd.mkdir(parents=True, exist_ok=True)
    old = os.getcwd()
    os.chdir(cwd)
    try:
        r = CliRunner().invoke(cli.main, [*args, "-q"], catch_exceptions=False)
    finally:
        os.chdir(old)
    assert r.exit_code == 0, r.output


def _run_complete(args: list[str], out: Path, stage: str) -> float:
    """Run to the end in a fresh process; the seconds from its input read to its exit."""
    out.mkdir(parents=True, exist_ok=True)
    p = _pcrelight(out, *args)
    t_read, _ = _wait_for_read(p, stage)
    _, err = p.communicate(timeout=300)
    assert p.returncode == 0, err
    return time.perf_counter() - t_read


def _references(stage: str, w: Path) -> tuple[dict[str, bytes], dict[str, bytes], float]:
    """The previous outputs, and the new ones twice — once in this process, once in a fresh one (which
    also times the stage after it read its input): the same bytes. (Once a stage per module: cached.)"""
    if stage in _REFS:
        return _REFS[stage]
    _prepare(stage, w)
    base = w / stage
    _run_in_process(_args(stage, w, new=False), base / "old")
    _run_in_process(_args(stage, w, new=True), base / "new")
    new = _outputs(base / "new")
    span = _run_complete(_args(stage, w, new=True), base / "new", stage)  # the same folder: the reports name their paths
    again = _outputs(base / "new")
    old = _outputs(base / "old")
    assert sorted(new) == sorted(again) == sorted(old), (sorted(new), sorted(old))
    for k in new:
        assert _same(k, new[k], again[k]), f"{stage}: {k}: this process and a fresh one wrote different outputs"
    assert any(not _same(k, old[k], new[k]) for k in new), f"{stage}: the previous and the new outputs are the same"
    _REFS[stage] = old, new, span
    return _REFS[stage]


_REFS: dict[str, tuple[dict[str, bytes], dict[str, bytes], float]] = {}


@pytest.fixture(scope="module")
def bsh_refs(work):
    return _references("build-bsh", work)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_signal_during_stage_exits_128_plus_n_outputs_intact(work, bsh_refs, sig):
    old, _, _ = bsh_refs
    out = work / f"sig{int(sig)}"
    shutil.copytree(work / "build-bsh" / "old", out)
    p = _pcrelight(out, *_args("build-bsh", work, new=True))
    _wait_for_read(p)
    time.sleep(0.05)
    p.send_signal(sig)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 128 + sig, (p.returncode, err)
    last = err.strip().splitlines()[-1]
    assert last == f"pcrelight: interrupted by signal {int(sig)}; outputs left as they were", err
    assert "Traceback" not in err
    assert _outputs(out) == old and _temps(out) == []


KNOWN: dict[str, str] = {}  # stage → why its trials fail today (render-cubemaps' was fixed: it drops stale faces last)


def _trials(stage: str) -> int:
    """Kill -9 trials of ``stage`` in this run (skips the stage when none)."""
    if ALL_STAGES or stage == "build-bsh":
        return TRIALS
    if stage not in CI_STAGES:
        pytest.skip(f"{stage}: its trials run under make fuzz (PCRELIGHT_KILL_STAGES=all); make test: "
                    f"build-bsh, {', '.join(CI_STAGES)}")
    return CI_TRIALS


def _check_files(stage: str, t: int, got: dict[str, bytes], old: dict[str, bytes], new: dict[str, bytes],
                 figures: dict) -> None:
    """Every output is the previous one byte for byte or the complete new one; count which."""
    assert sorted(got) == sorted(old), (t, sorted(got))
    kinds = []
    for name, b in got.items():
        is_old, is_new = b == old[name], _same(name, b, new[name])
        assert is_old or is_new, f"{stage} trial {t}: {name} is neither the previous output nor a complete new one"
        if is_old != is_new:  # (a preview can come out the same for both)
            kinds.append("old" if is_old else "new")
            figures[f"files_{kinds[-1]}"] += 1
    figures["mixed_trials"] += len(set(kinds)) > 1  # stopped between two writes: each file whole


def _report(key: str, figures: dict) -> None:
    rep = os.environ.get("PCRELIGHT_KILL_REPORT")
    if rep:
        Path(rep).parent.mkdir(parents=True, exist_ok=True)
        allfig = json.loads(Path(rep).read_text()) if Path(rep).exists() else {}
        allfig[key] = figures
        Path(rep).write_text(json.dumps(allfig, indent=2) + "\n")
    print(f"{key} figures:", figures)


def _rng() -> random.Random:
    seed = int(os.environ.get("PCRELIGHT_KILL_SEED", "0")) or (None if TRIALS > 3 else 30)
    return random.Random(seed)


@pytest.mark.parametrize("stage", [pytest.param(s, marks=pytest.mark.xfail(reason=KNOWN[s], strict=False)) if s in KNOWN
                                   else s for s in STAGE_ARGS])
def test_kill9_at_random_points_nothing_lost(work, stage):
    trials = _trials(stage)
    old, new, span = _references(stage, work)
    rng = _rng()
    figures = {"stage": stage, "trials": 0, "killed": 0, "finished_first": 0, "files_old": 0, "files_new": 0,
               "mixed_trials": 0, "temp_files_left": 0, "temp_files_removed_by_next_run": 0, "stage_span_s": round(span, 2)}
    for t in range(trials):
        out = work / stage / f"k{t}"
        shutil.copytree(work / stage / "old", out)
        p = _pcrelight(out, *_args(stage, work, new=True))
        _wait_for_read(p, stage)
        # every other trial aims at the end of the stage, where it writes its files; a single trial (make test)
        # at the middle of its work, so that it surely lands while the stage runs
        time.sleep(span * (rng.uniform(0.2, 0.5) if trials == 1 else rng.uniform(0.55, 1.05) if t % 2
                           else rng.uniform(0, 1.1)))
        p.kill()
        _, err = p.communicate(timeout=60)
        figures["trials"] += 1
        assert p.returncode in (-signal.SIGKILL, 0), (p.returncode, err)
        figures["killed" if p.returncode == -signal.SIGKILL else "finished_first"] += 1
        _check_files(stage, t, _outputs(out), old, new, figures)
        left = _temps(out)
        figures["temp_files_left"] += len(left)
        if left:  # the next write of the same outputs removes what the killed process left
            _run_in_process(_args(stage, work, new=True), out)
            assert _temps(out) == [], _temps(out)
            figures["temp_files_removed_by_next_run"] += len(left)
        shutil.rmtree(out)
    _report(stage, figures)
    assert figures["trials"] == trials
    assert figures["killed"] >= 1, f"{stage}: no kill -9 landed while the stage ran ({figures})"


SIGNAL_TRIALS = int(os.environ.get("PCRELIGHT_SIGNAL_TRIALS", str(max(2, TRIALS // 5))))


@pytest.mark.parametrize("stage", list(STAGE_ARGS))
def test_signal_at_random_points_exit_128_plus_n_no_temp_file(work, stage):
    """SIGTERM and SIGINT (alternately) at a random point of each stage: exit 128 + N with the one line, no
    traceback, no temp file left, every output the previous one or a complete new one (a stop after the
    stage renamed one of its outputs into place keeps that file: each file is whole) — or exit 0 when the
    stage finished first (a stop after the command's work is ignored: the interpreter's shutdown restored the
    default actions, and a signal then killed the process, returncode −N, until 2026-12-03).
    ``make test``: one SIGTERM a stage, mid-stage; ``make fuzz``: SIGNAL_TRIALS a stage at random points."""
    if not ALL_STAGES and stage not in CI_STAGES:
        pytest.skip(f"{stage}: not in PCRELIGHT_KILL_CI_STAGES")
    old, new, span = _references(stage, work)
    trials = SIGNAL_TRIALS if ALL_STAGES else 1
    rng = _rng()
    figures = {"stage": stage, "trials": 0, "stopped": 0, "finished_first": 0, "files_old": 0, "files_new": 0,
               "mixed_trials": 0, "temp_files_left": 0}
    for t in range(trials):
        sig = (signal.SIGTERM, signal.SIGINT)[t % 2]
        out = work / stage / f"s{t}"
        shutil.copytree(work / stage / "old", out)
        p = _pcrelight(out, *_args(stage, work, new=True))
        _wait_for_read(p, stage)
        time.sleep(span * (rng.uniform(0, 1.1) if ALL_STAGES else rng.uniform(0.2, 0.5)))
        p.send_signal(sig)
        _, err = p.communicate(timeout=120)
        figures["trials"] += 1
        assert p.returncode in (128 + sig, 0), (stage, t, p.returncode, err)
        assert "Traceback" not in err and "Exception ignored" not in err, err
        got = _outputs(out)
        if p.returncode == 128 + sig:
            figures["stopped"] += 1
            assert err.strip().splitlines()[-1] == f"pcrelight: interrupted by signal {int(sig)}; outputs left as they were", err
        else:
            figures["finished_first"] += 1
        _check_files(stage, t, got, old, new, figures)
        left = _temps(out)
        figures["temp_files_left"] += len(left)
        assert left == [], f"{stage} trial {t}: {sig.name} left {left}"
        shutil.rmtree(out)
    _report(f"{stage} (SIGTERM/SIGINT)", figures)
    assert figures["trials"] == trials
    assert figures["stopped"] >= 1, f"{stage}: no signal landed while the stage ran ({figures})"


SWALLOWERS = {
    # Interrupted was an Exception: this loop swallowed it, the stage went on, renamed its new output into
    # place and exited 0
    "catch-all": ("        for _ in range(100):\n"
                  "            try:\n"
                  "                time.sleep(0.02)\n"
                  "            except Exception:\n"
                  "                pass\n"),
    # a stop raised in a finaliser (or a ctypes callback: llvmlite's, while numba compiles) is printed as
    # "Exception ignored in …" with a traceback and lost: the handler defers it to the next safe point
    "finaliser": ("        class Slow:\n"
                  "            def __del__(self):\n"
                  "                time.sleep(0.02)\n"
                  "        for _ in range(100):\n"
                  "            Slow()\n"),
}


@pytest.mark.parametrize("where", list(SWALLOWERS))
def test_signal_is_not_swallowed(tmp_path, where):
    """A stop request that lands where Python would swallow an exception still stops the stage: exit 143,
    one line, no traceback, the previous output untouched, no temp file."""
    target = tmp_path / "out.ply"
    target.write_bytes(b"previous")
    code = (f"import sys, time; sys.path.insert(0, {str(ROOT)!r})\n"
            "import cli\n"
            "from pipeline import io\n"
            "def stage():\n"
            f"    with io.atomic_path({str(target)!r}) as tmp:\n"
            "        tmp.write_bytes(b'partial')\n"
            "        print('ready', flush=True)\n"
            + SWALLOWERS[where] +
            "cli._guard(0, stage)\n")
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "ready"
    time.sleep(0.3)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 128 + signal.SIGTERM, (p.returncode, err)
    assert err.strip() == "pcrelight: interrupted by signal 15; outputs left as they were", err
    assert target.read_bytes() == b"previous" and sorted(x.name for x in tmp_path.iterdir()) == ["out.ply"]
