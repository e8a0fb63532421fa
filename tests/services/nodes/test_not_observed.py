"""Frames a runner never saw: counted once, from whichever source knows them first."""

from __future__ import annotations

from typing import cast

from middleware import Producer
from services.nodes._not_observed import NotObserved


class _Output:
    def __init__(self) -> None:
        self.skipped: dict[str, int] = {}

    def count_skip(self, reason: str, count: int = 1) -> None:
        self.skipped[reason] = self.skipped.get(reason, 0) + count


def test_the_subscriptions_total_and_the_notes_are_one_count_never_added() -> None:
    output = _Output()
    lost = NotObserved(cast(Producer, output))
    lost.total_is(4)  # the queue dropped 4 while the handler ran
    assert output.skipped == {"not-observed": 4}
    lost.carried(3)  # the next notes carry them: already counted
    lost.carried(1)
    assert output.skipped == {"not-observed": 4}
    lost.carried(2)  # a note carries 2 the total was not read for yet
    assert output.skipped == {"not-observed": 6}
    lost.total_is(6)
    lost.total_is(5)  # an older read, never a decrease
    assert output.skipped == {"not-observed": 6}
    lost.total_is(9)
    assert output.skipped == {"not-observed": 9}
