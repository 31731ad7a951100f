"""Module layering of fdi_ros, read from the source (every import statement, function-level
ones included): no import cycles; the core imports no plant wing, node, command or rclpy; no
plant is named outside the wings and the commands."""

from __future__ import annotations

import ast
import re
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "fdi_ros"
# Modules that may name a plant (the wings, the CLI's plant commands).
PLANT_NAMING = ("fdi_ros.plants", "fdi_ros.commands")
# Being moved into a wing of their own by other work; not yet part of the generic core.
PENDING_MOVE = ("fdi_ros.core.meanvalue", "fdi_ros.core.measured")


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
            out.add(base)
            out.update(f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in known)
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


def test_no_import_cycles():
    g = _graph()
    # a package importing its own sub-modules (re-exports) is not a cycle by itself
    g = {m: {i for i in deps if not _is_parent_package(m, i)} for m, deps in g.items()}
    assert _cycles(g) == []


def test_core_imports_no_plant_node_command_or_rclpy():
    mods = _modules()
    known = set(mods)
    bad = []
    for m, p in mods.items():
        if not m.startswith("fdi_ros.core") or m.startswith(PENDING_MOVE):
            continue
        for i in _imports(m, p, known):
            if i.startswith(("fdi_ros.plants", "fdi_ros.nodes", "fdi_ros.commands",
                             "fdi_ros.launcher", "fdi_ros.livegraph", "fdi_ros.graphwatch",
                             "rclpy")) or i == "fdi_ros":
                bad.append(f"{m} -> {i}")
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


def test_no_plant_named_outside_wings_and_commands():
    plants = re.compile(r"\b(diesel|turbofan|liu_ice)")
    bad = []
    for m, p in _modules().items():
        if m.startswith(PLANT_NAMING + PENDING_MOVE):
            continue
        bad += [f"{m}:{line}: {s!r}" for line, s in _string_literals(p) if plants.search(s)]
        bad += [f"{m}: imports {i}" for i in _imports(m, p, set(_modules()))
                if plants.search(i)]
    assert bad == []
