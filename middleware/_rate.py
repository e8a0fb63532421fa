"""The put rate a buffer reports in ``info`` and ``ls``: a pure estimate from put events.

The window holds the last puts as ``(time, elements)`` events, one per ``put`` or
``put_many``, not one time per element: a batch stores its elements at one instant, and a
window of per-element times that one batch fills (64 elements or more) has no span to
measure, so it read 0 Hz for a stream that kept coming. The elements of the window's first
event were put before the measured span began: counting them over that span overstates the
rate (a 200 Hz IMU in batches of 10 read 210 Hz). The rate is the elements put after the
first event over the span, as ``ros2 topic hz`` counts messages and not callbacks.
"""

from __future__ import annotations

from collections.abc import Sequence

# Nothing put for this long: the rate is 0, not the last window's.
STALE_NS = 5_000_000_000


def put_rate_hz(puts: Sequence[tuple[int, int]], now_ns: int) -> float:
    """Elements per second over ``puts``: ``(monotonic ns, elements)`` per put, oldest
    first; 0.0 with no span to measure or nothing put for ``STALE_NS``."""
    if len(puts) < 2:
        return 0.0
    first, last = puts[0][0], puts[-1][0]
    if last <= first or now_ns - last > STALE_NS:
        return 0.0
    # Times are non-decreasing: every event at the first instant leads the window.
    after_first = sum(count for t, count in puts if t != first)
    return after_first / ((last - first) / 1e9)
