"""pipeline/run/stages.py: one STAGES list (the CLI's verb order, `run`, `evaluate --run-all`), declared
inputs that earlier stages or the inputs folder provide, and the seed rules of `pcrelight run`.
(That the declarations match what each stage really reads and writes is checked on the tiny chain in
test_pipeline_e2e.py.)"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import cli
from pipeline import io
from pipeline.run import runner, stages
from pipeline.config import sub_seed, sub_seed_u64
from pipeline.errors import ConfigError
from pipeline.io.workspace import Workspace


def test_verbs_come_from_one_list():
    """pipeline/verbs.py declares every verb once: the stages `run` walks are its stage rows in its order, the CLI's
    verbs are all of its rows in its order (import: a scan → cloud; merge-brackets: brackets → photo; not in run)."""
    from pipeline.verbs import STAGE_VERBS, VERBS

    assert stages.VERBS == ["expose-match", "render-cubemaps", "patchmatch", "reproject", "poisson", "build-bsh",
                            "relight"] == list(STAGE_VERBS)
    assert cli.VERBS == [v.name for v in VERBS] == ["make-scene", "import", "merge-brackets", *stages.VERBS,
                                                    "evaluate", "trade", "run", "report", "batch", "info"]
    assert list(stages.STAGE) == stages.VERBS
    for st in stages.STAGES:  # every stage is built: its options class imports
        assert st.config_class().__name__ == st.config.partition(":")[2]


def _covers(declared: list[Path], p: Path) -> bool:
    return any(p == d or d in p.parents for d in declared)


def test_every_declared_input_is_an_input_file_or_an_earlier_output(tmp_path):
    ws = Workspace(tmp_path / "in", tmp_path / "ws")
    given = [ws.photo, ws.cloud_ldr, ws.scene, ws.object]
    made: list[Path] = []
    for st in stages.STAGES:
        for p in st.inputs(ws):
            assert p in given or _covers(made, p), f"{st.verb} reads {p}, which no earlier stage writes"
        outs = st.outputs(ws)
        assert outs and all(o.is_relative_to(ws.root) for o in outs)
        made += outs


def _tiny_inputs(folder: Path) -> None:
    """A 32×32 HDR photo and a 500-point LDR cloud: enough for expose-match."""
    rng = np.random.default_rng(0)
    io.write_image(folder / "photo.exr", (rng.random((32, 32, 3)) * 4.0).astype(np.float32))
    pts = rng.random((500, 3)).astype(np.float32)
    nrm = np.tile(np.float32([0, 1, 0]), (500, 1))
    io.write_cloud(folder / "cloud_ldr.ply", io.Cloud(pts, nrm, np.clip(rng.random((500, 3)) * 1.3, 0, 1).astype(np.float32)))


def _run(cli_run, tmp_path, toml: str, *args):
    cfg = tmp_path / "run.toml"
    cfg.write_text(toml.format(inp=tmp_path, ws=tmp_path / "ws"))
    code, _, err = cli_run("run", cfg, "--to", "expose-match", "--force", "-q", *args)
    rep = tmp_path / "ws" / "run.json"
    return code, err, (json.loads(rep.read_text()) if code == 0 and rep.exists() else None)


HEAD = '[run]\ninputs = "{inp}"\nworkspace = "{ws}"\n'


def test_run_takes_the_seed_written_in_its_toml(cli_run, tmp_path):
    _tiny_inputs(tmp_path)
    code, err, rep = _run(cli_run, tmp_path, "seed = 7\n" + HEAD)
    assert code == 0, err
    assert rep["stages"]["expose-match"]["config"]["seed"] == 7
    code, err, rep = _run(cli_run, tmp_path, "seed = 7\n" + HEAD, "--seed", "3")  # --seed wins
    assert code == 0, err
    assert rep["stages"]["expose-match"]["config"]["seed"] == 3 and rep["run"]["seed"] == 3
    code, err, rep = _run(cli_run, tmp_path, "seed = 7\n" + HEAD + "[expose-match]\nseed = 5\n")  # the stage's own
    assert code == 0, err
    assert rep["stages"]["expose-match"]["config"]["seed"] == 5
    code, err, _ = _run(cli_run, tmp_path, HEAD + "seed = 4\n")  # in [run] it would apply to nothing: refused
    assert code == 2 and "put 'seed' at the top of the file" in err


def test_run_options_on_the_command_line_win_over_the_toml(cli_run, tmp_path):
    _tiny_inputs(tmp_path)
    other = tmp_path / "elsewhere"
    code, err, _ = _run(cli_run, tmp_path, HEAD, "--workspace", str(other), "--no-previews")
    assert code == 0, err
    rep = json.loads((other / "run.json").read_text())
    assert rep["run"]["workspace"] == str(other) and rep["run"]["previews"] is False
    assert (other / "exposure.npz").exists() and not (other / "expose_match.png").exists()
    code, err, _ = _run(cli_run, tmp_path, HEAD, "--config", str(tmp_path / "run.toml"))
    assert code == 2 and "--config is not used" in err


def test_sub_seeds_follow_one_rule():
    # make-scene's stream default_rng([seed, 9]) and render-cubemaps' default_rng(seed) are this rule
    assert np.array_equal(np.random.default_rng(sub_seed(5, 9)).random(4), np.random.default_rng([5, 9]).random(4))
    assert np.array_equal(np.random.default_rng(sub_seed(5)).random(4), np.random.default_rng(5).random(4))
    u = {sub_seed_u64(s, t) for s in range(4) for t in range(50)}
    assert len(u) == 200 and all(0 <= x < 2 ** 64 for x in u)
    assert sub_seed_u64(1, 2) == sub_seed_u64(1, 2) != sub_seed_u64(2, 1)
    with pytest.raises(ConfigError, match="--seed must be ≥ 0"):
        sub_seed(-1)


def test_plan_is_jobs_with_options_resolved_from_one_read_of_the_toml(tmp_path, monkeypatch):
    """stages.plan: one job per stage from --from to --to, each with its resolved options; the TOML file is read
    once for all of them (config.TomlFile), and messages still name the file."""
    from pipeline import config

    _tiny_inputs(tmp_path)
    cfg = tmp_path / "run.toml"
    cfg.write_text("seed = 7\n" + HEAD.format(inp=tmp_path, ws=tmp_path / "ws") + "[poisson]\nk = 9\n")
    reads = []
    real = config.tomllib.load
    monkeypatch.setattr(config.tomllib, "load", lambda f: reads.append(f.name) or real(f))
    rp = runner.plan(str(cfg), "reproject", "build-bsh")
    assert reads == [str(cfg)]
    assert [j.verb for j in rp.jobs] == ["reproject", "poisson", "build-bsh"] and rp.jobs[0].ws == rp.ws
    assert rp.cfgs["poisson"].k == 9 and all(j.cfg.seed == 7 for j in rp.jobs)
    assert str(rp.config) == str(cfg) and rp.decisions.get("expansion").needed is True
    cfg.write_text(HEAD.format(inp=tmp_path, ws=tmp_path / "ws") + "[poisson]\nk = 0\n")
    with pytest.raises(ConfigError, match=f"^{cfg}: \\[poisson\\] k "):
        runner.plan(str(cfg), "poisson", "poisson")


def test_a_job_runs_the_same_in_this_process_and_on_an_executor(tmp_path):
    """stages.execute: a job run in this process and on the local executor (a spawned worker) writes the same bytes;
    a task's error comes back from the executor as a value, which execute raises."""
    import shutil

    from pipeline.run.executor import LocalExecutor
    from pipeline.expansion.poisson import PoissonConfig

    rng = np.random.default_rng(1)
    pts = rng.random((400, 3)).astype(np.float32)
    valid = (rng.random(400) > 0.1).astype(np.uint8)
    (tmp_path / "in").mkdir()
    cloud = io.Cloud(pts, np.tile(np.float32([0, 1, 0]), (400, 1)), rng.random((400, 3)).astype(np.float32),
                     valid=valid, quality=np.zeros(400, np.float32), source=valid.copy())
    io.write_cloud(tmp_path / "in" / "cloud_ldr.ply", io.Cloud(cloud.points, cloud.normals, cloud.colors))
    outs = {}
    with LocalExecutor(1) as ex:
        for name, on in (("here", None), ("there", ex)):
            ws = Workspace(tmp_path / "in", tmp_path / name, previews=False)
            ws.root.mkdir()
            io.write_cloud(ws.cloud_proj, cloud)
            assert runner.execute(runner.Job("poisson", PoissonConfig(), ws), on) > 0
            outs[name] = ws.cloud_hdr.read_bytes()
        with pytest.raises(ValueError, match="boom"):
            runner.execute(_Boom(), ex)
    assert outs["here"] == outs["there"] and len(outs["here"]) > 1000
    assert int((io.read_cloud(tmp_path / "here" / "cloud_hdr.ply").valid == 0).sum()) < int((valid == 0).sum())
    shutil.rmtree(tmp_path / "in")


class _Boom:
    """A job whose stage raises (picklable: a module-level class)."""

    name = "boom"

    @property
    def stage(self):
        raise ValueError("boom")


def test_every_stage_verb_is_generated_from_its_row():
    """cli.py declares no stage verb a second time: each STAGES row's verb has its row's paths (in order) and its
    config dataclass's fields as options, and its help."""
    for st in stages.STAGES:
        cmd = cli.main.commands[st.verb]
        assert cmd is cli.STAGE_VERBS[st.verb] and cmd.short_help == st.short and cmd.help == st.doc
        names = [p.name for p in cmd.params]
        assert names[-len(st.params):] == [p.name for p in st.params]
        assert set(st.config_class().field_names()) <= set(names)
        for p, q in zip(st.params, cmd.params[-len(st.params):]):
            assert q.required == p.required and (q.param_type_name == "argument") == (not p.flag)
            assert not p.flag or p.flag in q.opts
