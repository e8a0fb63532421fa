from __future__ import annotations

import pytest
from hypothesis import given, settings
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


def test_start_and_duration_form_is_refused_because_zenoh_splits_parameters_at_semicolons() -> None:
    with pytest.raises(QueryError, match=r"\[start;duration\] form cannot travel"):
        parse_time_range("[100;2ms]", NOW)


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
        ("[1 2]", "missing '..'"),
        ("[now(-99999999999999999999s)..]", "out of range"),
        ("[now(-999999999999999999999s)..]", "too many digits"),
        ("[now(-9999999999999999999s)..]", "out of range"),
        ("[" + "9" * 5000 + "..]", "out of range"),
        ("[" + "0" * 5000 + "1..]", None),
        ("[now(" + "1" * 5000 + "s)..]", "too many digits"),
        ("[-1..]", "out of range"),
        (f"[{2**63}..]", "out of range"),
        ("]..0[", "it is empty"),
        (f"]{2**63 - 1}..[", "it is empty"),
        ("[9999-12-31T23:59:59Z..]", "out of range"),
        ("[1960-01-01T00:00:00Z..]", "out of range"),
        ("[\u0661\u0662..]", "bad time"),
        ("[now(1\u0662s)..]", "bad duration"),
    ],
    ids=lambda value: value[:40] if isinstance(value, str) else None,
)
def test_malformed_ranges_name_the_problem(text: str, message: str | None) -> None:
    if message is None:  # leading zeros are harmless, however many
        assert parse_time_range(text, NOW) == TimeRange(1, None)
        return
    with pytest.raises(QueryError, match=message):
        parse_time_range(text, NOW)


@settings(deadline=None)  # no wall-clock bound per example
@given(st.integers(0, 2**62), st.integers(0, 2**40))
def test_integer_ranges_round_trip_through_the_selector_value(start: int, length: int) -> None:
    rng = TimeRange(start, start + length)
    assert parse_time_range(rng.to_selector_value(), NOW) == rng


def test_integer_nanoseconds_are_exact_beyond_float_precision() -> None:
    odd = 2**53 + 1
    assert parse_time_range(f"[{odd}..{2**63 - 1}]", NOW) == TimeRange(odd, 2**63 - 1)
    assert parse_duration_ns("9007199254740993ns") == odd
    assert parse_time_ns(f"now(+{odd}ns)", 0) == odd


def test_fractional_durations_are_exact() -> None:
    assert parse_duration_ns("0.1s") == 100_000_000
    assert parse_duration_ns("1.000000001s") == 1_000_000_001
    assert parse_duration_ns("-1.5h") == -5_400_000_000_000


def test_time_range_refuses_ends_outside_int64_nanoseconds() -> None:
    with pytest.raises(QueryError, match="out of range"):
        TimeRange(-1, None)
    with pytest.raises(QueryError, match="out of range"):
        TimeRange(None, 2**63)


_PIECES = st.sampled_from(
    ["[", "]", "..", ";", "now(", ")", "-", "+", "s", "ns", "w", ".", "Z", "T", " ", "0", "9"]
)


def _check_parses_within_bounds_or_raises_query_error(text: str) -> None:
    try:
        rng = parse_time_range(text, NOW)
    except QueryError:
        return
    for end in (rng.start_ns, rng.end_ns):
        assert end is None or 0 <= end < 2**63
    if rng.start_ns is not None and rng.end_ns is not None:
        assert rng.start_ns <= rng.end_ns


@settings(deadline=None)  # no wall-clock bound per example
@given(st.text(max_size=60))
def test_any_text_parses_within_bounds_or_raises_query_error(text: str) -> None:
    _check_parses_within_bounds_or_raises_query_error(text)


@settings(deadline=None)  # no wall-clock bound per example
@given(
    st.lists(
        st.one_of(_PIECES, st.integers(-(2**70), 2**70).map(str), st.text(max_size=3)),
        max_size=12,
    ).map("".join)
)
def test_range_shaped_text_parses_within_bounds_or_raises_query_error(text: str) -> None:
    _check_parses_within_bounds_or_raises_query_error(text)


@settings(deadline=None)  # no wall-clock bound per example
@given(
    st.sampled_from(["[", "]"]),
    st.integers(-(2**66), 2**66),
    st.sampled_from(["ns", "u", "ms", "s", "m", "h", "d", "w"]),
    st.sampled_from(["]", "["]),
)
def test_relative_ranges_parse_within_bounds_or_raise_query_error(
    opening: str, amount: int, unit: str, closing: str
) -> None:
    _check_parses_within_bounds_or_raises_query_error(f"{opening}now({amount}{unit})..{closing}")
