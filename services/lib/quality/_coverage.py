"""Which gyro samples an exposure needs, and a CoverageError when they are not there.

Missing data must never look like a still camera (q = 1), so every way of not covering an
exposure raises, naming the interval and what is missing.
"""

from __future__ import annotations

from typing import NoReturn

import numpy as np
import numpy.typing as npt

from ._errors import CoverageError
from ._exposure import Exposure
from ._gyro import GyroSamples


def _ms(ns: int) -> str:
    return f"{ns / 1e6:.3f} ms"


def covering(
    gyro: GyroSamples,
    start_ns: int,
    end_ns: int,
    max_gap_ns: int | None,
    exposure: Exposure,
    offset_ns: int,
) -> slice:
    """The slice of samples from the last one at or before ``start_ns`` to the first one at
    or after ``end_ns`` (gyro clock). ``exposure`` and ``offset_ns`` only name the exposure
    in messages.

    Raises CoverageError when there are fewer than two samples, the samples start after
    ``start_ns`` or end before ``end_ns``, or two neighbours in the slice are more than
    ``max_gap_ns`` apart (None: two nominal sample periods).
    """
    t_ns = gyro.t_ns
    count = t_ns.size

    def window() -> str:
        # Only called when raising.
        return (
            f"exposure [{exposure.start_ns}, {exposure.end_ns}] ns (camera clock) needs gyro "
            f"samples over [{start_ns}, {end_ns}] ns (gyro clock, offset {offset_ns:+d} ns)"
        )

    if count < 2:
        raise CoverageError(
            f"{window()}, but there {'is' if count == 1 else 'are'} {count} gyro sample"
            f"{'' if count == 1 else 's'}; at least two around the exposure are needed"
        )
    first = int(t_ns.searchsorted(start_ns, "right")) - 1
    last = int(t_ns.searchsorted(end_ns, "left"))
    if first < 0:
        raise CoverageError(
            f"{window()}, but the gyro samples start at {int(t_ns[0])} ns, "
            f"{_ms(int(t_ns[0]) - start_ns)} after the exposure starts; wait for or fetch "
            "earlier samples, or check the camera-gyro time offset"
        )
    if last >= count:
        raise CoverageError(
            f"{window()}, but the gyro samples end at {int(t_ns[-1])} ns, "
            f"{_ms(end_ns - int(t_ns[-1]))} before the exposure ends; wait for later "
            "samples, or check the camera-gyro time offset"
        )
    if max_gap_ns is None:
        limit = 2 * gyro.period_ns
        wide = gyro.wide_steps
        if wide.size:
            k = int(wide.searchsorted(first))
            if k < wide.size and wide[k] < last:
                _raise_gap(window(), t_ns, int(wide[k]), limit)
    elif last > first:
        steps = t_ns[first + 1 : last + 1] - t_ns[first:last]
        at = int(np.argmax(steps))
        if int(steps[at]) > max_gap_ns:
            _raise_gap(window(), t_ns, first + at, max_gap_ns)
    return slice(first, last + 1)


def _raise_gap(window: str, t_ns: npt.NDArray[np.int64], at: int, limit_ns: int) -> NoReturn:
    gap = int(t_ns[at + 1] - t_ns[at])
    raise CoverageError(
        f"{window}, but there is a gap of {_ms(gap)} between the gyro samples at "
        f"{int(t_ns[at])} and {int(t_ns[at + 1])} ns, longer than the allowed "
        f"{_ms(limit_ns)} (two nominal periods unless max_gap_ns says otherwise)"
    )
