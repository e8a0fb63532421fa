"""A query that reached no one is not an empty buffer.

When a service's lease lapses for a moment (a loaded machine), a query routed at that
instant matches no queryable and Zenoh answers it with nothing, not an error. ``Node.query``
then looks at the buffer's description: if the buffer holds what was asked for, it asks once
more. The network is replaced by a stand-in that answers the first ask with nothing: what
is tested is the decision, not Zenoh."""

from __future__ import annotations

from typing import Any

import pytest

from middleware import BufferInfo, DataObject, Retention, TimeRange
from middleware._query import Queries
from middleware._timerange import parse_time_range


class _Lapsing(Queries):
    """A node whose first ``lapses`` queries reach no one; the buffer holds ``held``."""

    def __init__(self, held: list[int], lapses: int = 1) -> None:
        self.held, self.lapses, self.asked = held, lapses, 0

    def _start_get(self, target: str, params: dict[str, str], timeout_s: float) -> Any:
        self.asked += 1
        if self.asked <= self.lapses:
            return []
        if "ts" in params:
            return [t for t in self.held if t == int(params["ts"])]
        if "last" in params:
            return self.held[-int(params["last"]) :]
        return [t for t in self.held if parse_time_range(params["_time"]).contains(t)]

    def _collect(self, target: str, replies: Any) -> list[DataObject]:
        return [DataObject(t, b"", b"<m/>") for t in replies]

    def buffer_info(self, target: str, *, timeout_s: float = 2.0) -> BufferInfo:
        return BufferInfo(
            "cam", "log", "generic", Retention(), len(self.held), 0,
            min(self.held, default=None), max(self.held, default=None), 0.0, 0, 0, 0,
        )  # fmt: skip


def test_a_lapsed_answer_from_a_buffer_that_holds_elements_is_asked_again() -> None:
    node = _Lapsing([10, 20, 30])
    assert [e.timestamp_ns for e in node.latest("cam/log", 2)] == [20, 30]
    assert node.asked == 2


@pytest.mark.parametrize(
    ("ask", "again"),
    [
        ({"time_range": TimeRange(15, 25)}, True),  # inside the held span
        ({"time_range": TimeRange(31, None)}, False),  # after the newest: truly empty
        ({"time_range": TimeRange(None, 9)}, False),  # before the oldest
        ({"time_range": "[0..5]"}, False),
    ],
)
def test_only_a_question_the_held_span_could_answer_is_asked_again(
    ask: dict[str, Any], again: bool
) -> None:
    node = _Lapsing([10, 20, 30])
    node.query("cam/log", **ask)
    assert node.asked == (2 if again else 1)


def test_an_empty_buffer_is_asked_once() -> None:
    node = _Lapsing([])
    assert node.query("cam/log", last=3) == []
    assert node.asked == 1


def test_a_second_empty_answer_is_the_answer() -> None:
    node = _Lapsing([10, 20], lapses=5)
    assert node.query("cam/log", last=1) == []
    assert node.asked == 2


def test_a_fetch_started_ahead_that_reached_no_one_is_asked_again() -> None:
    node = _Lapsing([10, 20, 30], lapses=1)
    pending = node._start_exact("cam/log", 20, 1.0)
    assert node._finish_exact("cam/log", 20, pending).timestamp_ns == 20
    assert node.asked == 2
