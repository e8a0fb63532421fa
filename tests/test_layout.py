"""Test files need unique names: tests/ has no __init__.py, so pytest imports them by basename."""

from __future__ import annotations

from collections import Counter

from tests.conftest import REPO


def test_test_module_basenames_are_unique() -> None:
    names = Counter(p.name for p in (REPO / "tests").rglob("test_*.py"))
    assert [n for n, c in names.items() if c > 1] == []
