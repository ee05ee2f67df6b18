"""bench/manifest.toml against bench/: every result is some run's output, every script some run's script; benches
never import tests and tests never import benches (issue 42). Reads files only: no bench runs."""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "bench"
LIBRARY = {"bench/__init__.py", "bench/benchlib.py", "bench/run.py"}   # the bench's own code, not benches
TOPICS = {"bsh", "expansion", "photos", "relight", "gatherers", "speed", "peers", "batch", "plan", "composite", "splats"}


@pytest.fixture(scope="module")
def runs() -> list[dict]:
    with open(BENCH / "manifest.toml", "rb") as f:
        return tomllib.load(f)["run"]


def rel(p: Path) -> str:
    return p.relative_to(ROOT).as_posix()


def results() -> set[str]:
    """Every CSV/PNG under bench/ but the scratch folder (bench/_work/, git-ignored)."""
    return {rel(p) for ext in ("csv", "png") for p in BENCH.rglob(f"*.{ext}") if "_work" not in p.parts}


def bench_scripts() -> set[str]:
    return {rel(p) for p in BENCH.rglob("*.py")
            if "_work" not in p.parts and p.name != "__init__.py" and rel(p) not in LIBRARY}


def test_every_run_is_complete(runs):
    names = [r["name"] for r in runs]
    assert len(names) == len(set(names)), "run names must be unique"
    for r in runs:
        for key in ("name", "topic", "script", "description", "outputs", "full_args", "headline"):
            assert key in r, f"{r.get('name')}: no {key}"
        assert r["topic"] in TOPICS, r["name"]
        if r["script"] != "cli.py":
            assert r["script"] == f"bench/{r['topic']}/{Path(r['script']).name}", f"{r['name']}: script outside its topic"
        if r.get("quick"):
            assert "quick_args" in r, f"{r['name']}: in the quick subset without quick_args"
            assert all(o.startswith("{quick}/") for o in r.get("quick_outputs", [])), r["name"]
        for o in r["outputs"]:
            assert o.startswith(f"bench/{r['topic']}/"), f"{r['name']}: {o} outside its topic folder"


def test_every_result_is_a_manifest_output(runs):
    outputs = {o for r in runs for o in r["outputs"]}
    assert sorted(results() - outputs) == [], "CSV/PNG under bench/ that no manifest run writes"


def test_every_manifest_output_exists(runs):
    missing = [o for r in runs for o in r["outputs"] if not (ROOT / o).exists()]
    assert missing == []


def test_every_manifest_script_exists(runs):
    assert [r["script"] for r in runs if not (ROOT / r["script"]).is_file()] == []


def test_every_bench_script_is_in_the_manifest(runs):
    assert sorted(bench_scripts() - {r["script"] for r in runs}) == []


def test_the_quick_subset_is_small(runs):
    quick = [r["name"] for r in runs if r.get("quick")]
    assert 5 <= len(quick) <= 20, quick


def test_the_readme_indexes_every_result(runs):
    readme = (BENCH / "README.md").read_text()
    assert [o for r in runs for o in r["outputs"] if Path(o).name not in readme] == []
    assert len(readme.splitlines()) <= 400


def imports(path: Path) -> set[str]:
    """Top-level module names ``path`` imports (anywhere in it)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module.split(".")[0])
    return out


def path_edits(path: Path) -> list[str]:
    """The string constants of its ``sys.path`` edits (``sys.path.insert(0, str(ROOT / "tests"))`` → ["tests"])."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                and node.func.attr in ("insert", "append") and ast.unparse(node.func.value) == "sys.path"):
            found += [c.value for c in ast.walk(node) if isinstance(c, ast.Constant) and isinstance(c.value, str)]
    return found


def test_benches_never_import_tests():
    tests = {p.stem for p in (ROOT / "tests").glob("*.py")} | {"tests"}
    for f in BENCH.rglob("*.py"):
        if "_work" in f.parts:
            continue
        assert not imports(f) & tests, f"{rel(f)} imports {imports(f) & tests}"
        assert not any("tests" in s for s in path_edits(f)), f"{rel(f)} puts tests/ on sys.path"


def test_tests_never_import_benches():
    benches = {"bench"} | {p.stem for p in BENCH.rglob("*.py") if p.name != "__init__.py"}
    for f in (ROOT / "tests").rglob("*.py"):
        bad = imports(f) & benches
        assert not bad, f"{rel(f)} imports {bad}"
        assert not any("bench" in s for s in path_edits(f)), f"{rel(f)} puts bench/ on sys.path"
