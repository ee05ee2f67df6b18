"""Issue 42's mechanical move, run once at commit e81c08b (kept for the record and for its check): git mv every
module to its package, then rewrite every import, dotted module name and pipeline/ path in the tree by one table.
``python docs/relayout_42.py`` (from the repository root, on the tree before the move) did it;
``python docs/relayout_42.py --check BEFORE/out/demo AFTER/out/demo`` compares two runs of ``make demo``."""
import ast, re, subprocess, sys
from pathlib import Path

MOVES = {  # old module (dotted, under pipeline.) -> new
    "workspace": "io.workspace",
    "itmo": "expansion.itmo", "splats": "expansion.splats", "photo_set": "expansion.photo_set",
    "register_photo": "expansion.register_photo", "expose_match": "expansion.expose_match",
    "render_cubemaps": "expansion.render_cubemaps", "patchmatch": "expansion.patchmatch",
    "reproject": "expansion.reproject", "poisson": "expansion.poisson",
    "bsh_core": "bsh.tree", "bsh_format": "bsh.format", "build_bsh": "bsh.build_bsh",
    "brdf": "gather.brdf",
    "gbuffer": "relight.gbuffer", "relight": "relight.relight",
    "gather.surfels": "relight.surfels", "gather.room_shadow": "relight.room_shadow",
    "gather.self_reflect": "relight.self_reflect", "gather.adaptive": "relight.adaptive",
    "scene_geometry": "scene.geometry", "scene_mitsuba": "scene.mitsuba_render", "make_scene": "scene.make_scene",
    "import_scan": "ingest.import_scan", "merge_brackets": "ingest.merge_brackets",
    "evaluate": "measure.evaluate", "trade": "measure.trade",
    "stages": "run.stages", "plan": "run.plan", "own": "run.own", "place": "run.place", "report": "run.report",
    "info": "run.info", "batch": "run.batch", "executor": "run.executor", "executor_ray": "run.executor_ray",
}
GLSL = {"brdf.glsl": "gather/", "gbuffer.vert.glsl": "relight/", "gbuffer.frag.glsl": "relight/",
        "splat.vert.glsl": "expansion/", "splat.frag.glsl": "expansion/"}
NEW_PKGS = ["expansion", "bsh", "relight", "scene", "ingest", "measure", "run"]
PKG_DOC = {
    "expansion": "The HDR expansion of the LDR cloud (§4): expose-match, render-cubemaps, patchmatch, reproject, poisson, and what they share (inverse tone mapping, point splats, photo sets, photo registration).",
    "bsh": "The bounding sphere hierarchy (§5.1, §5.4): the build-bsh stage, the tree builder and its kernels, the 40-byte node format.",
    "relight": "The relight stage (§5.2–5.4) and what it alone uses: the G-buffer, the object's surfels, the room's shadow, self-reflection, adaptive shading.",
    "scene": "make-scene: the synthetic rooms, their geometry and their Mitsuba 3 ground truth.",
    "ingest": "Bringing user data in: import (scans in any format), merge-brackets (LDR brackets into an HDR photo).",
    "measure": "Measuring the pipeline: evaluate (Table 2) and trade (what each second buys, the presets).",
    "run": "Running the pipeline: the stage registry and runner, the planner, your own room (own, place), the report, info, batches and executors.",
}
ROOT = Path.cwd()
OLD = {f"pipeline.{k}": f"pipeline.{v}" for k, v in MOVES.items()}
ALL_OLD = {".".join(f.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
           for f in (ROOT / "pipeline").rglob("*.py")}


def new_name(mod: str) -> str:
    """The new dotted name of an old dotted name (a module or an attribute path under one)."""
    parts = mod.split(".")
    for i in range(len(parts), 0, -1):
        head = ".".join(parts[:i])
        if head in OLD:
            return ".".join([OLD[head], *parts[i:]])
    return mod


def module_of(path: Path, root: Path = ROOT) -> str:
    return ".".join(path.relative_to(root).with_suffix("").parts).removesuffix(".__init__")


def rel(frm_pkg: str, target: str) -> tuple[int, str]:
    """(level, module) of a relative import of ``target`` from package ``frm_pkg``."""
    a, b = frm_pkg.split("."), target.split(".")
    n = 0
    while n < min(len(a), len(b)) and a[n] == b[n]:
        n += 1
    return len(a) - n + 1, ".".join(b[n:])


def fmt_from(level: int, mod: str, names: list[str]) -> str:
    return f"from {'.' * level}{mod} import {', '.join(names)}"


def rewrite_imports(src: str, old_mod: str | None, new_mod: str | None, is_pkg: bool) -> str:
    """Rewrite the import statements of one file (``old_mod``: its old dotted name when it is in pipeline/)."""
    tree = ast.parse(src)
    lines = src.splitlines(keepends=True)
    edits = []
    old_pkg = None if old_mod is None else (old_mod if is_pkg else old_mod.rpartition(".")[0])
    new_pkg = None if new_mod is None else (new_mod if is_pkg else new_mod.rpartition(".")[0])
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                parts = old_pkg.split(".")
                base = ".".join(parts[:len(parts) - node.level + 1])
                mod = f"{base}.{node.module}" if node.module else base
            else:
                mod = node.module or ""
            if not (mod == "pipeline" or mod.startswith("pipeline.")):
                continue
            groups: dict[str, list[str]] = {}
            for a in node.names:
                full = f"{mod}.{a.name}"
                if full in ALL_OLD:             # a module imported by name: `from . import reproject`
                    nf = new_name(full)
                    pkg, _, leaf = nf.rpartition(".")
                    alias = a.asname or (a.name if leaf != a.name else None)
                    groups.setdefault(pkg, []).append(f"{leaf} as {alias}" if alias else leaf)
                else:
                    groups.setdefault(new_name(mod), []).append(f"{a.name} as {a.asname}" if a.asname else a.name)
            stmts = []
            for tgt, names in groups.items():
                if new_pkg is not None and node.level:       # stay relative inside the package
                    lv, m = rel(new_pkg, tgt)
                    if lv == 1 and m == "" :
                        stmts.append(fmt_from(1, "", names))
                    else:
                        stmts.append(fmt_from(lv, m, names))
                else:
                    stmts.append(fmt_from(0, tgt, names))
            edits.append((node, stmts))
        elif isinstance(node, ast.Import):
            if not any(a.name == "pipeline" or a.name.startswith("pipeline.") for a in node.names):
                continue
            names = []
            for a in node.names:
                nn = new_name(a.name) if a.name.startswith("pipeline") else a.name
                names.append(f"{nn} as {a.asname}" if a.asname else nn)
            edits.append((node, ["import " + ", ".join(names)]))
    lines = [rewrite_text(l) if i not in {j for n, _ in edits for j in range(n.lineno - 1, n.end_lineno)} else l
             for i, l in enumerate(lines)]
    for node, stmts in sorted(edits, key=lambda e: (e[0].lineno, e[0].col_offset), reverse=True):
        l0, l1 = node.lineno - 1, node.end_lineno - 1
        head = lines[l0][:node.col_offset]
        tail = rewrite_text(lines[l1][node.end_col_offset:])
        indent = head if head.strip() == "" else None
        if indent is not None:
            text = head + ("\n" + indent).join(stmts) + tail
        else:                                  # `try: from x import y` on one line etc.
            assert len(stmts) == 1, (node.lineno, stmts)
            text = head + stmts[0] + tail
        lines[l0:l1 + 1] = [text]
    return "".join(lines)


DOTTED = re.compile(r"\bpipeline\.(" + "|".join(sorted((re.escape(k) for k in MOVES), key=len, reverse=True)) + r")(?![\w])")
PATHS = {f"pipeline/{k.replace('.', '/')}.py": f"pipeline/{v.replace('.', '/')}.py" for k, v in MOVES.items()}
PATHS.update({f"pipeline/{g}": f"pipeline/{d}{g}" for g, d in GLSL.items()})
PATHS["pipeline/templates/"] = "pipeline/run/templates/"
PATHRE = re.compile("|".join(re.escape(k) for k in sorted(PATHS, key=len, reverse=True)))


def rewrite_text(src: str) -> str:
    src = DOTTED.sub(lambda m: new_name("pipeline." + m.group(1)), src)
    return PATHRE.sub(lambda m: PATHS[m.group(0)], src)


def main() -> None:
    tracked = subprocess.run(["git", "ls-files"], capture_output=True, text=True, check=True).stdout.split()
    py_old = {f: module_of(ROOT / f) for f in tracked if f.startswith("pipeline/") and f.endswith(".py")}
    # 1. imports (before moving: the old module names resolve relative imports)
    new_src = {}
    for f in tracked:
        if not f.endswith(".py"):
            continue
        src = (ROOT / f).read_text()
        old_mod = py_old.get(f)
        new_mod = new_name(old_mod) if old_mod else None
        new_src[f] = rewrite_imports(src, old_mod, new_mod, f.endswith("__init__.py"))
    for f, s in new_src.items():
        (ROOT / f).write_text(s)
    # 2. dotted names and paths in every other text file (.py files: done with their imports)
    for f in tracked:
        p = ROOT / f
        if p.suffix in (".md", ".toml", ".txt", ".glsl", ".j2", ".cfg", ".sh", ".html") or p.name in ("Makefile", "run"):
            pass
        else:
            continue
        if p.suffix in (".py", ".md", ".toml", ".txt", ".glsl", ".j2", ".cfg") or p.name in ("Makefile", "run"):
            try:
                s = p.read_text()
            except UnicodeDecodeError:
                continue
            t = rewrite_text(s)
            if t != s:
                p.write_text(t)
    # 3. git mv
    for pkg in NEW_PKGS:
        d = ROOT / "pipeline" / pkg
        d.mkdir(exist_ok=True)
        init = d / "__init__.py"
        if not init.exists():
            init.write_text(f'"""{PKG_DOC[pkg]}"""\n')
            subprocess.run(["git", "add", str(init)], check=True)
    for k, v in MOVES.items():
        subprocess.run(["git", "mv", f"pipeline/{k.replace('.', '/')}.py", f"pipeline/{v.replace('.', '/')}.py"], check=True)
    for g, d in GLSL.items():
        subprocess.run(["git", "mv", f"pipeline/{g}", f"pipeline/{d}{g}"], check=True)
    subprocess.run(["git", "mv", "pipeline/templates", "pipeline/run/templates"], check=True)


TIMING = re.compile(r"time|timing|second|_s$|^s$|wall|cpu|elapsed|duration|date|load|steps|when|started|finished|"
                    r"pid|host|cache", re.I)


def check(before: Path, after: Path) -> int:
    """The move's check: every data file of two runs' workspaces byte-identical, every JSON report identical but for
    its timing keys. Prints each difference; returns how many."""
    import hashlib
    import json

    def norm(x):
        if isinstance(x, dict):
            return {k: norm(v) for k, v in x.items() if not TIMING.search(k)}
        return [norm(v) for v in x] if isinstance(x, list) else x

    files = sorted({f.relative_to(before) for f in before.rglob("*") if f.is_file()}
                   | {f.relative_to(after) for f in after.rglob("*") if f.is_file()})
    bad = same = 0
    for rel in files:
        a, b = before / rel, after / rel
        if not (a.exists() and b.exists()):
            print("only in one:", rel); bad += 1
        elif rel.suffix == ".json":
            ok = norm(json.loads(a.read_text())) == norm(json.loads(b.read_text()))
            print(("same but timings: " if ok else "DIFFERENT: ") + str(rel)); bad += not ok
        elif rel.suffix in (".html", ".err", ".log") or rel.name.startswith("."):
            print("not compared (timings, log lines):", rel)
        elif hashlib.sha256(a.read_bytes()).digest() != hashlib.sha256(b.read_bytes()).digest():
            print("DIFFERENT:", rel); bad += 1
        else:
            same += 1
    print(f"{same} data files byte-identical, {bad} differences")
    return bad


if __name__ == "__main__":
    if sys.argv[1:2] == ["--check"]:
        sys.exit(1 if check(Path(sys.argv[2]), Path(sys.argv[3])) else 0)
    main()
