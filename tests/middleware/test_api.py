"""The public surface: one front door, and Zenoh kept behind it."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest
import zenoh

import middleware
from middleware import FramegateError, TransportError
from middleware._session import zenoh_errors

REPO = Path(__file__).resolve().parents[2]


def _isort_style(name: str) -> tuple[int, str]:
    # ruff's RUF022 order: CONSTANTS, then Classes, then functions.
    return (0 if name.isupper() else 1 if name[0].isupper() else 2, name)


def test_all_is_sorted_and_complete() -> None:
    assert middleware.__all__ == sorted(middleware.__all__, key=_isort_style)
    for name in middleware.__all__:
        assert hasattr(middleware, name), name


def test_the_reading_order_names_every_module_that_exists() -> None:
    """The package's docstring is a newcomer's map: a module left out of it, or one it
    names that is gone, sends them the wrong way."""
    doc = middleware.__doc__ or ""
    named = set(re.findall(r"``(_[a-z_]+)``", doc.split("Reading order", 1)[1]))
    modules = {p.stem for p in (REPO / "middleware").glob("_*.py")} - {"__init__"}
    assert modules - named == set(), "not in the reading order"
    assert named - modules == set(), "in the reading order, but no such module"


def test_every_error_is_a_framegate_error() -> None:
    for name in middleware.__all__:
        obj = getattr(middleware, name)
        if isinstance(obj, type) and issubclass(obj, Exception):
            assert issubclass(obj, FramegateError), name


def test_zenoh_errors_map_to_transport_error() -> None:
    with pytest.raises(TransportError, match="doing a thing failed in Zenoh: boom") as info:
        with zenoh_errors("doing a thing"):
            raise zenoh.ZError("boom")
    assert isinstance(info.value.__cause__, zenoh.ZError)


def test_services_never_import_zenoh() -> None:
    # Allowed: the raw-Zenoh benchmark baseline, and the ROS 2 bridge's one module that
    # speaks rmw_zenoh's own keys (a foreign protocol, not framegate's).
    allowed = {"services/cli/bench.py", "services/evidence/bench", "services/nodes/ros2/_link.py"}
    for path in (REPO / "services").rglob("*.py"):
        rel = path.relative_to(REPO).as_posix()
        if any(rel.startswith(a) for a in allowed):
            continue
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            assert not any(n == "zenoh" or n.startswith("zenoh.") for n in names), rel
