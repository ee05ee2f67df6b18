"""Code rules that keep one place per concept: no module reaches into another's private
(underscore) names, and the face-folder file names are spelled only in pipeline/workspace.py
(in the package and the CLI; a bench script may name its own scratch files)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCES = sorted([*ROOT.glob("pipeline/**/*.py"), ROOT / "cli.py", *ROOT.glob("bench/*.py")])


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
                    and node.value.id in modules):
                found.append(f"{f.relative_to(ROOT)}:{node.lineno} uses {node.value.id}.{node.attr}")
    assert found == []


def test_face_folder_names_are_spelled_once():
    for name in ('"cameras.npz"', '"renderings.npz"', '"face_{', '"face_*'):
        where = [f.relative_to(ROOT).as_posix() for f in SOURCES
                 if "bench" not in f.parts and name in f.read_text()]
        assert where == ["pipeline/workspace.py"], (name, where)
