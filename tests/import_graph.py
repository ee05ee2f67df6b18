"""pipeline's import graph and its layers (docs/ARCHITECTURE.md): every ``pipeline.*`` import of every module, at
the top or inside a function, the layer of each module, the imports that go up a layer, and the circles.

    python tests/import_graph.py [ROOT] [--old]

prints the counts for the tree at ROOT (default: this checkout); ``--old`` reads a tree of before the move of
issue 42 (flat ``pipeline/``), placing each module in the layer of the module it became (docs/relayout_42.py).
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

# Low to high: a module may import its own layer (no circle) and the layers below, never one above.
LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("core", ("pipeline", "pipeline.errors", "pipeline.verbs", "pipeline.schemas", "pipeline.color",
              "pipeline.camera", "pipeline.display", "pipeline.runtime", "pipeline.gl", "pipeline.config",
              "pipeline.metrics", "pipeline.bsh.format", "pipeline.bsh.cones")),
    ("io", ("pipeline.io",)),
    ("libraries", ("pipeline.bsh", "pipeline.expansion.itmo", "pipeline.expansion.splats", "pipeline.expansion.gaussians",
                   "pipeline.expansion.register_photo", "pipeline.expansion.photo_set", "pipeline.gather",
                   "pipeline.relight", "pipeline.scene.geometry", "pipeline.scene.mitsuba_render")),
    ("stages", ("pipeline.expansion", "pipeline.bsh.build_bsh", "pipeline.relight.relight", "pipeline.scene",
                "pipeline.ingest")),
    ("run", ("pipeline.run",)),
    ("measure", ("pipeline.measure",)),
)


def layer_of(module: str, layers=LAYERS) -> int:
    """The layer index of a dotted module name: its longest matching prefix (a package prefix covers its modules)."""
    best, depth = None, -1
    for i, (_, prefixes) in enumerate(layers):
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and p.count(".") > depth:
                best, depth = i, p.count(".")
    if best is None:
        raise KeyError(f"{module}: in no layer of tests/import_graph.py")
    return best


def modules(root: Path) -> dict[str, Path]:
    """Every module of ``root/pipeline`` by its dotted name (a package by its own name)."""
    out = {}
    for f in sorted((root / "pipeline").rglob("*.py")):
        out[".".join(f.relative_to(root).with_suffix("").parts).removesuffix(".__init__")] = f
    return out


def imports(source: str, module: str, is_package: bool, known: set[str]) -> list[tuple[str, int]]:
    """(imported pipeline module, line) for every import in ``source`` of ``module``; ``from p import x`` counts as
    an import of ``p.x`` when that is a module, else of ``p``."""
    pkg = module if is_package else module.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names if a.name.split(".")[0] == "pipeline"]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = pkg.split(".")
                base = ".".join(parts[:len(parts) - node.level + 1])
                mod = f"{base}.{node.module}" if node.module else base
            else:
                mod = node.module or ""
            if mod.split(".")[0] != "pipeline":
                continue
            out += [(f"{mod}.{a.name}" if f"{mod}.{a.name}" in known else mod, node.lineno) for a in node.names]
    return out


def graph(root: Path, rename: dict[str, str] | None = None) -> dict[str, set[str]]:
    """module → the pipeline modules it imports (names after ``rename``: old module → new)."""
    mods = modules(root)
    ren = rename or {}
    g: dict[str, set[str]] = {}
    for m, f in mods.items():
        src = ren.get(m, m)
        g[src] = {ren.get(t, t) for t, _ in imports(f.read_text(), m, f.name == "__init__.py", set(mods))
                  if t in mods and t != m}
    return g


def circles(g: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(g.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    sys.setrecursionlimit(max(10000, sys.getrecursionlimit()))
    for v in sorted(g):
        if v not in index:
            visit(v)
    return out


def upward(g: dict[str, set[str]], layers=LAYERS) -> list[tuple[str, str]]:
    """Every (importer, imported) pair whose imported module is in a higher layer."""
    return sorted((a, b) for a, targets in g.items() for b in targets if layer_of(b, layers) > layer_of(a, layers))


def old_names(root: Path) -> dict[str, str]:
    """Before issue 42's move: old dotted module → new, from docs/relayout_42.py's table."""
    here = Path(__file__).resolve().parents[1] / "docs" / "relayout_42.py"
    table = ast.literal_eval(next(n.value for n in ast.parse(here.read_text()).body
                                  if isinstance(n, ast.Assign) and getattr(n.targets[0], "id", "") == "MOVES"))
    return {f"pipeline.{k}": f"pipeline.{v}" for k, v in table.items()}


def main(argv: list[str]) -> None:
    args = [a for a in argv if not a.startswith("--")]
    root = Path(args[0]) if args else Path(__file__).resolve().parents[1]
    g = graph(root, old_names(root) if "--old" in argv else None)
    # the old tree's gather/io packages and modules that only later got their own layer map onto the new ones
    cs, up = circles(g), upward(g)
    print(f"{root}: {len(g)} modules, {sum(len(v) for v in g.values())} import edges, "
          f"{len(cs)} circles ({sum(len(c) for c in cs)} modules in them), {len(up)} upward imports")
    for c in cs:
        print("  circle:", " ↔ ".join(c))
    for a, b in up:
        print(f"  up: {a} → {b}")


if __name__ == "__main__":
    main(sys.argv[1:])
