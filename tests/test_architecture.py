"""The layout drawn in ``services/__init__.py`` holds: imports only point down, no cycles."""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.conftest import REPO

# Lower layers come later; a module may import its own layer or any later one.
LAYERS = (
    "services.cli",
    "services.evidence",
    "services.tools",
    "services.launch",
    "services.nodes",
    "services.lib",
    "middleware",
    "schemas",
)


def _modules() -> dict[str, Path]:
    found: dict[str, Path] = {}
    for top in ("middleware", "services", "schemas"):
        for path in (REPO / top).rglob("*.py"):
            parts = list(path.relative_to(REPO).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            found[".".join(parts)] = path
    return found


MODULES = _modules()


def _imports(module: str, path: Path) -> Iterator[str]:
    """Every project module ``module`` imports, also inside functions (lazy imports count)."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                stem = ".".join(base + ([node.module] if node.module else []))
            else:
                stem = node.module or ""
            # `from pkg import mod` imports the submodule when there is one.
            names = [f"{stem}.{a.name}" for a in node.names if f"{stem}.{a.name}" in MODULES]
            names = names or [stem]
        else:
            continue
        for name in names:
            while name and name not in MODULES:
                name = name.rpartition(".")[0]
            if name:
                yield name


GRAPH = {m: set(_imports(m, p)) - {m} for m, p in MODULES.items()}


def _layer(module: str) -> int:
    for index, prefix in enumerate(LAYERS):
        if module == prefix or module.startswith(prefix + "."):
            return index
    return -1  # `services` itself: the map, imports nothing


@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_only_point_down(module: str) -> None:
    upward = sorted(i for i in GRAPH[module] if _layer(i) < _layer(module))
    assert upward == [], f"{module} imports a layer above it: {upward} (see services/__init__.py)"


def test_middleware_imports_nothing_of_services() -> None:
    offenders = {m: sorted(i for i in GRAPH[m] if i.startswith("services")) for m in MODULES}
    assert {m: i for m, i in offenders.items() if m.startswith("middleware") and i} == {}


def test_there_are_no_import_cycles() -> None:
    # Tarjan's strongly connected components; a component of more than one module is a cycle.
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for nxt in GRAPH[node]:
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                top = stack.pop()
                component.append(top)
                if top == node:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for node in sorted(GRAPH):
        if node not in index:
            visit(node)
    assert cycles == []
