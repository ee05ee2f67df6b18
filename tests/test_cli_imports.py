"""Start-up paid once (issue 23 item 3): the CLI imports only what the verb it runs needs. ``import cli`` builds no
verb (each is built on first lookup), so it imports no stage module and none of numba, trimesh, Open3D, SciPy;
building the relight verb (its options from RelightConfig) imports the relight stage's module and still none of
them (relight imports trimesh for the object and numba for the object's surfel BSH when it runs, not before)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("numba", "trimesh", "open3d", "scipy", "cv2", "mitsuba")


def _modules_after(code: str) -> set[str]:
    """The top-level module names in sys.modules after running ``code`` in a fresh interpreter (this checkout)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-c", code + "\nimport sys, json\nprint(json.dumps(sorted(sys.modules)))"],
                         capture_output=True, text=True, env=env, cwd=ROOT, check=True).stdout
    return set(json.loads(out.strip().splitlines()[-1]))


def test_import_cli_imports_no_stage_and_no_heavy_library():
    mods = _modules_after("import cli")
    assert not {m for m in mods if m.split(".")[0] in HEAVY}
    stage_modules = {f"pipeline.{m}" for m in ("scene.make_scene", "ingest.import_scan", "ingest.merge_brackets",
                                               "expansion.expose_match", "expansion.render_cubemaps",
                                               "expansion.patchmatch", "expansion.reproject", "expansion.poisson",
                                               "bsh.build_bsh", "relight.relight", "measure.evaluate", "measure.trade")}
    assert not mods & stage_modules
    assert "cli" in mods


def test_relight_verb_builds_without_numba_trimesh_open3d():
    mods = _modules_after("import cli\ncmd = cli.main.get_command(None, 'relight')\n"
                          "assert 'method' in {p.name for p in cmd.params}")
    assert "pipeline.relight.relight" in mods
    assert not {m for m in mods if m.split(".")[0] in ("numba", "trimesh", "open3d")}
    # the other stages' modules were not imported for relight's options
    assert "pipeline.expansion.render_cubemaps" not in mods and "pipeline.bsh.build_bsh" not in mods


def test_every_verb_is_listed_and_builds():
    """The lazy verbs are all still there: --help lists each and each builds with its options."""
    import cli

    names = cli.main.list_commands(None)
    assert names[:len(cli.VERBS)] == cli.VERBS
    for verb in names:
        cmd = cli.main.get_command(None, verb)
        assert cmd is not None and cmd.name == verb and cmd is cli.main.get_command(None, verb)
