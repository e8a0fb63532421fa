"""The pipeline fuzzer's short run: a few hundred hostile elements against the four services."""

from __future__ import annotations

import pytest

from tests.fuzz.pipeline import run

pytestmark = pytest.mark.integration


@pytest.mark.slow
def test_every_service_survives_hostile_cameras_gyros_and_consumers() -> None:
    tally = run(300, 100, seed=0)
    assert tally.batches == 3 and tally.counts["checks"] == 3
    assert tally.counts["forwarding-checks"] == 3
    assert tally.hostile >= 150, tally.counts
    assert tally.counts["good-frames-decided"] > 0, tally.counts
