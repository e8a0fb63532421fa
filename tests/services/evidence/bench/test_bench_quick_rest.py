"""``framegate bench --quick`` of the scenarios past the transport ones (see ``quick_run``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.services.evidence.bench.quick_run import REST, quick_run


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timeout(960)
def test_quick_run_gives_numbers_for_the_rest_of_the_scenarios(tmp_path: Path) -> None:
    quick_run(tmp_path, list(REST))
