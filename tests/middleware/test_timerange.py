from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from middleware import QueryError, TimeRange, parse_duration_ns, parse_time_ns, parse_time_range

NOW = 1_800_000_000_000_000_000


def test_relative_range_resolves_against_now() -> None:
    assert parse_time_range("[now(-2s)..now()]", NOW) == TimeRange(NOW - 2_000_000_000, NOW)


def test_open_ends_are_none() -> None:
    assert parse_time_range("[now(-1m)..]", NOW) == TimeRange(NOW - 60_000_000_000, None)
    assert parse_time_range("[..]", NOW) == TimeRange(None, None)


def test_exclusive_brackets_shift_integer_ends() -> None:
    assert parse_time_range("]10..20[", NOW) == TimeRange(11, 19)


def test_start_and_duration_form() -> None:
    assert parse_time_range("[100;2ms]", NOW) == TimeRange(100, 2_000_100)


def test_rfc3339_keeps_nanoseconds() -> None:
    t = parse_time_ns("2026-11-22T14:00:00.123456789Z")
    assert t % 1_000_000_000 == 123_456_789
    assert parse_time_ns("2026-11-22T15:00:00+01:00") == parse_time_ns("2026-11-22T14:00:00Z")


@pytest.mark.parametrize(
    ("unit", "factor"),
    [
        ("ns", 1),
        ("u", 1_000),
        ("ms", 10**6),
        ("s", 10**9),
        ("m", 60 * 10**9),
        ("h", 3600 * 10**9),
        ("d", 86400 * 10**9),
        ("w", 7 * 86400 * 10**9),
    ],
)
def test_duration_units(unit: str, factor: int) -> None:
    assert parse_duration_ns(f"3{unit}") == 3 * factor


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("x", "bad time range"),
        ("[1..0]", "ends before it starts"),
        ("[now(-2q)..]", "bad duration"),
        ("[2026-13-01T00:00:00Z..]", "month must be in 1..12"),
        ("[yesterday..]", "bad time 'yesterday'"),
        ("[1 2]", "missing '..' or ';'"),
    ],
)
def test_malformed_ranges_name_the_problem(text: str, message: str) -> None:
    with pytest.raises(QueryError, match=message):
        parse_time_range(text, NOW)


@given(st.text(max_size=40))
def test_arbitrary_text_parses_or_raises_query_error(text: str) -> None:
    try:
        rng = parse_time_range(text, NOW)
    except QueryError:
        return
    if rng.start_ns is not None and rng.end_ns is not None:
        assert rng.start_ns <= rng.end_ns


@given(st.integers(0, 2**62), st.integers(0, 2**40))
def test_integer_ranges_round_trip_through_the_selector_value(start: int, length: int) -> None:
    rng = TimeRange(start, start + length)
    assert parse_time_range(rng.to_selector_value(), NOW) == rng
