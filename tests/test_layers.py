"""Module layering of fdi_ros, read from the source (every import statement, function-level
ones included, and every module named in a string to be imported by name): no import cycles;
the core imports no plant wing, node, command or rclpy, not even through other modules; no
plant is named in code (identifiers or strings, any case) outside the wings and the commands;
every node file is thin (at most 150 lines)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "fdi_ros"
# Modules that may name a plant (the wings, the CLI's plant commands).
PLANT_NAMING = ("fdi_ros.plants", "fdi_ros.commands")
NODE_MAX_LINES = 150


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PKG.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in PKG.rglob("*.py")}


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """fdi_ros modules (and the external roots) imported anywhere in ``path``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    is_pkg = path.name == "__init__.py"
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                pkg = name.split(".")
                pkg = pkg if is_pkg else pkg[:-1]
                pkg = pkg[:len(pkg) - node.level + 1]
                base = ".".join(pkg + ([base] if base else []))
            subs = {f"{base}.{a.name}" for a in node.names} & known
            # "from pkg import mod" depends on pkg.mod (and on pkg only for its other names)
            out.update(subs if len(subs) == len(node.names) else subs | {base})
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) \
                and node.value.partition(":")[0] in known:
            out.add(node.value.partition(":")[0])  # imported by name ("module" or "module:attr")
    # "import a.b.c" depends on a.b.c; keep the longest known module name of each import
    resolved = set()
    for imp in out:
        parts = imp.split(".")
        while parts and ".".join(parts) not in known:
            parts.pop()
        resolved.add(".".join(parts) if parts else imp.split(".")[0])
    return resolved - {name}


def _graph() -> dict[str, set[str]]:
    mods = _modules()
    known = set(mods)
    return {m: {i for i in _imports(m, p, known) if i in known} for m, p in mods.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _is_parent_package(a: str, b: str) -> bool:
    return b.startswith(a + ".")


def test_cycle_finder_finds_a_planted_cycle():
    g = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycles(g) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_import_reader_sees_function_level_imports(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("from fdi_ros import bag\n\n\ndef f():\n    from fdi_ros.plants import diesel\n"
                 "    import rclpy.node\n    return {'k': 'fdi_ros.nodes.x:make'}\n")
    got = _imports("fdi_ros.core.m", f, {"fdi_ros", "fdi_ros.bag", "fdi_ros.plants",
                                          "fdi_ros.plants.diesel", "fdi_ros.nodes.x"})
    assert got == {"fdi_ros.bag", "fdi_ros.plants.diesel", "rclpy", "fdi_ros.nodes.x"}


def test_no_import_cycles():
    g = _graph()
    # a package importing its own sub-modules (re-exports) is not a cycle by itself
    g = {m: {i for i in deps if not _is_parent_package(m, i)} for m, deps in g.items()}
    assert _cycles(g) == []


def test_core_imports_no_plant_node_command_or_rclpy():
    """Directly or through any module it imports (e.g. the bag reader)."""
    mods = _modules()
    known = set(mods)
    direct = {m: _imports(m, p, known) for m, p in mods.items()}
    bad = []
    for m in mods:
        if not m.startswith("fdi_ros.core"):
            continue
        seen: set[str] = set()
        todo = [m]
        while todo:
            for i in direct.get(todo.pop(), ()):
                if i not in seen:
                    seen.add(i)
                    todo.append(i)
        bad += [f"{m} -> {i}" for i in sorted(seen)
                if i.startswith(("fdi_ros.plants", "fdi_ros.nodes", "fdi_ros.commands",
                                 "fdi_ros.launcher", "fdi_ros.livegraph",
                                 "fdi_ros.graphwatch", "fdi_ros.cli", "rclpy"))
                or i == "fdi_ros"]
    assert bad == []


def test_plants_import_no_command_or_node():
    """Wings (bank builders, identification) stand below the CLI and the nodes."""
    mods = _modules()
    known = set(mods)
    bad = [f"{m} -> {i}" for m, p in mods.items() if m.startswith("fdi_ros.plants")
           for i in _imports(m, p, known)
           if i.startswith(("fdi_ros.commands", "fdi_ros.nodes", "fdi_ros.cli"))]
    assert bad == []


def _string_literals(path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text())
    docs = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = getattr(node, "body", [])
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value,
                                                                      ast.Constant):
                docs.add(id(body[0].value))
    return [(n.lineno, n.value) for n in ast.walk(tree)
            if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs]


def _identifiers(path: Path) -> list[tuple[int, str]]:
    """Names the code defines or uses: variables, attributes, functions, classes, arguments,
    keywords, import aliases."""
    out = []
    for n in ast.walk(ast.parse(path.read_text())):
        if isinstance(n, ast.Name):
            out.append((n.lineno, n.id))
        elif isinstance(n, ast.Attribute):
            out.append((n.lineno, n.attr))
        elif isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            out.append((n.lineno, n.name))
        elif isinstance(n, ast.arg):
            out.append((n.lineno, n.arg))
        elif isinstance(n, ast.keyword) and n.arg:
            out.append((n.value.lineno, n.arg))
        elif isinstance(n, ast.alias):
            out.append((n.lineno, n.asname or n.name))
    return out


def _plant_pattern() -> re.Pattern[str]:
    """Every plant of the registry (a new wing is covered without editing this test)."""
    from fdi_ros.plants import TABLE

    names = sorted(TABLE, key=len, reverse=True)
    assert {"diesel", "turbofan"} <= set(names)
    return re.compile(r"(?<![a-z0-9])(" + "|".join(map(re.escape, names)) + ")", re.I)


def test_plant_pattern_finds_names_in_any_case():
    plants = _plant_pattern()
    for s in ("diesel", "DieselParams", "load_turbofan", "LIU_ICE_X", "a.diesel.b"):
        assert plants.search(s), s
    for s in ("tank", "fdi_ros.core.supervisor", "fuel_diff"):
        assert not plants.search(s), s


def test_no_plant_named_outside_wings_and_commands():
    plants = _plant_pattern()
    bad = []
    for m, p in _modules().items():
        if m.startswith(PLANT_NAMING):
            continue
        bad += [f"{m}:{line}: {s!r}" for line, s in _string_literals(p) if plants.search(s)]
        bad += [f"{m}:{line}: name {s}" for line, s in _identifiers(p) if plants.search(s)]
        bad += [f"{m}: imports {i}" for i in _imports(m, p, set(_modules()))
                if plants.search(i)]
    assert bad == []


def test_nodes_are_thin():
    long = {p.name: n for p in (PKG / "nodes").glob("*.py")
            if (n := len(p.read_text().splitlines())) > NODE_MAX_LINES}
    assert long == {}, f"node files over {NODE_MAX_LINES} lines: {long}"
