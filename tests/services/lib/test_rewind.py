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

    def buffer_info(target: str, timeout_s: float, unambiguous: bool) -> Any:
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
