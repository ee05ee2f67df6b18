"""Code rules that keep the architecture (docs/ARCHITECTURE.md): layers import downwards only and no module is in a
circle (tests/import_graph.py), one verb registry, no module reaches into another's private (underscore) names,
and the face-folder file names are spelled only in pipeline/io/workspace.py (in the package and the CLI; a bench
script may name its own scratch files)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCES = sorted([*ROOT.glob("pipeline/**/*.py"), ROOT / "cli.py",
                  *(f for f in ROOT.glob("bench/**/*.py") if "_work" not in f.parts)])  # (_work: full runs' checkouts)


# the standard library's public names that begin with an underscore (os._exit: leave without the interpreter's
# shutdown, cli.py after a stop request)
STDLIB_PUBLIC = {("os", "_exit")}


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def test_no_module_imports_another_modules_private_names():
    found = []
    for f in SOURCES:
        tree = ast.parse(f.read_text(), str(f))
        modules = set()  # names bound to imported modules or objects in this file
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                found += [f"{f.relative_to(ROOT)}:{node.lineno} imports {a.name}" for a in node.names if _private(a.name)]
                modules |= {a.asname or a.name for a in node.names}
            elif isinstance(node, ast.Import):
                modules |= {(a.asname or a.name).split(".")[0] for a in node.names}
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and _private(node.attr) and isinstance(node.value, ast.Name)
                    and node.value.id in modules and (node.value.id, node.attr) not in STDLIB_PUBLIC):
                found.append(f"{f.relative_to(ROOT)}:{node.lineno} uses {node.value.id}.{node.attr}")
    assert found == []


def test_face_folder_names_are_spelled_once():
    for name in ('"cameras.npz"', '"renderings.npz"', '"face_{', '"face_*'):
        where = [f.relative_to(ROOT).as_posix() for f in SOURCES
                 if "bench" not in f.parts and name in f.read_text()]
        assert where == ["pipeline/io/workspace.py"], (name, where)


def _stage_modules() -> dict[str, str]:
    """``pipeline.<module>`` of every stage in pipeline/run/stages.py's STAGES → its verb."""
    from pipeline.run.stages import STAGES

    return {s.config.partition(":")[0]: s.verb for s in STAGES}


def _imported_modules(source: str, pkg: str = "pipeline") -> set[str]:
    """Every ``pipeline.*`` module a module of package ``pkg`` imports (top level or inside a function),
    absolute names."""
    tree = ast.parse(source)
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ".".join(pkg.split(".")[:len(pkg.split(".")) - node.level + 1])
                mod = f"{base}.{node.module}" if node.module else base
            else:
                mod = node.module or ""
            out.add(mod)
            out |= {f"{mod}.{a.name}" for a in node.names}  # `from . import reproject`
    return {m for m in out if m.startswith("pipeline.")}


def test_no_stage_imports_another_stage():
    """A stage module (pipeline/run/stages.py's STAGES) imports no other stage module; what two stages share lives in
    a non-stage module (cube-map cameras and splats: pipeline/expansion/splats.py; luminance: pipeline/color.py; …)."""
    stages = _stage_modules()
    assert len(stages) >= 7 and "pipeline.expansion.render_cubemaps" in stages and "pipeline.bsh.build_bsh" in stages
    found = []
    for mod in stages:
        f = ROOT / (mod.replace(".", "/") + ".py")
        pkg = mod.rpartition(".")[0]
        found += [f"{mod} imports {other}" for other in sorted(_imported_modules(f.read_text(), pkg) & set(stages))
                  if other != mod]
    assert found == []


def test_the_production_path_does_not_import_the_ground_truth_module():
    """pipeline/scene/mitsuba_render.py (Mitsuba: the ground truth) is imported by make-scene alone; the cameras every
    stage shares live in pipeline/camera.py."""
    users = sorted(f.stem for f in (ROOT / "pipeline").rglob("*.py")
                   if "pipeline.scene.mitsuba_render" in _imported_modules(
                       f.read_text(), ".".join(f.relative_to(ROOT).parent.parts)))
    assert users == ["make_scene"]


def test_the_stage_import_rule_sees_every_import_form():
    """The rule's import parser finds `from .x import y`, `from . import x`, `from ..x import y` and
    `import pipeline.x` (also inside functions), so a stage cannot slip past it by the form of its import."""
    src = ("from .render_cubemaps import cube_cameras\n"
           "def f():\n    from . import reproject\n    import pipeline.expansion.poisson\n")
    assert {"pipeline.expansion.render_cubemaps", "pipeline.expansion.reproject", "pipeline.expansion.poisson"} <= _imported_modules(src, "pipeline.expansion")
    assert "pipeline.bsh.build_bsh" in _imported_modules("from ..bsh.build_bsh import build_bsh\n", "pipeline.gather")


# the file-format packages that only pipeline/io/ may call (readers in one place); OpenImageIO is not listed:
# camera.exif_fov opens the photo for its EXIF tags (a reader of metadata that returns None for an unreadable file)
FORMAT_PACKAGES = ("plyfile", "pye57", "laspy", "pygltflib")


def test_files_are_read_only_through_pipeline_io():
    """The scan, PLY and glTF parsers are imported only by ``pipeline/io/`` (one place for readers; a new
    scan format is one row of ``io.CLOUD_READERS``), and Open3D reads point clouds only there."""
    found = []
    for f in SOURCES:
        rel = f.relative_to(ROOT).as_posix()
        if rel.startswith("pipeline/io/"):
            continue
        tree = ast.parse(f.read_text(), str(f))
        for node in ast.walk(tree):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
            found += [f"{rel}:{node.lineno} imports {n}" for n in names if n.split(".")[0] in FORMAT_PACKAGES]
            if isinstance(node, ast.Attribute) and node.attr in ("read_point_cloud", "read_triangle_mesh"):
                found.append(f"{rel}:{node.lineno} calls {node.attr}")
    assert found == []


def test_every_scan_suffix_has_a_reader_in_the_registry():
    from pipeline import io

    assert {".ply", ".pcd", ".xyz", ".xyzrgb", ".pts", ".e57", ".las", ".laz"} <= set(io.CLOUD_READERS)
    assert all(s == s.lower() and s.startswith(".") and callable(r) for s, r in io.CLOUD_READERS.items())


# ----------------------------------------------------------------------------- layers and circles
def test_every_module_is_in_a_layer_and_imports_downwards_only():
    """tests/import_graph.py's LAYERS (core < io < libraries < stages < run < measure): no module imports one of a
    higher layer (top-level or inside a function), and none is in an import circle."""
    import import_graph as ig

    g = ig.graph(ROOT)
    assert all(ig.layer_of(m) >= 0 for m in g)          # KeyError names a module in no layer
    assert ig.upward(g) == []
    assert ig.circles(g) == []


def test_the_layer_rule_sees_a_planted_upward_import_and_circle(tmp_path):
    """Copies of pipeline/, one with a planted upward import (a core module importing the runner, inside a
    function), one with a planted circle (io.npz ↔ io.images): each fails its rule, naming what was planted."""
    import shutil

    import import_graph as ig

    def plant(name: str, edits: dict[str, str]) -> Path:
        root = tmp_path / name
        shutil.copytree(ROOT / "pipeline", root / "pipeline", ignore=shutil.ignore_patterns("__pycache__"))
        for rel, line in edits.items():
            f = root / "pipeline" / rel
            f.write_text(f.read_text() + f"\n\ndef _planted():\n    {line}\n")
        return root

    up = ig.graph(plant("up", {"color.py": "from .run.runner import run_pipeline"}))
    assert ig.upward(up) == [("pipeline.color", "pipeline.run.runner")]
    circle = ig.graph(plant("circle", {"io/images.py": "from .npz import read_npz", "io/npz.py": "from . import images"}))
    assert ig.circles(circle) == [["pipeline.io.images", "pipeline.io.npz"]] and ig.upward(circle) == []


def test_the_move_removed_the_circles_and_upward_imports_of_the_flat_layout():
    """The counts docs/ARCHITECTURE.md states, on a tree of before issue 42 (git's copy at the commit before the
    move, when git is there): 4 circles (25 modules) and 7 upward imports then, none now."""
    import subprocess
    import tempfile

    import import_graph as ig

    base = "e81c08b~1"
    if subprocess.run(["git", "-C", str(ROOT), "cat-file", "-e", base], capture_output=True).returncode:
        import pytest

        pytest.skip("no git history of the move in this checkout")
    with tempfile.TemporaryDirectory() as d:
        tar = subprocess.run(["git", "-C", str(ROOT), "archive", base, "pipeline"], capture_output=True, check=True)
        subprocess.run(["tar", "-x", "-C", d], input=tar.stdout, check=True)
        g = ig.graph(Path(d), ig.old_names(Path(d)))
    cs = ig.circles(g)
    assert (len(cs), sum(map(len, cs)), len(ig.upward(g))) == (4, 25, 7)


# ----------------------------------------------------------------------------- one verb registry
def test_every_verb_is_declared_once_in_the_registry():
    """pipeline/verbs.py is the one list: the CLI's verbs, their order in --help, the tables a config file may
    hold (check_file), the stages `run` walks and README's stage table all come from it."""
    import re

    import cli
    from pipeline.config import check_file
    from pipeline.errors import ConfigError
    from pipeline.run.stages import STAGES
    from pipeline.verbs import STAGE_VERBS, TABLES, VERBS, stage_table

    names = [v.name for v in VERBS]
    assert len(set(names)) == len(names)
    listed = cli.main.list_commands(None)
    assert [n for n in listed if n in names] == names and set(listed) <= set(cli.VERB)   # (+ tests' own verbs)
    help_text = cli.main.get_help(cli.click.Context(cli.main))
    assert [line.split()[0] for line in help_text.splitlines() if line.startswith("    ") and line.split()
            and line.split()[0] in names][:len(names)] == names
    assert [s.verb for s in STAGES] == list(STAGE_VERBS)
    assert TABLES == {v.name for v in VERBS if v.config}
    for t in sorted(TABLES):                             # every verb's table is accepted, a made-up one is not
        check_file({t: {}}, "x.toml")
    import pytest

    with pytest.raises(ConfigError, match=r"x.toml: unknown table \[nope\]"):
        check_file({"nope": {}}, "x.toml")
    readme = (ROOT / "README.md").read_text()
    block = re.search(r"<!-- stages:begin -->\n(.*?)<!-- stages:end -->", readme, re.S).group(1)
    assert block.rstrip("\n").splitlines() == stage_table(), "README's stage table: run python -m pipeline.verbs"
    src = (ROOT / "cli.py").read_text()
    assert "@main.command" not in src and "main.add_command" not in src   # one way to declare a verb
