"""``framegate bench --quick hostile``: numbers for every attack (the rest of the quick run:
``test_bench_command.py``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.services.evidence.bench.quick_run import quick_run


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timeout(960)
def test_quick_hostile_run_gives_numbers_for_every_attack(tmp_path: Path) -> None:
    # Windows of 2 s instead of the quick run's 10: numbers for every attack are what is
    # checked here, not their goals (the 10 s windows made this two thirds of a quick run).
    quick_run(tmp_path, ["hostile"], "--duration", "2")
