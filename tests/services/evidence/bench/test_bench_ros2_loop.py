"""``ros2-loop`` is opt-in: it runs only when named (minutes, and the approach rendered)."""

from __future__ import annotations

import pytest

from services.evidence.bench import SCENARIO_NAMES, BenchError, BenchOptions
from services.evidence.bench._runner import SCENARIOS


def test_the_loop_scenario_runs_only_when_named() -> None:
    assert "ros2-loop" not in SCENARIO_NAMES
    assert "ros2-loop" not in BenchOptions.create(quick=True).scenarios
    assert BenchOptions.create(("ros2-loop",), quick=True).scenarios == ("ros2-loop",)
    assert "ros2-loop" in SCENARIOS


def test_an_unknown_scenario_names_the_opt_in_ones_too() -> None:
    with pytest.raises(BenchError, match="ros2-loop"):
        BenchOptions.create(("ros2-lop",), quick=True)
