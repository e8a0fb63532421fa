"""Zenoh's time-range syntax for the ``_time`` selector parameter.

zenoh-python exposes no parser, so this is ours. Grammar (Zenoh's ``TimeRange`` without its
``[start;duration]`` form, which cannot travel in a selector: Zenoh splits parameters at
``;``, so the service would receive ``_time=[start`` and a stray ``duration]`` parameter)::

    range    := ("[" | "]") [time] ".." [time] ("]" | "[")     "[" inclusive, "]" exclusive start
    time     := "now(" [("-" | "+") duration] ")" | RFC 3339 | integer nanoseconds (framegate)
    duration := number unit,  unit in ns, u, us, ms, s, m, h, d, w

Both ends resolve to int nanoseconds since the Unix epoch, computed exactly (no float), and
must lie in ``0..MAX_TIME_NS`` (a signed 64-bit count, as Zenoh's and the wire's timestamps);
``now()`` is read once per parse. Anything else, however long or strange, is a
``QueryError`` naming the problem: a query is input from a peer, and a service answers it
with an error reply, never a traceback.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from datetime import datetime
from fractions import Fraction

from ._clock import now_ns as clock_now_ns
from ._errors import QueryError

MAX_TIME_NS = 2**63 - 1
"""The largest timestamp framegate accepts: int64 nanoseconds (the year 2262)."""

_UNIT_NS = {
    "ns": 1,
    "u": 1_000,
    "us": 1_000,
    "ms": 1_000_000,
    "s": 1_000_000_000,
    "m": 60 * 1_000_000_000,
    "h": 3600 * 1_000_000_000,
    "d": 86_400 * 1_000_000_000,
    "w": 7 * 86_400 * 1_000_000_000,
}
# ASCII digits only: \d would also take Arabic-Indic and other digits, which int() accepts.
_DURATION = re.compile(r"\s*([+-]?)([0-9]+(?:\.[0-9]*)?|\.[0-9]+)\s*(ns|us|u|ms|s|m|h|d|w)\s*")
_INTEGER = re.compile(r"[+-]?[0-9]+")
_NOW = re.compile(r"now\((.*)\)", re.DOTALL)
_RFC3339 = re.compile(
    r"([0-9]{4}-[0-9]{2}-[0-9]{2}[Tt ][0-9]{2}:[0-9]{2}:[0-9]{2})(?:\.([0-9]{1,9}))?"
    r"([Zz]|[+-][0-9]{2}:[0-9]{2})"
)
# More integer digits than this cannot fit in MAX_TIME_NS (19 digits) in any unit; checking
# the length first keeps int() away from 5000-digit strings (Python refuses > 4300 digits).
_MAX_INTEGER_DIGITS = 20
# Fractional digits beyond nanoseconds of a week cannot change the rounded result.
_MAX_FRACTION_DIGITS = 30
_RANGE_HELP = "write [start..end] (either end may be empty) or ]start..end[ for exclusive ends"


@dataclass(frozen=True, slots=True)
class TimeRange:
    """A closed interval [start_ns, end_ns]; None means open on that side.

    Both ends lie in ``0..MAX_TIME_NS``; anything else is a QueryError at construction.
    """

    start_ns: int | None = None
    end_ns: int | None = None

    def __post_init__(self) -> None:
        for name in ("start_ns", "end_ns"):
            value = getattr(self, name)
            if value is not None:
                _check_time_ns(value, f"{name}={value}")

    def contains(self, timestamp_ns: int) -> bool:
        """Whether a timestamp lies inside the range."""
        if self.start_ns is not None and timestamp_ns < self.start_ns:
            return False
        return self.end_ns is None or timestamp_ns <= self.end_ns

    def to_selector_value(self) -> str:
        """The ``_time`` value for this range (integer-ns ends, a framegate extension)."""
        start = "" if self.start_ns is None else str(self.start_ns)
        end = "" if self.end_ns is None else str(self.end_ns)
        return f"[{start}..{end}]"


def parse_duration_ns(text: str) -> int:
    """Parse ``2s``, ``-500ms``, ``1.5h`` ... into signed nanoseconds, exactly.

    The magnitude must not exceed ``MAX_TIME_NS``; fractions of a nanosecond round to even.
    """
    match = _DURATION.fullmatch(text)
    if not match:
        raise QueryError(
            f"bad duration {_short(text)}: write a number and a unit "
            "(ns, u, ms, s, m, h, d, w), e.g. 2s"
        )
    sign, number, unit = match.groups()
    whole, _, fraction = number.partition(".")
    whole = whole.lstrip("0")
    if len(whole) > _MAX_INTEGER_DIGITS or len(fraction) > _MAX_FRACTION_DIGITS:
        raise QueryError(
            f"duration {_short(text)} has too many digits: durations are limited to "
            f"{MAX_TIME_NS} ns (about 292 years)"
        )
    value = round(Fraction(f"{whole or '0'}.{fraction or '0'}") * _UNIT_NS[unit])
    if value > MAX_TIME_NS:
        raise QueryError(
            f"duration {_short(text)} is out of range: durations are limited to "
            f"{MAX_TIME_NS} ns (about 292 years)"
        )
    return -value if sign == "-" else value


def parse_time_ns(text: str, now_ns: int | None = None) -> int:
    """Parse one time: ``now()``, ``now(-2s)``, RFC 3339, or integer nanoseconds.

    The result lies in ``0..MAX_TIME_NS``; anything else is a QueryError.
    """
    text = text.strip()
    if not text:
        raise QueryError("empty time: write now(), now(-2s), an RFC 3339 time or nanoseconds")
    now_match = _NOW.fullmatch(text)
    if now_match:
        base = clock_now_ns() if now_ns is None else now_ns
        inner = now_match.group(1).strip()
        return _check_time_ns(base + (parse_duration_ns(inner) if inner else 0), text)
    if _INTEGER.fullmatch(text):
        digits = text.lstrip("+-").lstrip("0")
        if len(digits) > _MAX_INTEGER_DIGITS:
            raise QueryError(f"time {_short(text)} is out of range: {_TIME_BOUNDS}")
        value = int(digits or "0")
        return _check_time_ns(-value if text.startswith("-") else value, text)
    return _check_time_ns(_parse_rfc3339_ns(text), text)


_TIME_BOUNDS = f"times lie between 0 (the Unix epoch) and {MAX_TIME_NS} ns (the year 2262)"


def _check_time_ns(value: int, text: str) -> int:
    if not 0 <= value <= MAX_TIME_NS:
        raise QueryError(f"time {_short(text)} is out of range: {_TIME_BOUNDS}")
    return value


def _short(text: str) -> str:
    """The bad value for a message, cut short: a query may carry kilobytes of it."""
    return repr(text) if len(text) <= 60 else repr(text[:57] + "...")


def _parse_rfc3339_ns(text: str) -> int:
    match = _RFC3339.fullmatch(text)
    if not match:
        raise QueryError(
            f"bad time {_short(text)}: expected now(), now(-2s), RFC 3339 "
            "(2026-11-22T14:00:00.5Z) or integer nanoseconds since the epoch"
        )
    head, fraction, zone = match.groups()
    try:
        whole = datetime.fromisoformat(head + ("+00:00" if zone in "Zz" else zone))
        seconds = int(whole.timestamp())
    except (ValueError, OverflowError) as exc:
        raise QueryError(f"bad time {_short(text)}: {exc}") from exc
    return seconds * 1_000_000_000 + int((fraction or "0").ljust(9, "0"))


def parse_time_range(text: str, now_ns: int | None = None) -> TimeRange:
    """Parse a ``_time`` value into a closed integer range within ``0..MAX_TIME_NS``."""
    value = text.strip()
    if len(value) < 4 or value[0] not in "[]" or value[-1] not in "[]":
        raise QueryError(f"bad time range {_short(text)}: {_RANGE_HELP}")
    now = clock_now_ns() if now_ns is None else now_ns
    start_open, end_open = value[0] == "]", value[-1] == "["
    body = value[1:-1]
    if ".." not in body:
        if ";" in body:
            raise QueryError(
                f"bad time range {_short(text)}: the [start;duration] form cannot travel in "
                "a Zenoh selector (';' separates parameters); write [start..now(+2s)] or "
                "integer ends instead"
            )
        raise QueryError(f"bad time range {_short(text)}: missing '..' between the ends")
    left, _, right = body.partition("..")
    start = parse_time_ns(left, now) if left.strip() else None
    end = parse_time_ns(right, now) if right.strip() else None
    if start is not None and start_open:
        start += 1
    if end is not None and end_open:
        end -= 1
    if (start is not None and start > MAX_TIME_NS) or (end is not None and end < 0):
        raise QueryError(f"bad time range {_short(text)}: it is empty ({_TIME_BOUNDS})")
    if start is not None and end is not None and start > end:
        raise QueryError(f"bad time range {_short(text)}: it ends before it starts")
    return TimeRange(start, end)
