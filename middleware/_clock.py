"""Time in framegate: the process clock that stamps elements (``SteadyClock``, the time
model) and one clock-offset sample between processes, NTP-style (``ClockSample``)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class ClockSample:
    """One exchange: the remote clock minus ours, and the round trip that bounds its error."""

    offset_ns: int
    round_trip_ns: int

    @classmethod
    def from_times(cls, sent_ns: int, remote_ns: int, received_ns: int) -> ClockSample:
        """``remote - midpoint(sent, received)``: the remote read its clock somewhere in our
        [sent, received] window, so the error is at most half the round trip."""
        return cls(remote_ns - (sent_ns + received_ns) // 2, received_ns - sent_ns)


# -- the time model ------------------------------------------------------------------------
# A change of (system wall - monotonic) larger than this between two readings is a step of
# the system clock (NTP/chrony steps, a manual `date -s`); smaller drifts are followed.
STEP_THRESHOLD_NS = 50_000_000
# While ahead of the system clock after a backward step, time runs this much slower than
# the monotonic clock until it agrees with the system clock again (chrony slews at up to
# 8.3 %): stamps keep increasing and intervals shrink by at most this fraction.
SLEW_RATE = 0.05


@dataclass(frozen=True, slots=True)
class ClockStatus:
    """What ``SteadyClock`` has seen: steps of the system clock and how far ahead it runs."""

    steps: int
    last_step_ns: int  # size of the last step (+ forward, - backward); 0 before any
    lead_ns: int  # how far this clock runs ahead of the system clock now (slewing back)


class SteadyClock:
    """Wall-clock time in int ns that never goes backward in this process.

    Time model: ``now_ns() = system wall clock + lead``. ``lead`` is 0 until the system
    clock steps backward; then it takes the step's size, so time continues where it was,
    and shrinks at ``SLEW_RATE`` of elapsed monotonic time (time runs 5 % slow) until this
    clock agrees with the system clock again. A forward step is followed at once (time
    jumps ahead; any lead absorbs it first). Steps are detected as changes of
    (wall - monotonic), since the monotonic clock never steps; each is logged once with
    its size. Readings strictly increase (two calls in the same nanosecond differ by 1).

    Thread-safe; the clocks are parameters so that tests can drive it.
    """

    def __init__(
        self,
        *,
        wall: Callable[[], int] | None = None,
        monotonic: Callable[[], int] | None = None,
        on_step: Callable[[int], None] | None = None,
    ) -> None:
        # Looked up at each reading, so that a process (or a test) that replaces
        # ``time.time_ns`` is followed.
        self._wall = wall or (lambda: time.time_ns())
        self._monotonic = monotonic or (lambda: time.monotonic_ns())
        self._on_step = on_step
        self._lock = threading.Lock()
        self._mono_ns = self._monotonic()
        self._skew_ns = self._wall() - self._mono_ns  # wall - monotonic at the last reading
        self._lead_ns = 0
        self._last_ns = 0
        self._steps = 0
        self._last_step_ns = 0

    def now_ns(self) -> int:
        step = 0
        with self._lock:
            mono = self._monotonic()
            wall = self._wall()
            skew = wall - mono
            if abs(skew - self._skew_ns) > STEP_THRESHOLD_NS:
                step = skew - self._skew_ns
                self._steps += 1
                self._last_step_ns = step
                self._lead_ns = max(0, self._lead_ns - step)
            elif self._lead_ns:
                self._lead_ns = max(0, self._lead_ns - int((mono - self._mono_ns) * SLEW_RATE))
            self._skew_ns, self._mono_ns = skew, mono
            now = max(wall + self._lead_ns, self._last_ns + 1)
            self._last_ns = now
        if step and self._on_step is not None:
            self._on_step(step)
        return now

    def status(self) -> ClockStatus:
        self.now_ns()  # a reading detects a step that happened since the last one
        with self._lock:
            return ClockStatus(self._steps, self._last_step_ns, self._lead_ns)


def _log_step(step_ns: int) -> None:
    logging.getLogger("framegate.middleware").warning(
        "the system clock stepped %s by %.3f s; framegate time %s",
        "forward" if step_ns > 0 else "backward",
        abs(step_ns) / 1e9,
        "follows it"
        if step_ns > 0
        else f"continues and slews back to it at {SLEW_RATE:.0%} (stamps keep increasing)",
    )


# The process's clock: every element framegate stamps or judges by "now" reads it.
CLOCK = SteadyClock(on_step=_log_step)


def now_ns() -> int:
    """Wall-clock ns since the epoch that never goes backward in this process (see
    ``SteadyClock``): stamp elements with it."""
    return CLOCK.now_ns()
