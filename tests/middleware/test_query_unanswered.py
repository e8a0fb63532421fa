"""A query that reached no one is not an empty buffer.

When a service's lease lapses for a moment (a loaded machine), a query routed at that
instant matches no queryable and Zenoh answers it with nothing, not an error. A service's
answer always ends with its end mark (even an empty one), so ``Node.query`` tells the two
apart: no end mark, and the question is asked once more. The network is replaced by a
stand-in that answers the first asks with nothing: what is tested is the decision, not
Zenoh (``test_query_complete`` drives a real service)."""

from __future__ import annotations

from typing import Any

import pytest

from middleware import BufferInfo, DataObject, NotFoundError, Retention
from middleware._query import Queries
from middleware._timerange import parse_time_range


class _Lapsing(Queries):
    """A node whose first ``lapses`` queries reach no one; the buffer holds ``held``."""

    def __init__(self, held: list[int], lapses: int = 1) -> None:
        self.held, self.lapses, self.asked = held, lapses, 0

    def _start_get(self, target: str, params: dict[str, str], timeout_s: float) -> Any:
        self.asked += 1
        if self.asked <= self.lapses:
            return None  # no reply at all
        if "ts" in params:
            return [t for t in self.held if t == int(params["ts"])]
        if "last" in params:
            return self.held[-int(params["last"]) :]
        return [t for t in self.held if parse_time_range(params["_time"]).contains(t)]

    def _start_exact(
        self, target: str, timestamp_ns: int, timeout_s: float, session: str | None = None
    ) -> Any:
        # The real one collects Zenoh replies on a callback (``Collected``); here the
        # stand-in's answer is the pending fetch, as for every other query.
        return self._start_get(target, {"ts": str(timestamp_ns)}, timeout_s)

    def _answer(
        self,
        target: str,
        replies: Any,
        *,
        most: int | None = None,
        session: str | None = None,
        deadline: float | None = None,
        timeout_s: float = 0.0,
    ) -> tuple[list[DataObject], bool]:
        if replies is None:
            return [], False
        return [DataObject(t, b"", b"<m/>") for t in replies], True

    def service_session(self, service: str) -> str | None:
        return None  # no session answers as the service here: every reply counts

    def buffer_info(self, target: str, *, timeout_s: float = 2.0) -> BufferInfo:
        return BufferInfo(
            "cam", "log", "generic", Retention(), len(self.held), 0,
            min(self.held, default=None), max(self.held, default=None), 0.0, 0, 0, 0,
        )  # fmt: skip


def test_a_query_that_reached_no_one_is_asked_again() -> None:
    node = _Lapsing([10, 20, 30])
    assert [e.timestamp_ns for e in node.latest("cam/log", 2)] == [20, 30]
    assert node.asked == 2


def test_an_answered_empty_range_is_not_asked_again() -> None:
    node = _Lapsing([10, 20, 30], lapses=0)
    assert node.query("cam/log", time_range="[11..19]") == []
    assert node.asked == 1


def test_a_second_query_that_reached_no_one_is_the_answer() -> None:
    node = _Lapsing([10, 20], lapses=5)
    assert node.query("cam/log", last=1) == []
    assert node.asked == 2


def test_a_fetch_started_ahead_that_reached_no_one_is_asked_again() -> None:
    node = _Lapsing([10, 20, 30], lapses=1)
    pending = node._start_exact("cam/log", 20, 1.0)
    assert node._finish_exact("cam/log", 20, pending).timestamp_ns == 20
    assert node.asked == 2


def test_a_fetch_answered_without_its_element_is_not_found_at_once() -> None:
    node = _Lapsing([10, 30], lapses=0)
    pending = node._start_exact("cam/log", 20, 1.0)
    with pytest.raises(NotFoundError):
        node._finish_exact("cam/log", 20, pending)
    assert node.asked == 1
