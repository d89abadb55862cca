"""The library's packages depend one way: io at the bottom, report on top, the demo beside.

Every ``import`` in ``georeg/`` (module level or inside a function) is read with ``ast``; a module
may import from its own package or from one listed below it, never from one above.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "georeg"
ORDER = ["io", "map", "index", "register", "frames", "products", "trajectory", "export", "report", "demo"]


def _imports(path: Path) -> list[tuple[int, str]]:
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            out += [(node.lineno, n) for n in names if n.startswith("georeg.")]
        elif isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names if a.name.startswith("georeg.")]
    return out


def _package(dotted: str) -> str | None:
    parts = dotted.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in ORDER else None


MODULES = sorted(p for p in PKG.rglob("*.py") if p.parent != PKG)


def test_every_module_lives_in_a_stage_package() -> None:
    flat = sorted(p.name for p in PKG.glob("*.py") if p.name != "__init__.py")
    assert flat == [], f"modules outside a stage package: {flat}"
    assert {p.relative_to(PKG).parts[0] for p in MODULES} == set(ORDER)


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PKG)))
def test_imports_point_down(path: Path) -> None:
    own = path.relative_to(PKG).parts[0]
    bad = [
        f"{path.relative_to(PKG.parent)}:{line} imports {name}"
        for line, name in _imports(path)
        if (pkg := _package(name)) and ORDER.index(pkg) > ORDER.index(own)
    ]
    assert not bad, "\n".join(bad)


def test_no_module_outside_demo_imports_the_demo() -> None:
    users = [
        str(p.relative_to(PKG))
        for p in MODULES
        if p.relative_to(PKG).parts[0] != "demo" and any(_package(n) == "demo" for _, n in _imports(p))
    ]
    assert users == []


def _module_name(path: Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def _import_graph(package: str) -> dict[str, set[str]]:
    """Module -> the modules of the same package it imports (module level or in a function;
    ``from georeg.x import y`` counts as importing ``georeg.x.y`` when that is a module)."""
    mods = {_module_name(p): p for p in MODULES if p.relative_to(PKG).parts[0] == package}
    graph: dict[str, set[str]] = {}
    for name, path in mods.items():
        deps = {n if n in mods else n.rsplit(".", 1)[0] for _, n in _imports(path)}
        graph[name] = {d for d in deps if d in mods and d != name and not d.endswith(package)}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of ``graph`` (a list of modules, the first repeated at the end) or None."""
    state: dict[str, int] = {}  # 1 = on the stack, 2 = done
    stack: list[str] = []

    def visit(n: str) -> list[str] | None:
        state[n] = 1
        stack.append(n)
        for d in sorted(graph.get(n, ())):
            if state.get(d) == 1:
                return stack[stack.index(d) :] + [d]
            if d not in state and (c := visit(d)):
                return c
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state and (c := visit(n)):
            return c
    return None


def test_find_cycle_sees_a_cycle_through_a_lazy_import() -> None:
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


@pytest.mark.parametrize("package", ORDER)
def test_no_import_cycle_inside_a_package(package: str) -> None:
    """Within a package, imports form no circle (a lazy import inside a function counts: a
    module that calls back up into its caller is a side path, not a layer)."""
    cycle = find_cycle(_import_graph(package))
    assert cycle is None, " -> ".join(cycle or [])
