"""The command line: verb table, help with defaults, config overlays, one-line errors."""

from __future__ import annotations

import json
import subprocess
import sys

import click
import pytest

import cli
from pipeline.errors import NotImplementedStage

ALL = ["expose-match", "render-cubemaps", "patchmatch", "reproject", "poisson", "build-bsh", "relight",
       "make-scene", "merge-brackets", "evaluate", "trade", "run", "info"]


def test_help_lists_all_eleven_verbs(cli_run):
    code, out, _ = cli_run("--help")
    assert code == 0
    for v in ALL:
        assert f"  {v} " in out


@pytest.mark.parametrize("verb", [v for v in ALL if v != "info"])
def test_every_stage_has_common_options(cli_run, verb):
    code, out, _ = cli_run(verb, "--help")
    assert code == 0
    for opt in ("--seed", "--config", "--preview", "-q", "-v"):
        assert opt in out
    assert "[default: 0]" in out  # the seed's default is shown


def _dummy_verb():
    """A throw-away verb built with the same decorator as every stage (registered once)."""
    if "x-io-check" in cli.main.commands:
        return
    from dataclasses import dataclass, field

    from pipeline import io
    from pipeline.config import StageConfig

    @dataclass
    class XCfg(StageConfig):
        size: int = field(default=4, metadata={"help": "size [pixels]"})

        def check(self):
            self._require(self.size >= 1, "size", "must be ≥ 1")

    import pipeline.config as pc
    from pipeline.verbs import VERB, Verb

    pc.XCfg = XCfg  # so the decorator can import it by name
    # a test verb: declared in the registry's lookup table as every verb is (not in VERBS: not a user's verb)
    VERB["x-io-check"] = Verb("x-io-check", "pipeline.config:XCfg", "tool", "test verb", "test verb", (), "", "", "")

    @cli.stage("x-io-check")
    @click.argument("cloud", required=False)
    @click.option("--npz", default=None)
    @click.option("--exr", default=None)
    @click.option("--todo", is_flag=True)
    def _x(cfg, preview, cloud, npz, exr, todo):
        if todo:
            raise NotImplementedStage("x-io-check")
        if cloud:
            io.read_cloud(cloud)
        if npz:
            io.read_npz(npz, "pcrelight.cameras/1")
        if exr:
            io.read_image(exr)


@pytest.fixture
def xverb():
    _dummy_verb()


def test_not_implemented_answers_exit_2_one_line(cli_run, xverb):
    code, out, err = cli_run("x-io-check", "--todo")
    assert code == 2 and err == "pcrelight: x-io-check is not implemented yet\n" and out == ""


def _bad_files(tmp_path):
    import numpy as np

    from pipeline import io

    full = "x y z nx ny nz red green blue".split()
    hdr = lambda n, f: "ply\nformat ascii 1.0\nelement vertex %d\n" % n + "".join(f"property float {x}\n" for x in f) + "end_header\n"
    (tmp_path / "empty.ply").write_text(hdr(0, full))
    (tmp_path / "nan.ply").write_text(hdr(1, full) + "0 0 0 0 1 0 nan 1 1\n")
    (tmp_path / "nonormal.ply").write_text(hdr(1, full[:3] + full[6:]) + "0 0 0 1 1 1\n")
    (tmp_path / "nocolour.ply").write_text(hdr(1, full[:6]) + "0 0 0 0 1 0\n")
    (tmp_path / "trunc.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\n"
                                         + b"".join(b"property float %s\n" % x.encode() for x in full) + b"end_header\n" + b"\0" * 30)
    np.savez(tmp_path / "wrong.npz", schema=np.asarray("pcrelight.other/1"))
    np.savez(tmp_path / "noschema.npz", K=np.zeros((1, 3, 3)))
    np.savez(tmp_path / "dtype.npz", schema=np.asarray("pcrelight.cameras/1"), K=np.zeros((1, 3, 3), np.float32),
             world_to_camera=np.zeros((1, 4, 4)), resolution=np.zeros((1, 2), np.int32), view=np.zeros(1, np.int32),
             face=np.zeros(1, np.int32), eye=np.zeros((1, 3)))
    io.write_image(tmp_path / "ok.exr", np.ones((32, 32, 3), np.float32))
    (tmp_path / "corrupt.exr").write_bytes((tmp_path / "ok.exr").read_bytes()[:200])


@pytest.mark.parametrize("args,needle", [
    (["missing.ply"], "missing.ply: no such file"),
    (["empty.ply"], "empty.ply: empty point cloud"),
    (["nan.ply"], "nan.ply: 1 points have non-finite colors"),
    (["nocolour.ply"], "nocolour.ply: PLY has no colours"),
    (["trunc.ply"], "trunc.ply: not a readable PLY"),
    (["--npz", "wrong.npz"], "wrong.npz: schema is 'pcrelight.other/1', expected 'pcrelight.cameras/1'"),
    (["--npz", "noschema.npz"], "noschema.npz: no 'schema' key"),
    (["--npz", "dtype.npz"], "dtype.npz: schema pcrelight.cameras/1: 'K' has dtype float32, expected float64"),
    (["--exr", "corrupt.exr"], "corrupt.exr: "),
    (["--size", "0"], "--size must be ≥ 1, got 0"),
])
def test_bad_input_one_line_exit_code(cli_run, xverb, tmp_path, monkeypatch, args, needle):
    _bad_files(tmp_path)
    monkeypatch.chdir(tmp_path)
    code, out, err = cli_run("x-io-check", *args)
    assert code == (2 if args[0] == "--size" else 1)
    assert err.count("\n") == 1 and err.startswith("pcrelight: ") and needle in err, err


def test_missing_normals_are_estimated_not_an_error(cli_run, xverb, tmp_path, monkeypatch):
    _bad_files(tmp_path)
    monkeypatch.chdir(tmp_path)
    code, out, err = cli_run("x-io-check", "nonormal.ply")
    assert code == 0 and "estimated them" in err


def test_config_unknown_key_through_cli(cli_run, xverb, tmp_path):
    (tmp_path / "c.toml").write_text("[x-io-check]\nsise = 3\n")
    code, out, err = cli_run("x-io-check", "--config", tmp_path / "c.toml", "--todo")
    assert code == 2 and "unknown key 'sise' in [x-io-check]" in err and err.count("\n") == 1


def test_sigterm_exits_143_and_leaves_no_output(tmp_path):
    """A long command stopped by SIGTERM exits 128+15 and leaves the previous output intact."""
    import signal
    import time

    target = tmp_path / "out.ply"
    target.write_bytes(b"previous")
    code = (
        "import time, cli\n"
        "from pipeline import io, runtime\n"
        "def long():\n"
        "    with io.atomic_path(%r) as tmp:\n"
        "        tmp.write_bytes(b'partial')\n"
        "        print('ready', flush=True)\n"
        "        for _ in runtime.progress(range(600)): time.sleep(0.05)\n"
        "cli._guard(0, long)\n" % str(target)
    )
    p = subprocess.Popen([sys.executable, "-c", code], cwd=str(cli.__file__).rsplit("/", 1)[0],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "ready"  # handlers installed, temp file written
    time.sleep(0.2)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=30)
    assert p.returncode == 128 + signal.SIGTERM, err
    assert target.read_bytes() == b"previous"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["out.ply"]
    assert err.strip().endswith("interrupted by signal 15; outputs left as they were")


def test_info_reports_gl_and_mitsuba(cli_run):
    code, out, _ = cli_run("info", "--json")
    d = json.loads(out)
    assert code == 0 and d["gl"]["ok"] and d["gl"]["geometry_shader_transform_feedback"]
    assert "llvmpipe" in d["gl"]["renderer"].lower() or d["gl"]["vendor"]
    assert d["mitsuba"]["variant"] == "llvm_ad_rgb" and d["mitsuba"]["llvm"].startswith("19")
    code, out, _ = cli_run("info")
    assert "geometry shader + transform feedback: ok" in out


def test_progress_bar_only_on_a_terminal_outside_ci(monkeypatch, capsys):
    """A bar with ETA on an interactive terminal; nothing in CI, with -q, or when stderr is a pipe."""
    import io as _io

    from pipeline import runtime

    class TTY(_io.StringIO):
        def isatty(self):
            return True

    runtime.setup_logging(0)
    tty = TTY()
    monkeypatch.setattr(sys, "stderr", tty)
    monkeypatch.delenv("CI", raising=False)
    assert runtime.progress_enabled()
    assert list(runtime.progress(range(3), total=3, desc="work")) == [0, 1, 2]
    assert "work:" in tty.getvalue() and "/3 [" in tty.getvalue()  # a tqdm bar (count, elapsed<ETA)
    monkeypatch.setenv("CI", "true")
    assert not runtime.progress_enabled()
    monkeypatch.delenv("CI")
    runtime.setup_logging(-1)
    assert not runtime.progress_enabled()
    runtime.setup_logging(0)
    monkeypatch.setattr(sys, "stderr", _io.StringIO())
    assert not runtime.progress_enabled()


@pytest.mark.parametrize("args,needle", [
    (["patchmatch", "nocub", "--out", "o", "--min-fit-fraction", "1.5"], "--min-fit-fraction must be in [0, 1], got 1.5"),
    (["patchmatch", "nocub", "--out", "o", "--fit-q", "0"], "--fit-q must be > 0, got 0.0"),
    (["patchmatch", "nocub", "--out", "o", "--max-fit-median-q", "-1"], "--max-fit-median-q must be > 0, got -1.0"),
    (["render-cubemaps", "x.ply", "--out", "o", "--outlier-std", "0"], "--outlier-std must be > 0, got 0.0"),
    (["render-cubemaps", "x.ply", "--out", "o", "--outlier-neighbors", "-1"], "--outlier-neighbors must be ≥ 0, got -1"),
    (["make-scene", "--out", "o", "--cloud-target", "1"], "--cloud-target must be in [0, 1), got 1.0"),
    (["make-scene", "--out", "o", "--ref-target", "-0.5"], "--ref-target must be in [0, 1), got -0.5"),
    (["make-scene", "--out", "o", "--precise-target", "0"], "--precise-target must be in (0, 1), got 0.0"),
    (["make-scene", "--out", "o", "--photos", "nope"], "--photos must name distinct rules of: bright, lights, sun"),
])
def test_new_options_out_of_range_one_line_before_any_work(cli_run, tmp_path, monkeypatch, args, needle):
    """Options added with the photo-fit check, the outlier filter and adaptive sampling fail on the
    command line with one line and exit 2, before reading inputs or writing anything."""
    monkeypatch.chdir(tmp_path)
    code, out, err = cli_run(*args)
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("pcrelight: ") and needle in err, err
    assert list(tmp_path.iterdir()) == []
