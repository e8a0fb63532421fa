"""The time model: ``SteadyClock`` never goes backward and absorbs system clock steps."""

from __future__ import annotations

import pytest

from middleware import SteadyClock, _clock
from middleware._clock import SLEW_RATE
from middleware._timerange import parse_time_range

S = 1_000_000_000


class FakeClocks:
    def __init__(self) -> None:
        self.wall = 1_700_000_000 * S
        self.mono = 5 * S

    def advance(self, ns: int) -> None:
        self.wall += ns
        self.mono += ns


def make() -> tuple[FakeClocks, SteadyClock, list[int]]:
    clocks, steps = FakeClocks(), []
    clock = SteadyClock(
        wall=lambda: clocks.wall, monotonic=lambda: clocks.mono, on_step=steps.append
    )
    return clocks, clock, steps


def test_backward_step_keeps_time_increasing_and_slews_back() -> None:
    clocks, clock, steps = make()
    before = clock.now_ns()
    clocks.wall -= 62 * S  # chronyd makestep: only the wall clock moves
    after = clock.now_ns()
    assert after > before and after - before < S  # production does not stall
    assert steps == [-62 * S]
    assert clock.status().lead_ns == 62 * S
    clocks.advance(S)
    one_second_later = clock.now_ns()
    assert abs(one_second_later - after - int(S * (1 - SLEW_RATE))) <= 1
    clocks.advance(int(62 * S / SLEW_RATE) + S)
    assert clock.status().lead_ns == 0
    clocks.advance(S)
    assert clock.now_ns() == clocks.wall


def test_forward_step_is_followed_at_once_and_logged_once() -> None:
    clocks, clock, steps = make()
    clock.now_ns()
    clocks.wall += 3600 * S
    assert clock.now_ns() == clocks.wall
    clock.now_ns()
    assert steps == [3600 * S]
    assert clock.status().steps == 1


def test_small_drift_is_not_a_step_and_readings_strictly_increase() -> None:
    clocks, clock, steps = make()
    readings = [clock.now_ns() for _ in range(5)]  # no time passes between them
    assert readings == sorted(set(readings))
    clocks.wall += 10_000_000  # 10 ms: NTP slewing, not a step
    clock.now_ns()
    assert steps == []


def test_a_time_query_now_continues_across_a_backward_step(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``[now(-2s)..]`` after a backward step of the system clock still means the last 2 s
    of stamps: ``now()`` is the process clock, which did not go back with the system's."""
    clocks = FakeClocks()
    clock = SteadyClock(wall=lambda: clocks.wall, monotonic=lambda: clocks.mono)
    monkeypatch.setattr(_clock, "CLOCK", clock)
    stamped = _clock.now_ns()  # an element stamped just before the step
    clocks.wall -= 60 * S  # chrony's makestep, backward
    clocks.advance(S // 2)
    window = parse_time_range("[now(-2s)..]")
    assert window.start_ns is not None
    assert window.start_ns <= stamped < window.start_ns + 2 * S, (window, stamped)
    assert abs(window.start_ns - (stamped + S // 2 - 2 * S)) < S // 10
