from __future__ import annotations

import sys

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from middleware import DataObject, DuplicateTimestampError, PayloadTooLargeError, Retention
from middleware._buffer import TimeSeries


def _series(timestamps: list[int], retention: Retention | None = None) -> TimeSeries:
    series = TimeSeries(retention or Retention(max_count=None, max_bytes=None))
    for t in timestamps:
        series.append(DataObject(t, b"p", b"m"))
    return series


def test_duplicate_timestamp_is_refused_not_overwritten() -> None:
    series = _series([10, 20])
    with pytest.raises(DuplicateTimestampError, match="20 duplicates the newest"):
        series.append(DataObject(20, b"new", b"m"))
    assert series.exact(20) == DataObject(20, b"p", b"m")


def test_older_than_newest_is_refused() -> None:
    with pytest.raises(DuplicateTimestampError, match="older than the newest"):
        _series([10, 20]).append(DataObject(15, b"", b""))


def test_oversized_payload_is_refused() -> None:
    series = TimeSeries(Retention(max_payload_bytes=4))
    with pytest.raises(PayloadTooLargeError, match="5 bytes exceeds this buffer's limit of 4"):
        series.append(DataObject(1, b"12345", b""))
    assert len(series) == 0


def test_retention_by_count_evicts_oldest() -> None:
    series = _series(list(range(10)), Retention(max_count=3, max_bytes=None))
    assert [e.timestamp_ns for e in series.range()] == [7, 8, 9]


def test_retention_by_bytes_evicts_oldest() -> None:
    series = TimeSeries(Retention(max_count=None, max_bytes=25))
    for t in range(5):
        series.append(DataObject(t, b"x" * 9, b"m"))  # 10 bytes each
    assert [e.timestamp_ns for e in series.range()] == [3, 4]
    assert series.total_bytes == 20


def test_retention_by_age_is_measured_from_the_newest() -> None:
    series = _series([0, 5, 10, 15], Retention(max_count=None, max_bytes=None, max_age_ns=6))
    assert [e.timestamp_ns for e in series.range()] == [10, 15]


def test_nearest_prefers_closest_then_older() -> None:
    series = _series([10, 20, 30])
    assert series.nearest(24).timestamp_ns == 20  # type: ignore[union-attr]
    assert series.nearest(25).timestamp_ns == 20  # type: ignore[union-attr]
    assert series.nearest(26).timestamp_ns == 30  # type: ignore[union-attr]
    assert series.nearest(-5).timestamp_ns == 10  # type: ignore[union-attr]
    assert _series([]).nearest(5) is None


def test_payload_is_held_by_reference_not_copied() -> None:
    payload = bytes(1_000_000)
    series = _series([])
    before = sys.getrefcount(payload)
    series.append(DataObject(1, payload, b"m"))
    assert sys.getrefcount(payload) == before + 1
    assert series.exact(1).payload is payload  # type: ignore[union-attr]


def test_compaction_keeps_lookups_right() -> None:
    series = _series(list(range(5000)), Retention(max_count=100, max_bytes=None))
    assert len(series) == 100
    assert [e.timestamp_ns for e in series.latest(3)] == [4997, 4998, 4999]
    assert series.exact(4900) is not None and series.exact(4899) is None


@settings(deadline=None)  # no wall-clock bound per example
@given(
    st.lists(st.integers(0, 10_000), unique=True, max_size=60),
    st.integers(-10, 10_010),
    st.integers(-10, 10_010),
    st.one_of(st.none(), st.integers(1, 20)),
    st.integers(1, 80),
)
def test_range_matches_brute_force(
    keys: list[int], a: int, b: int, last: int | None, max_count: int
) -> None:
    keys.sort()
    series = _series(keys, Retention(max_count=max_count, max_bytes=None))
    kept = keys[-max_count:] if keys else []
    lo, hi = min(a, b), max(a, b)
    expected = [k for k in kept if lo <= k <= hi]
    if last is not None:
        expected = expected[-last:]
    assert [e.timestamp_ns for e in series.range(lo, hi, last=last)] == expected
    assert [e.timestamp_ns for e in series.latest(5)] == kept[-5:]


def _kept_by_rule(elements: list[DataObject], r: Retention) -> list[DataObject]:
    """Retention as its docstring states it, one element at a time: drop the oldest while
    any limit is exceeded, always keeping the newest."""
    kept: list[DataObject] = []
    for element in elements:
        kept.append(element)
        while len(kept) > 1:
            held = sum(e.size_bytes for e in kept)
            over = (
                (r.max_count is not None and len(kept) > r.max_count)
                or (r.max_bytes is not None and held > r.max_bytes)
                or (
                    r.max_age_ns is not None
                    and kept[-1].timestamp_ns - kept[0].timestamp_ns > r.max_age_ns
                )
            )
            if not over:
                break
            kept.pop(0)
    return kept


@settings(deadline=None)  # no wall-clock bound per example
@given(
    st.lists(st.tuples(st.integers(1, 50), st.integers(0, 40)), min_size=1, max_size=80),
    st.lists(st.integers(1, 6), min_size=1, max_size=20),
    st.one_of(st.none(), st.integers(1, 12)),
    st.one_of(st.none(), st.integers(1, 300)),
    st.one_of(st.none(), st.integers(1, 200)),
)
def test_batches_evict_exactly_as_single_appends_by_the_rule(
    steps: list[tuple[int, int]],
    batch_sizes: list[int],
    max_count: int | None,
    max_bytes: int | None,
    max_age_ns: int | None,
) -> None:
    r = Retention(max_count=max_count, max_bytes=max_bytes, max_age_ns=max_age_ns)
    elements, t = [], 0
    for gap, size in steps:
        t += gap
        elements.append(DataObject(t, bytes(size), b"m"))
    series = TimeSeries(r)
    at, sizes = 0, iter(batch_sizes * len(elements))
    while at < len(elements):
        batch = tuple(elements[at : at + next(sizes)])
        series.extend(batch)
        at += len(batch)
    # Batches evict after the whole batch: the rule applied once at the end of each batch
    # keeps what single appends keep at that point, since limits only ever drop the oldest.
    expected = _kept_by_rule(elements, r)
    assert series.range() == expected
    assert series.total_bytes == sum(e.size_bytes for e in expected)


@settings(deadline=None)  # no wall-clock bound per example
@given(
    st.lists(st.integers(1, 1000), unique=True).map(sorted),
    st.integers(0, 1001),
    st.integers(1, 5),
)
def test_discard_after_removes_exactly_the_newer_and_lets_older_stamps_follow(
    stamps: list[int], cut: int, keep: int
) -> None:
    series = _series(stamps, Retention(max_count=keep, max_bytes=None))
    held = [e.timestamp_ns for e in series.range()]
    removed = series.discard_after(cut)
    assert [e.timestamp_ns for e in removed] == [t for t in held if t > cut]
    assert [e.timestamp_ns for e in series.range()] == [t for t in held if t <= cut]
    assert series.total_bytes == 2 * len(series)  # b"p" + b"m" each
    series.append(DataObject(cut + 1, b"p", b"m"))  # stamps continue from the cut
    assert series.newest_ns == cut + 1
