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
