"""The package's front door (its benchmark is a scenario of ``framegate bench``)."""

from __future__ import annotations

import services.lib.quality as quality


def test_all_is_complete_and_sorted_like_ruff_sorts_it() -> None:
    names = quality.__all__
    constants = [n for n in names if n.isupper()]
    assert names == sorted(constants) + sorted(n for n in names if not n.isupper())
    for name in names:
        assert hasattr(quality, name), name
