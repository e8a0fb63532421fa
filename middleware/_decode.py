"""The one bounded, typed gate for what framegate reads back from the network as JSON: a
service's ``@info`` description (``framegate info``, ``ls``, the one-producer-per-name check,
who may refuse a subscription), whose records ``_info_codec`` reads field by field through
``typed_field`` here.

A peer can answer anything, so every reply passes the same gate before a field is used:

1. size: at most ``MAX_REPLY_BYTES`` (a service's own description repeats at most
   ``_info_codec.SHOWN_TEXT`` characters of each name a peer's token gives, so one buffer's
   256 + 256 subscriptions take at most ``BUFFER_DESCRIPTION_BYTES``, 512 KiB);
2. UTF-8;
3. nesting: at most ``MAX_DEPTH`` levels of brackets, counted before parsing (Python's
   parser recurses per level: 100,000 nested brackets would raise ``RecursionError``);
4. JSON, then the required keys with their types, field by field, and what a value of
   that type may be: an int within 0 .. 2^63 - 1 (stamps, counters, sizes; a queue at
   least 1), a float finite and not negative, a string at most ``MAX_TEXT`` characters
   with no control character or lone surrogate (a terminal would run an escape sequence,
   and printing a surrogate raises).

Every failure is one ``QueryError`` whose one-line message names the service (or what was
being decoded) and the first thing that is wrong; nothing else escapes. The binary
messages of the protocol (notification headers, acks, element attachments) are msgpack with
their own type checks in ``_wire``; msgpack bounds nesting and sizes itself.
"""

from __future__ import annotations

import itertools
import json
import math
import re
from typing import Any, TypeVar

from ._errors import QueryError

MAX_REPLY_BYTES = 4 << 20
MAX_DEPTH = 32
# Characters of one string field (names, hosts, reasons) at most.
MAX_TEXT = 1024
INT_END = 2**63
# Control characters and lone surrogates, and the invisible ones that reorder or hide what
# a terminal shows (bidi overrides and isolates, zero-width marks, line separators): a peer
# could make a name read as another.
_UNPRINTABLE = re.compile(
    "[\x00-\x1f\x7f-\x9f\ud800-\udfff\u200b-\u200f\u2028-\u202e\u2060-\u2069\ufeff]"
)

T = TypeVar("T")
# JSON strings (escapes included): removed before brackets are counted.
_STRINGS = re.compile(rb'"(?:[^"\\]|\\.)*"', re.DOTALL)
_DEPTH = {ord("["): 1, ord("{"): 1, ord("]"): -1, ord("}"): -1}
_NOT_BRACKETS = bytes(b for b in range(256) if b not in _DEPTH)


def decode_json(raw: bytes, what: str) -> Any:
    """``raw`` as JSON within the bounds above; QueryError naming ``what`` if not."""
    if len(raw) > MAX_REPLY_BYTES:
        raise QueryError(f"{what}: reply of {len(raw)} bytes exceeds {MAX_REPLY_BYTES}")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise QueryError(f"{what}: reply is not UTF-8 (byte {exc.start})") from None
    brackets = _STRINGS.sub(b"", raw).translate(None, _NOT_BRACKETS)
    depth = max(itertools.accumulate(_DEPTH[b] for b in brackets), default=0)
    if depth > MAX_DEPTH:
        raise QueryError(f"{what}: reply nests {depth} levels deep, more than {MAX_DEPTH}")
    try:
        return json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise QueryError(f"{what}: reply is not JSON ({exc})") from None


def typed_field(
    body: Any, key: str, kind: type[T], what: str, *, optional: bool = False, least: int = 0
) -> T:
    """``body[key]`` as ``kind`` within the bounds of the module doc (an int at least
    ``least``, which may be negative for a signed quantity)."""
    if not isinstance(body, dict):
        raise QueryError(f"{what}: expected an object, got {type(body).__name__}")
    if key not in body or (optional and body[key] is None):
        if optional:
            return None  # type: ignore[return-value]
        raise QueryError(f"{what}: reply lacks {key!r}")
    value = body[key]
    # JSON has one number type for ints and floats; bool is an int to Python, never here.
    ok = isinstance(value, kind) and not (isinstance(value, bool) and kind is not bool)
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value, ok = float(value), True
    if not ok:
        raise QueryError(f"{what}: {key!r} is {type(value).__name__}, not {kind.__name__}")
    if kind is int and not least <= value < INT_END:
        raise QueryError(f"{what}: {key!r} is {_short(value)}, outside {least} .. 2^63 - 1")
    if kind is float and not 0.0 <= value < math.inf:
        raise QueryError(f"{what}: {key!r} is {value}, not a finite number >= 0")
    if kind is str:
        check_text(value, f"{what}: {key!r}")
    return value  # type: ignore[no-any-return]


def check_text(value: str, what: str) -> None:
    """QueryError naming ``what`` unless ``value`` is printable and at most ``MAX_TEXT``."""
    if len(value) > MAX_TEXT:
        raise QueryError(f"{what} is {len(value)} characters long, more than {MAX_TEXT}")
    bad = _UNPRINTABLE.search(value)
    if bad is not None:
        raise QueryError(f"{what} holds an unprintable character (U+{ord(bad.group()):04X})")


def is_text(value: object) -> bool:
    """Whether ``value`` passes ``check_text``: what a peer may put in a name that framegate
    repeats to others (a token's id and holder, a reason)."""
    return isinstance(value, str) and len(value) <= MAX_TEXT and not _UNPRINTABLE.search(value)


def printable(text: str, limit: int = MAX_TEXT) -> str:
    """A peer's text fit for one line of a terminal or log: each unprintable character (a
    newline, an escape sequence's ESC, a lone surrogate) written as its escape, at most
    ``limit`` characters kept."""
    clipped = text[:limit] + ("..." if len(text) > limit else "")
    return _UNPRINTABLE.sub(lambda m: repr(m.group())[1:-1], clipped)


# Names a message lists at most (any peer can add live services: 300 tokens made one
# "live services: ..." line of 300 names; 65,536 of 1,024 characters would be 64 MiB).
LISTED_NAMES = 20


def listing(names: list[str], most: int = LISTED_NAMES) -> str:
    """``names`` for one line of a message: at most ``most`` of them, each printable and
    cut short, then how many more; ``none`` if there are none."""
    if not names:
        return "none"
    shown = ", ".join(printable(name, 64) for name in names[:most])
    rest = len(names) - most
    return shown + (f" and {rest} more" if rest > 0 else "")


def _short(value: int) -> str:
    text = str(value)
    return text if len(text) <= 24 else f"{text[:12]}...({len(text)} digits)"
