"""The put rate a buffer reports in ``info`` and ``ls``: a pure estimate from put events.

The window holds the last puts as events, one per ``put`` or ``put_many``, not one time per
element: a batch stores its elements at one instant, and a window of per-element times that
one batch fills (64 elements or more) has no span to measure, so it read 0 Hz for a stream
that kept coming. The elements of the window's first event were put before the measured span
began: counting them over that span overstates the rate (a 200 Hz IMU in batches of 10 read
210 Hz). The rate is the elements put after the first event over the span, as ``ros2 topic
hz`` counts messages and not callbacks.

Puts closer together than ``MERGE_NS`` share one slot of the window, so a window of
``WINDOW`` slots spans at least ``WINDOW * MERGE_NS`` of a fast stream: 64 single puts
spanned 0.13 s of a 500 Hz stream (``play`` puts gyro samples one by one), and on a busy
machine, where puts come in bursts, ``info`` read it as 270 to 612 Hz.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

# Nothing put for this long: the rate is 0, not the last window's.
STALE_NS = 5_000_000_000
# Slots in the window, and how close a put must follow a slot's first to join it.
WINDOW = 64
MERGE_NS = 50_000_000


@dataclass(slots=True)
class _Slot:
    first_ns: int
    last_ns: int
    elements: int
    # Elements put at ``first_ns`` itself: before the span, when this slot is the oldest.
    at_first: int


@dataclass(slots=True)
class PutRate:
    """The last puts, in ``WINDOW`` slots; ``hz`` is their rate."""

    _slots: deque[_Slot] = field(default_factory=lambda: deque(maxlen=WINDOW))

    def add(self, now_ns: int, elements: int) -> None:
        """``elements`` were put at monotonic ``now_ns`` (non-decreasing)."""
        if self._slots and now_ns - self._slots[-1].first_ns < MERGE_NS:
            slot = self._slots[-1]
            slot.last_ns = now_ns
            slot.elements += elements
            if now_ns == slot.first_ns:
                slot.at_first += elements
            return
        self._slots.append(_Slot(now_ns, now_ns, elements, elements))

    def hz(self, now_ns: int) -> float:
        """Elements per second over the window; 0.0 with no span to measure or nothing put
        for ``STALE_NS``."""
        if not self._slots:
            return 0.0
        first, last = self._slots[0].first_ns, self._slots[-1].last_ns
        if last <= first or now_ns - last > STALE_NS:
            return 0.0
        after_first = sum(s.elements for s in self._slots) - self._slots[0].at_first
        return after_first / ((last - first) / 1e9)
