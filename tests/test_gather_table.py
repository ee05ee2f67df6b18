"""The gatherer table (pipeline/gather): relight's --method choices, its presets, evaluate's method and
the bench scripts read it, and a gatherer added from tests/ by one module and one table row
(tests/gather_constant.py) runs through the real relight CLI end to end."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from pipeline import io
from pipeline.gather import GATHERERS

TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent


def test_choices_and_presets_read_the_table():
    from pipeline.measure.evaluate import EvaluateConfig
    from pipeline.relight.relight import RelightConfig

    for cls in (RelightConfig, EvaluateConfig):
        (f,) = [f for f in cls.__dataclass_fields__.values() if f.name == "method"]
        assert tuple(f.metadata["choices"]) == tuple(GATHERERS)
    assert {"classic", "mipmapped", "hybrid"} <= set(GATHERERS)
    assert all(p["method"] in GATHERERS for p in RelightConfig.presets().values())


def _scene(tmp_path: Path) -> list[str]:
    import trimesh
    from bsh_builders import simple_bsh_arrays

    rng = np.random.default_rng(0)
    p = rng.normal(size=(300, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    io.write_npz(tmp_path / "bsh.npz", "pcrelight.bsh/1", **simple_bsh_arrays(3 * p, -p, np.ones((300, 3)), 0.4))
    tm = trimesh.creation.icosphere(2, radius=0.5)
    io.write_mesh(tmp_path / "o.ply", tm.vertices, tm.faces, tm.vertex_normals)
    return ["relight", "--bsh", str(tmp_path / "bsh.npz"), "--object", str(tmp_path / "o.ply"), "--eye", "0,0,2",
            "--target", "0,0,0", "--size", "16x12", "--brdf", "lambert", "--albedo", "0.5,0.25,1", "--microbuffer", "8"]


def _cli(args: list[str], register: bool) -> subprocess.CompletedProcess:
    pre = "import gather_constant; " if register else ""
    code = (f"import sys; sys.path[:0] = [{str(TESTS)!r}, {str(ROOT)!r}]; {pre}import cli; "
            f"sys.argv = ['pcrelight', *sys.argv[1:]]; cli.main()")
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=300)


def test_gatherer_added_from_tests_runs_relight_end_to_end(tmp_path):
    args = _scene(tmp_path) + ["--method", "constant", "--out", str(tmp_path / "out"), "-q"]
    r = _cli(args, register=False)                      # not in the table: not a --method choice
    assert r.returncode == 2 and "constant" in r.stderr
    r = _cli(args, register=True)                       # one module + one row: relight runs it
    assert r.returncode == 0, r.stderr
    img = io.read_image(tmp_path / "out" / "relit.exr")
    st = io.read_json(tmp_path / "out" / "stats.json")
    cov = img[..., 3] > 0
    assert st["method"] == "constant" and cov.sum() == st["covered_pixels"] > 20
    assert np.array_equal(img[cov][:, :3], np.broadcast_to(np.float32([1.0, 0.5, 2.0]), (int(cov.sum()), 3)))
    assert np.all(img[~cov] == 0)
    assert (tmp_path / "out" / "relit.png").exists()
