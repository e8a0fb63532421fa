"""Hostile input against a live service (a few hundred cases; 10,000 in the benchmark run)."""

from __future__ import annotations

import pytest

from tests.fuzz.run import run

pytestmark = pytest.mark.integration


def test_live_service_survives_hostile_input_and_loses_nothing() -> None:
    tally = run(cases=600, seed=7)
    print(dict(tally.counts))
    assert tally.counts["FAILURE"] == 0, "\n".join(tally.failures)
    assert tally.counts["crashes"] == 0
    for category in (
        "query-rejected",
        "put-accepted",
        "put-rejected",
        "garbage-sent",
        "tokens-sent",
        "forgeries-sent",
        "flow-taken",
    ):
        assert tally.counts[category] > 0, category
