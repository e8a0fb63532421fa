"""When a stage may remove what it put: only for a step of the source's own clock."""

from __future__ import annotations

import pytest

from services.lib.rewind import SourceClock, rewind_after

S = 1_000_000_000
MS = 1_000_000
HORIZON = 10 * S
NEWEST = 1_000 * S


def _clock(offset_ns: int, pid: int = 1, steps: int | None = 0, error_ns: int = MS) -> SourceClock:
    return SourceClock("host", pid, steps, offset_ns, error_ns)


def test_a_camera_whose_old_clock_ran_ahead_is_rewound_to_its_new_start() -> None:
    # A rogue (or a camera) 9 s ahead, then the real camera: 4 s back from the newest put.
    check = rewind_after(NEWEST, NEWEST - 4 * S, _clock(9 * S), _clock(0, pid=2), HORIZON)
    assert check.after_ns == NEWEST - 4 * S - 1
    # Slow answers on a loaded machine (250 ms round trips) do not hide a real step.
    slow = _clock(0, pid=2, error_ns=125 * MS)
    check = rewind_after(NEWEST, NEWEST - 4 * S, _clock(9 * S, error_ns=125 * MS), slow, HORIZON)
    assert check.after_ns == NEWEST - 4 * S - 1


@pytest.mark.parametrize(
    ("first_ns", "before", "after", "why"),
    [
        # A rogue's single stale put: another process, but its clock is right.
        (NEWEST - 3600 * S, _clock(0), _clock(0, pid=2), "not-a-clock-step"),
        (1, _clock(0), _clock(0, pid=2), "not-a-clock-step"),
        # A rogue that answers its clock query slowly (0.9 s round trip: error 0.45 s) and
        # puts one frame 0.3 s back: a step its clock's error could explain, not proves.
        (
            NEWEST - 300 * MS,
            _clock(20 * MS),
            _clock(0, pid=2, error_ns=450 * MS),
            "not-a-clock-step",
        ),
        # A camera restarted with its clock 5 s behind: the frames before were right.
        (NEWEST - 3 * S, _clock(0), _clock(-5 * S, pid=2), "new-clock-further-off"),
        # The same process and clock: its stamps never go back, one element proves nothing.
        (NEWEST - 3 * S, _clock(9 * S), _clock(9 * S), "same-clock"),
        # Not measured: nothing is known, nothing removed.
        (NEWEST - 3 * S, None, _clock(0, pid=2), "clock-unknown"),
        (NEWEST - 3 * S, _clock(9 * S), None, "clock-unknown"),
        # Further back than the producer's horizon, even if the clocks explain it.
        (NEWEST - 60 * S, _clock(70 * S), _clock(0, pid=2), "beyond-horizon"),
        (NEWEST + 1, _clock(0), _clock(0, pid=2), "in-order"),
    ],
)
def test_nothing_is_removed_unless_the_source_clock_stepped_back(
    first_ns: int, before: SourceClock | None, after: SourceClock | None, why: str
) -> None:
    check = rewind_after(NEWEST, first_ns, before, after, HORIZON)
    assert (check.after_ns, check.why) == (None, why)


def test_a_burst_of_stale_elements_asks_the_input_a_bounded_number_of_times() -> None:
    import logging
    from types import SimpleNamespace
    from typing import Any, cast

    from services.lib.rewind import ASKS_PER_S, RewindFollower

    asks: list[str] = []

    def buffer_info(target: str, timeout_s: float, unambiguous: bool, session: Any) -> Any:
        assert unambiguous, "what removes elements must not rest on one peer's word"
        asks.append(target)
        return SimpleNamespace(rewinds=())  # the input recorded no rewind

    node = SimpleNamespace(buffer_info=buffer_info)
    output = SimpleNamespace(series=SimpleNamespace(newest_ns=1_000))
    follower = RewindFollower(
        cast(Any, node), "mediator/images", cast(Any, output), logging.getLogger("test")
    )
    # A peer's thousand stale elements: each is skipped (nothing removed), few asks made.
    assert not any(follower.follow(500) for _ in range(1000))
    assert len(asks) == ASKS_PER_S


class _Output:
    """A stage's output as the follower sees it: stamps, newest, discard_after."""

    def __init__(self, stamps: list[int]) -> None:
        self.stamps = stamps
        self.removed: list[int] = []

    @property
    def series(self) -> object:
        from types import SimpleNamespace

        return SimpleNamespace(newest_ns=max(self.stamps, default=None))

    def discard_after(self, after_ns: int, reason: str) -> int:
        gone = [s for s in self.stamps if s > after_ns]
        self.stamps = [s for s in self.stamps if s <= after_ns]
        self.removed += gone
        return len(gone)


def _follower(
    output: _Output, rewinds: list[object], sessions: list[object] | None = None
) -> object:
    import logging
    from types import SimpleNamespace
    from typing import Any, cast

    from services.lib.rewind import RewindFollower

    def buffer_info(target: str, timeout_s: float, unambiguous: bool, session: Any) -> Any:
        if sessions is not None:
            sessions.append(session)
        return SimpleNamespace(rewinds=tuple(rewinds))

    node = SimpleNamespace(buffer_info=buffer_info)
    return RewindFollower(
        cast(Any, node), "mediator/images", cast(Any, output), logging.getLogger("test")
    )


def test_a_producer_that_took_the_name_cannot_rewind_what_it_never_delivered() -> None:
    """A rogue offers mediator/images while the mediator is down, puts one frame after the
    detector's newest result, removes it with a genuine rewind reaching 95 s back, and sends
    a stale frame: only the result of the rogue's own frame may go."""
    from middleware import Rewind

    output = _Output(list(range(10, 101, 10)))  # results of the real mediator's frames
    rewind = Rewind(after_ns=5, count=1, first_ns=110, last_ns=110, cause="rewound")
    follower = _follower(output, [rewind])
    follower.seen("real")  # type: ignore[attr-defined]
    follower.seen(None)  # type: ignore[attr-defined]  # not registered for a moment
    follower.seen("real")  # type: ignore[attr-defined]
    follower.seen("rogue")  # type: ignore[attr-defined]  # it greeted the subscription
    output.stamps.append(110)  # its result
    # A stale frame from before the rogue's time: nothing of the rogue's explains it.
    assert not follower.follow(50)  # type: ignore[attr-defined]
    assert output.removed == []
    # One within its time: the rewind removes its own frame's result, nothing older.
    assert follower.follow(105)  # type: ignore[attr-defined]
    assert output.removed == [110]
    assert output.stamps == list(range(10, 101, 10))


def test_the_same_producer_rewinds_what_it_delivered() -> None:
    """A mediator that rewound after a camera's clock stepped back (it kept running): its
    rewind removes every result after its bound, as before."""
    from middleware import Rewind

    output = _Output(list(range(10, 101, 10)))
    rewind = Rewind(after_ns=55, count=5, first_ns=60, last_ns=100, cause="rewound")
    sessions: list[object] = []
    follower = _follower(output, [rewind], sessions)
    # Greeted by the same producer throughout (a re-registration keeps its producer epoch;
    # a forged notification under a made-up epoch is no greeting and is not seen here).
    follower.seen("real")  # type: ignore[attr-defined]
    follower.seen(None)  # type: ignore[attr-defined]
    follower.seen("real", "zid-of-real")  # type: ignore[attr-defined]
    assert follower.follow(57)  # type: ignore[attr-defined]
    assert output.removed == [60, 70, 80, 90, 100]
    # Asked of the session that greeted the subscription only (a peer answering in the
    # mediator's name while its answer is late must not tell its rewinds).
    assert sessions == ["zid-of-real"]
