"""The in-memory time series behind a named buffer.

Timestamps only grow, so the series is two parallel append-only lists searched with
``bisect`` (O(log n) to find, O(k) to read k elements); eviction advances a head index and
compacts now and then, so eviction is amortised O(1) and nothing is copied per lookup.
"""

from __future__ import annotations

import threading
from bisect import bisect_left, bisect_right
from typing import cast

from ._errors import DuplicateTimestampError, PayloadTooLargeError
from ._records import DataObject, Retention

# Compact the lists when this many evicted slots sit at the front and they are most of it.
_COMPACT_MIN = 1024


class TimeSeries:
    """A bounded, strictly increasing series of DataObjects.

    Threads: every method takes ``_lock`` (it guards all fields); it is never held while
    calling anything outside this class.
    """

    def __init__(self, retention: Retention) -> None:
        self.retention = retention
        self._lock = threading.Lock()
        self._keys: list[int] = []
        self._items: list[DataObject | None] = []
        self._head = 0
        self._bytes = 0

    def __len__(self) -> int:
        with self._lock:
            return self._count()

    def _count(self) -> int:
        return len(self._keys) - self._head

    @property
    def total_bytes(self) -> int:
        """Payload and metadata bytes held."""
        with self._lock:
            return self._bytes

    @property
    def oldest_ns(self) -> int | None:
        with self._lock:
            return self._keys[self._head] if self._count() else None

    @property
    def newest_ns(self) -> int | None:
        with self._lock:
            return self._keys[-1] if self._count() else None

    def _check_put(self, timestamp_ns: int, payload_bytes: int) -> None:
        limit = self.retention.max_payload_bytes
        if payload_bytes > limit:
            raise PayloadTooLargeError(
                f"payload of {payload_bytes} bytes exceeds this buffer's limit of {limit} bytes"
            )
        newest = self._keys[-1] if self._count() else None
        if newest is not None and timestamp_ns <= newest:
            what = "duplicates" if timestamp_ns == newest else "is older than"
            raise DuplicateTimestampError(
                f"timestamp {timestamp_ns} {what} the newest element ({newest}); "
                "timestamps must strictly increase"
            )

    def append(self, element: DataObject) -> list[DataObject]:
        """Append and evict by retention; return what was evicted (oldest first)."""
        with self._lock:
            self._check_put(element.timestamp_ns, len(element.payload))
            self._keys.append(element.timestamp_ns)
            self._items.append(element)
            self._bytes += element.size_bytes
            return self._evict()

    def check_extend(self, elements: tuple[DataObject, ...]) -> None:
        """Raise if ``extend(elements)`` could not append them now (see ``extend``)."""
        with self._lock:
            self._check_extend(elements)

    def _check_extend(self, elements: tuple[DataObject, ...]) -> None:
        limit = self.retention.max_payload_bytes
        for element in elements:
            if len(element.payload) > limit:
                self._check_put(element.timestamp_ns, len(element.payload))
        self._check_put(elements[0].timestamp_ns, len(elements[0].payload))

    def extend(self, elements: tuple[DataObject, ...]) -> list[DataObject]:
        """Append strictly increasing elements, all or none, and evict once; the evicted.

        The caller has ordered the batch; only its first element is checked against the
        series (every later one is newer than the one before it).
        """
        with self._lock:
            self._check_extend(elements)
            self._keys.extend([e.timestamp_ns for e in elements])
            self._items.extend(elements)
            self._bytes += sum([len(e.payload) + len(e.metadata) for e in elements])
            return self._evict()

    def discard_after(self, timestamp_ns: int) -> list[DataObject]:
        """Remove every element stamped after ``timestamp_ns``; the removed, oldest first.

        The one way back in time: elements stamped by a clock that was wrong (a source
        restarted after its clock was corrected backward) would otherwise keep every later,
        correct one out for as long as the error.
        """
        with self._lock:
            cut = max(self._head, bisect_right(self._keys, timestamp_ns, self._head))
            removed = [self._at(i) for i in range(cut, len(self._keys))]
            del self._keys[cut:]
            del self._items[cut:]
            self._bytes -= sum(len(e.payload) + len(e.metadata) for e in removed)
            return removed

    def _evict(self) -> list[DataObject]:
        r = self.retention
        keys, items = self._keys, self._items
        newest, head, held = keys[-1], self._head, self._bytes
        # How far the head must move for each limit; the newest element always stays.
        end = len(keys) - 1
        target = head
        if r.max_count is not None:
            target = max(target, len(keys) - r.max_count)
        if r.max_age_ns is not None and newest - keys[head] > r.max_age_ns:
            target = max(target, bisect_left(keys, newest - r.max_age_ns, head))
        target = min(target, end)
        # Slices, not a loop per element: a batch evicts as many as it appends.
        evicted = cast(list[DataObject], items[head:target])
        if evicted:
            items[head:target] = [None] * len(evicted)
            held -= sum([len(e.payload) + len(e.metadata) for e in evicted])
        head = target
        if r.max_bytes is not None:
            while held > r.max_bytes and head < end:
                item = items[head]
                assert item is not None
                items[head] = None
                held -= len(item.payload) + len(item.metadata)
                evicted.append(item)
                head += 1
        self._head, self._bytes = head, held
        if head >= _COMPACT_MIN and head * 2 >= len(keys):
            del keys[:head]
            del items[:head]
            self._head = 0
        return evicted

    def _at(self, index: int) -> DataObject:
        item = self._items[index]
        assert item is not None
        return item

    def exact(self, timestamp_ns: int) -> DataObject | None:
        """The element with exactly this timestamp, or None."""
        with self._lock:
            i = bisect_left(self._keys, timestamp_ns, self._head)
            if i < len(self._keys) and self._keys[i] == timestamp_ns:
                return self._at(i)
            return None

    def nearest(self, timestamp_ns: int) -> DataObject | None:
        """The element whose timestamp is closest (the older one on a tie), or None."""
        with self._lock:
            if not self._count():
                return None
            i = bisect_left(self._keys, timestamp_ns, self._head)
            candidates = [j for j in (i - 1, i) if self._head <= j < len(self._keys)]
            best = min(candidates, key=lambda j: (abs(self._keys[j] - timestamp_ns), j))
            return self._at(best)

    def range(
        self, start_ns: int | None = None, end_ns: int | None = None, last: int | None = None
    ) -> list[DataObject]:
        """Elements with start <= t <= end in timestamp order; with ``last``, only the newest N."""
        with self._lock:
            lo = self._head if start_ns is None else bisect_left(self._keys, start_ns, self._head)
            hi = len(self._keys) if end_ns is None else bisect_right(self._keys, end_ns, self._head)
            if last is not None:
                lo = max(lo, hi - last)
            return [self._at(i) for i in range(lo, hi)]

    def latest(self, n: int) -> list[DataObject]:
        """The newest ``n`` elements in timestamp order."""
        return self.range(last=n)
