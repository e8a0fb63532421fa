"""The put rate a buffer reports in ``info`` and ``ls``: a pure estimate from put times.

A batch (``put_many``) stores its elements at one instant, so a window of per-element put
times holds runs of equal times, and its oldest run may be cut anywhere. The elements put
*at* the window's first instant arrived before the measured span began: counting them
over that span overstates the rate (a 200 Hz IMU in batches of 10 read 210 Hz with a
64-element window). The rate is the elements put after the first instant over the span.
"""

from __future__ import annotations

from collections.abc import Sequence

# Nothing put for this long: the rate is 0, not the last window's.
STALE_NS = 5_000_000_000


def put_rate_hz(put_times_ns: Sequence[int], now_ns: int) -> float:
    """Elements per second over ``put_times_ns`` (monotonic ns, oldest first, one per
    element); 0.0 with no span to measure or nothing put for ``STALE_NS``."""
    if not put_times_ns:
        return 0.0
    first, last = put_times_ns[0], put_times_ns[-1]
    if last <= first or now_ns - last > STALE_NS:
        return 0.0
    # Times are non-decreasing: the elements put at the first instant lead the window.
    at_first = next(i for i, t in enumerate(put_times_ns) if t != first)
    return (len(put_times_ns) - at_first) / ((last - first) / 1e9)
