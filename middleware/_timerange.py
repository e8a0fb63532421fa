"""Zenoh's time-range syntax for the ``_time`` selector parameter.

zenoh-python exposes no parser, so this is ours. Grammar (as in Zenoh's ``TimeRange``):

    range    := ("[" | "]") [time] ".." [time] ("]" | "[")     "[" inclusive, "]" exclusive start
              | ("[" | "]") time ";" duration ("]" | "[")
    time     := "now(" [["-"] duration] ")" | RFC 3339 | integer nanoseconds (framegate extension)
    duration := number unit,  unit in ns, u, us, ms, s, m, h, d, w

Both ends resolve to int nanoseconds since the Unix epoch; ``now()`` is read once per parse.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass
from datetime import datetime

from ._errors import QueryError

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
_DURATION = re.compile(r"^\s*(-?)(\d+(?:\.\d*)?|\.\d+)\s*(ns|us|u|ms|s|m|h|d|w)\s*$")
_NOW = re.compile(r"^now\((.*)\)$")
_FRACTION = re.compile(r"^(.*T\d\d:\d\d:\d\d)(?:\.(\d{1,9}))?(Z|[+-]\d\d:\d\d)$", re.IGNORECASE)


@dataclass(frozen=True, slots=True)
class TimeRange:
    """A closed interval [start_ns, end_ns]; None means open on that side."""

    start_ns: int | None = None
    end_ns: int | None = None

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
    """Parse ``2s``, ``-500ms``, ``1.5h`` ... into signed nanoseconds."""
    match = _DURATION.match(text)
    if not match:
        raise QueryError(
            f"bad duration {text!r}: write a number and a unit (ns, u, ms, s, m, h, d, w), e.g. 2s"
        )
    sign, number, unit = match.groups()
    value = round(float(number) * _UNIT_NS[unit])
    return -value if sign else value


def parse_time_ns(text: str, now_ns: int | None = None) -> int:
    """Parse one time: ``now()``, ``now(-2s)``, RFC 3339, or integer nanoseconds."""
    text = text.strip()
    if not text:
        raise QueryError("empty time: write now(), now(-2s), an RFC 3339 time or nanoseconds")
    now_match = _NOW.match(text)
    if now_match:
        base = time.time_ns() if now_ns is None else now_ns
        inner = now_match.group(1).strip()
        return base + (parse_duration_ns(inner) if inner else 0)
    if re.fullmatch(r"-?\d+", text):
        return int(text)
    return _parse_rfc3339_ns(text)


def _parse_rfc3339_ns(text: str) -> int:
    match = _FRACTION.match(text)
    if not match:
        raise QueryError(
            f"bad time {text!r}: expected now(), now(-2s), RFC 3339 "
            "(2026-11-22T14:00:00.5Z) or integer nanoseconds since the epoch"
        )
    head, fraction, zone = match.groups()
    try:
        whole = datetime.fromisoformat(head + ("+00:00" if zone.upper() == "Z" else zone))
    except ValueError as exc:
        raise QueryError(f"bad time {text!r}: {exc}") from exc
    frac_ns = int((fraction or "0").ljust(9, "0"))
    return int(whole.timestamp()) * 1_000_000_000 + frac_ns


def parse_time_range(text: str, now_ns: int | None = None) -> TimeRange:
    """Parse a ``_time`` value into a closed integer range."""
    value = text.strip()
    if len(value) < 4 or value[0] not in "[]" or value[-1] not in "[]":
        raise QueryError(
            f"bad time range {text!r}: write [start..end] (either end may be empty), "
            "]start..end[ for exclusive ends, or [start;duration]"
        )
    now = time.time_ns() if now_ns is None else now_ns
    start_open, end_open = value[0] == "]", value[-1] == "["
    body = value[1:-1]
    if ".." in body:
        left, _, right = body.partition("..")
        start = parse_time_ns(left, now) if left.strip() else None
        end = parse_time_ns(right, now) if right.strip() else None
    elif ";" in body:
        left, _, right = body.partition(";")
        start = parse_time_ns(left, now)
        end = start + parse_duration_ns(right)
    else:
        raise QueryError(f"bad time range {text!r}: missing '..' or ';' between the ends")
    if start is not None and start_open:
        start += 1
    if end is not None and end_open:
        end -= 1
    if start is not None and end is not None and start > end:
        raise QueryError(f"bad time range {text!r}: it ends before it starts")
    return TimeRange(start, end)
