"""Stopping a stage (issue 30): SIGINT/SIGTERM during build-bsh exit 128 + signal with the previous outputs
byte-identical and no temp file; kill -9 at random points of the stage (after it read its input: the
build and the writes) leaves every output either byte-identical to the previous one or byte-identical to
a complete new one. ``PCRELIGHT_KILL_TRIALS`` sets the trials (3 in ``make test``, 50 under ``make fuzz``);
``PCRELIGHT_KILL_REPORT=FILE`` writes the figures as JSON. A kill -9 cannot remove the temp file it
interrupts (``.<stem>.<pid>.*.tmp.<ext>``, ignored by git): those are counted, never take an output's name,
and the next write of that output removes them (their process is gone).
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
N_POINTS = 12000   # build-bsh runs ~1 s after reading its input on 2 cores: room to land a signal in it


def _pcrelight(cwd: Path, *args: str) -> subprocess.Popen:
    """The CLI in a fresh process, run in ``cwd`` (outputs named relative to it: every run's report reads the same)."""
    code = f"import sys; sys.path.insert(0, {str(ROOT)!r}); import cli; sys.argv[0] = 'pcrelight'; cli.main()"
    return subprocess.Popen([sys.executable, "-c", code, *args], cwd=str(cwd),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _wait_for_read(p: subprocess.Popen) -> tuple[float, list[str]]:
    """Block until the stage logged that it read its input (imports done, the stage under way)."""
    lines = []
    for line in p.stderr:
        lines.append(line)
        if "pcrelight.io: read " in line:
            return time.perf_counter(), lines
    raise AssertionError("the stage never logged reading its input: " + "".join(lines))


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    d = tmp_path_factory.mktemp("kill")
    rng = np.random.default_rng(7)
    p = rng.uniform(-1, 1, (N_POINTS, 3)).astype(np.float32)
    nr = (-p / np.linalg.norm(p, axis=1, keepdims=True)).astype(np.float32)
    io.write_cloud(d / "c.ply", io.Cloud(p, nr, rng.uniform(0, 2, (N_POINTS, 3)).astype(np.float32)))
    return d


def _args(d: Path, new: bool) -> list[str]:
    # previous output: --bits 16; new output: the default --bits 21 (another BSH)
    return ["build-bsh", str(d / "c.ply"), "--out", "bsh.npz", "--preview", "bsh.png", *([] if new else ["--bits", "16"])]


def _outputs(out: Path) -> dict[str, bytes]:
    return {f.name: f.read_bytes() for f in sorted(out.iterdir()) if not f.name.startswith(".")}


def _temps(out: Path) -> list[str]:
    return sorted(f.name for f in out.iterdir() if f.name.startswith(".") and ".tmp." in f.name)


def _report_equal(a: bytes, b: bytes) -> bool:
    """Two stage reports equal but for their timings."""
    strip = lambda o: {k: v for k, v in json.loads(o).items() if not k.startswith("timing")}  # noqa: E731
    return strip(a) == strip(b)


def _run_complete(d: Path, out: Path, new: bool) -> tuple[dict[str, bytes], float]:
    out.mkdir(parents=True, exist_ok=True)
    p = _pcrelight(out, *_args(d, new))
    t_read, _ = _wait_for_read(p)
    _, err = p.communicate(timeout=300)
    assert p.returncode == 0, err
    return _outputs(out), time.perf_counter() - t_read


def _run_in_process(d: Path, out: Path, new: bool) -> dict[str, bytes]:
    from click.testing import CliRunner

    import cli

    out.mkdir(parents=True, exist_ok=True)
    cwd = os.getcwd()
    os.chdir(out)
    try:
        r = CliRunner().invoke(cli.main, [*_args(d, new), "-q"], catch_exceptions=False)
    finally:
        os.chdir(cwd)
    assert r.exit_code == 0, r.output
    return _outputs(out)


@pytest.fixture(scope="module")
def references(work):
    """The previous outputs, and the new ones twice — once in this process, once in a fresh one (which
    also times the stage after it read its input): the same bytes."""
    old = _run_in_process(work, work / "old", new=False)
    new = _run_in_process(work, work / "new", new=True)
    again, span = _run_complete(work, work / "new", new=True)  # the same folder: the reports name their paths
    assert sorted(new) == sorted(again) == ["bsh.json", "bsh.npz", "bsh.png"]
    for k in ("bsh.npz", "bsh.png"):
        assert new[k] == again[k], f"{k}: two runs with the same seed differ"
    assert new["bsh.npz"] != old["bsh.npz"]  # (the preview may look the same)
    assert _report_equal(new["bsh.json"], again["bsh.json"])
    return old, new, span


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_signal_during_stage_exits_128_plus_n_outputs_intact(work, references, sig):
    old, _, _ = references
    out = work / f"sig{int(sig)}"
    shutil.copytree(work / "old", out)
    p = _pcrelight(out, *_args(work, new=True))
    _wait_for_read(p)
    time.sleep(0.05)
    p.send_signal(sig)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 128 + sig, (p.returncode, err)
    last = err.strip().splitlines()[-1]
    assert last == f"pcrelight: interrupted by signal {int(sig)}; outputs left as they were", err
    assert "Traceback" not in err
    assert _outputs(out) == old and _temps(out) == []


def test_kill9_at_random_points_nothing_lost(work, references):
    old, new, span = references
    rng = random.Random(int(os.environ.get("PCRELIGHT_KILL_SEED", "0")) or None if TRIALS > 3 else 30)
    figures = {"stage": "build-bsh", "points": N_POINTS, "trials": 0, "killed": 0, "finished_first": 0,
               "files_old": 0, "files_new": 0, "mixed_trials": 0, "temp_files_left": 0, "temp_files_removed_by_next_run": 0,
               "stage_span_s": round(span, 2)}
    for t in range(TRIALS):
        out = work / f"k{t}"
        shutil.copytree(work / "old", out)
        p = _pcrelight(out, *_args(work, new=True))
        _wait_for_read(p)
        # every other trial aims at the end of the stage, where it writes its three files
        time.sleep(span * (rng.uniform(0.55, 1.05) if t % 2 else rng.uniform(0, 1.1)))
        p.kill()
        _, err = p.communicate(timeout=60)
        figures["trials"] += 1
        assert p.returncode in (-signal.SIGKILL, 0), (p.returncode, err)
        figures["killed" if p.returncode == -signal.SIGKILL else "finished_first"] += 1
        got = _outputs(out)
        assert sorted(got) == sorted(old), (t, sorted(got))
        kinds = []
        for name, b in got.items():
            same = _report_equal if name.endswith(".json") else bytes.__eq__
            is_old, is_new = b == old[name], same(b, new[name])
            assert is_old or is_new, f"trial {t}: {name} is neither the previous output nor a complete new one"
            if is_old != is_new:  # (a preview can come out the same for both)
                kinds.append("old" if is_old else "new")
                figures[f"files_{kinds[-1]}"] += 1
        figures["mixed_trials"] += len(set(kinds)) > 1  # killed between two writes: each file whole
        left = _temps(out)
        figures["temp_files_left"] += len(left)
        assert all(n.split(".")[1] == "bsh" for n in left), left  # only this stage's own temp names
        if left:  # the next write of the same output removes what the killed process left
            again = _run_in_process(work, out, new=True)
            assert _temps(out) == [] and again["bsh.npz"] == new["bsh.npz"]
            figures["temp_files_removed_by_next_run"] += len(left)
        shutil.rmtree(out)
    rep = os.environ.get("PCRELIGHT_KILL_REPORT")
    if rep:
        Path(rep).parent.mkdir(parents=True, exist_ok=True)
        Path(rep).write_text(json.dumps(figures, indent=2) + "\n")
    print("kill -9 figures:", figures)
    assert figures["trials"] == TRIALS
