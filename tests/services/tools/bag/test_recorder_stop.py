"""How a recorder ends on time: past its fetch deadline it asks nothing more, and what the
queued notifications say was stored up to the stop but never fetched is counted (evicted,
lost in transport), never left out of the account.

The recorder's bookkeeping is driven directly, with a stand-in for the subscription that
holds queued notifications (no network: what is tested is the counting)."""

from __future__ import annotations

import threading
import time
from typing import Any

from middleware import DataObject, Notification
from services.tools.bag import Progress, Recorder, at_start
from services.tools.bag._recorder import BACKFILL_TRIES, STOP_SLACK_S, TAIL_FLOOR_S

STOP_NS = 1_000


class _Queue:
    """A subscription's queue of notifications, as ``Recorder`` reads it at the stop."""

    name = "cam/log"
    missed_total = 0
    producer_session = None

    def __init__(self, *seq_and_t: tuple[int, int]) -> None:
        self.notes = [Notification("cam", "log", t, seq) for seq, t in seq_and_t]

    def take_many(self, max_count: int, *, timeout_s: float | None = None) -> list[Notification]:
        taken, self.notes = self.notes[:max_count], self.notes[max_count:]
        return taken

    def fetch(self, *_: Any, **__: Any) -> Any:
        raise AssertionError("fetched past the deadline")


class _NoNetwork:
    """A node that must not be asked (the deadline has passed)."""

    def __getattr__(self, name: str) -> Any:
        raise AssertionError(f"asked the network ({name}) past the deadline")


def _recorder(sub: _Queue, *, anchor_seq: int, last_ns: int | None) -> Recorder:
    recorder = Recorder(
        _NoNetwork(),  # type: ignore[arg-type]
        sub,  # type: ignore[arg-type]
        None,  # type: ignore[arg-type]
        Progress("cam/log", "generic"),
        threading.Event(),
        None,
    )
    recorder.stop_ns = STOP_NS
    recorder.deadline = time.monotonic() - 1.0  # passed
    recorder._anchor_seq = anchor_seq
    recorder._last_ns = last_ns
    return recorder


def test_elements_notified_up_to_the_stop_and_not_fetched_are_counted() -> None:
    # Handled up to seq 10 (t 100), seq 11 backfilled (t 110); 12-15 queued, stamped before
    # the stop; 16 after it (not this recording's).
    sub = _Queue((12, 120), (13, 130), (14, 140), (15, 150), (16, STOP_NS + 1))
    recorder = _recorder(sub, anchor_seq=10, last_ns=110)
    recorder._since_anchor = [110]
    assert recorder._unfetched_at_stop() == 4


def test_a_gap_no_queued_notification_names_is_counted_by_sequence_numbers() -> None:
    # Only seq 15 is queued, yet 12-14 were stored before it and never fetched either.
    recorder = _recorder(_Queue((15, 150)), anchor_seq=10, last_ns=110)
    recorder._since_anchor = [110]
    assert recorder._unfetched_at_stop() == 4


def test_after_a_producer_restart_the_queued_notifications_are_what_is_known() -> None:
    recorder = _recorder(_Queue((1, 120), (2, 130)), anchor_seq=10, last_ns=110)
    assert recorder._unfetched_at_stop() == 2


def test_nothing_queued_is_nothing_counted() -> None:
    assert _recorder(_Queue(), anchor_seq=10, last_ns=110)._unfetched_at_stop() == 0


def test_past_the_deadline_nothing_is_asked_and_a_notified_element_is_counted_lost() -> None:
    sub = _Queue()
    recorder = _recorder(sub, anchor_seq=0, last_ns=None)
    recorder._backfill(STOP_NS, newest=5)  # would query: it must not
    recorder._on_notification(Notification("cam", "log", 500, 1))  # would fetch: it must not
    assert recorder.progress.evicted == 1


class _LapsingNode:
    """A producer that reaches no one for its first ``lapses`` queries (its lease lapsed):
    the query comes back empty, as Zenoh returns a query that matched no queryable."""

    def __init__(self, lapses: int, held: list[int]) -> None:
        self.lapses, self.held, self.asked = lapses, held, 0

    def query(self, target: str, **_: Any) -> list[Any]:
        self.asked += 1
        if self.asked <= self.lapses:
            return []
        return [DataObject(t, b"", b"<m/>") for t in self.held]


class _Written:
    """The write queue: what the recorder handed over."""

    def __init__(self) -> None:
        self.stamps: list[int] = []

    def put(self, progress: Progress, element: DataObject) -> bool:
        self.stamps.append(element.timestamp_ns)
        return True


def _backfilling(node: _LapsingNode) -> tuple[Recorder, _Written]:
    written = _Written()
    recorder = Recorder(
        node,  # type: ignore[arg-type]
        _Queue(),  # type: ignore[arg-type]
        written,  # type: ignore[arg-type]
        Progress("cam/log", "generic"),
        threading.Event(),
        None,
    )
    recorder.stop_ns, recorder.deadline = STOP_NS, time.monotonic() + 60.0
    recorder._anchor_seq, recorder._last_ns = 10, 100
    return recorder, written


def test_an_empty_answer_to_a_gap_the_sequence_numbers_count_is_asked_again() -> None:
    # Seq 14 arrives after 10: three elements lie between; the first answer is empty (the
    # producer reached no one), the second holds them. Nothing is counted evicted.
    node = _LapsingNode(lapses=1, held=[110, 120, 130])
    recorder, written = _backfilling(node)
    recorder._backfill(139, newest=3)
    assert node.asked == 2
    assert written.stamps == [110, 120, 130]
    assert recorder.progress.evicted == 0


def test_a_gap_never_answered_is_asked_a_bounded_number_of_times() -> None:
    node = _LapsingNode(lapses=1_000, held=[])
    recorder, written = _backfilling(node)
    recorder._backfill(139, newest=3)
    assert node.asked == BACKFILL_TRIES
    assert written.stamps == []


def test_the_tail_up_to_the_stop_is_asked_even_by_a_recorder_starved_past_its_deadline() -> None:
    # A starved recorder reaches its final backfill after the deadline: unasked, the tail
    # would be counted only as far as the (lagging) notifications tell.
    node = _LapsingNode(lapses=0, held=[110, 120])
    recorder, written = _backfilling(node)
    recorder.deadline = time.monotonic() - 1.0
    recorder._backfill(STOP_NS, timeout_s=STOP_SLACK_S, floor_s=TAIL_FLOOR_S)
    assert written.stamps == [110, 120]
    recorder._backfill(STOP_NS, timeout_s=STOP_SLACK_S)  # any other ask: none past it
    assert node.asked == 1


class _Holding:
    """A producer holding elements stamped ``held``: range queries answer from them, and a
    notified element is fetched."""

    name = "cam/log"
    missed_total = 0
    producer_session = None

    def __init__(self, held: list[int]) -> None:
        self.held = held

    def query(self, target: str, *, time_range: Any, last: int | None = None, **_: Any) -> Any:
        start = time_range.start_ns if time_range.start_ns is not None else -1
        end = time_range.end_ns if time_range.end_ns is not None else 1 << 62
        found = [DataObject(t, b"", b"<m/>") for t in self.held if start <= t <= end]
        return found[-last:] if last else found

    def fetch(self, note: Notification, **_: Any) -> DataObject:
        return DataObject(note.timestamp_ns, b"", b"<m/>")


def test_what_a_lapse_stored_and_the_buffer_no_longer_holds_is_counted_evicted() -> None:
    # Handled up to seq 50 (t 500); the registration lapsed, 105 elements were stored
    # meanwhile (t 510..1550), the buffer still holds the newest 63 of them; the new
    # registration's first notification (seq 1, t 1560) carries missed=105.
    held = list(range(930, 1551, 10))
    node = _Holding(held)
    written = _Written()
    recorder = Recorder(
        node,  # type: ignore[arg-type]
        node,  # type: ignore[arg-type]
        written,  # type: ignore[arg-type]
        Progress("cam/log", "generic"),
        threading.Event(),
        None,
    )
    recorder.deadline = time.monotonic() + 60.0
    recorder._anchor_seq, recorder._last_ns = 50, 500
    recorder._on_notification(Notification("cam", "log", 1560, 1, missed=105))
    assert written.stamps == [*held, 1560]
    assert recorder.progress.backfilled == len(held) == 63
    assert recorder.progress.evicted == 105 - 63


def test_at_start_asks_right_after_the_element_found_before_the_start() -> None:
    # The newest element at or before the start is t 849 (a gyro batch stored between the
    # two queries brings 850..870, stamped on both sides of the start 857): the second query
    # reaches back to 850, so no gap opens behind 849.
    node = _Holding(list(range(800, 850)))
    asked: list[Any] = []
    original = node.query

    def query(target: str, **kwargs: Any) -> Any:
        asked.append(kwargs["time_range"])
        if len(asked) == 2:
            node.held = list(range(800, 871))  # the batch arrived between the two queries
        return original(target, **kwargs)

    node.query = query  # type: ignore[method-assign]
    found = at_start(node, "cam/log", started_ns=857)  # type: ignore[arg-type]
    assert [e.timestamp_ns for e in found] == list(range(849, 871))
