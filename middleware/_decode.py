"""One bounded, typed decoder for what framegate reads back from the network as JSON: a
service's ``@info`` description (``framegate info``, ``ls``, the one-producer-per-name check,
who may refuse a subscription).

A peer can answer anything, so every reply passes the same gate before a field is used:

1. size: at most ``MAX_REPLY_BYTES`` (an ``@info`` of 256 + 256 subscriptions per buffer
   fits many times over);
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

from ._clock import ClockSample
from ._errors import QueryError
from ._records import (
    BufferInfo,
    BufferLimits,
    Retention,
    Rewind,
    ServiceInfo,
    SubscriptionInfo,
    SubscriptionMode,
)

MAX_REPLY_BYTES = 4 << 20
MAX_DEPTH = 32
# Characters of one string field (names, hosts, reasons) at most.
MAX_TEXT = 1024
_INT_END = 2**63
# Control characters and lone surrogates, and the invisible ones that reorder or hide what
# a terminal shows (bidi overrides and isolates, zero-width marks, line separators): a peer
# could make a name read as another.
_UNPRINTABLE = re.compile(
    "[\x00-\x1f\x7f-\x9f\ud800-\udfff\u200b-\u200f\u2028-\u202e\u2060-\u2069\ufeff]"
)
# Thread names of a service listed at most (``ServiceInfo.threads``).
MAX_THREADS = 256

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


def _field(
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
    if kind is int and not least <= value < _INT_END:
        raise QueryError(f"{what}: {key!r} is {_short(value)}, outside {least} .. 2^63 - 1")
    if kind is float and not 0.0 <= value < math.inf:
        raise QueryError(f"{what}: {key!r} is {value}, not a finite number >= 0")
    if kind is str:
        _check_text(value, f"{what}: {key!r}")
    return value  # type: ignore[no-any-return]


def _check_text(value: str, what: str) -> None:
    if len(value) > MAX_TEXT:
        raise QueryError(f"{what} is {len(value)} characters long, more than {MAX_TEXT}")
    bad = _UNPRINTABLE.search(value)
    if bad is not None:
        raise QueryError(f"{what} holds an unprintable character (U+{ord(bad.group()):04X})")


def is_text(value: object) -> bool:
    """Whether ``value`` passes ``_check_text``: what a peer may put in a name that framegate
    repeats to others (a token's id and holder, a reason)."""
    return isinstance(value, str) and len(value) <= MAX_TEXT and not _UNPRINTABLE.search(value)


def printable(text: str, limit: int = MAX_TEXT) -> str:
    """A peer's text fit for one line of a terminal or log: each unprintable character (a
    newline, an escape sequence's ESC, a lone surrogate) written as its escape, at most
    ``limit`` characters kept."""
    clipped = text[:limit] + ("..." if len(text) > limit else "")
    return _UNPRINTABLE.sub(lambda m: repr(m.group())[1:-1], clipped)


def _short(value: int) -> str:
    text = str(value)
    return text if len(text) <= 24 else f"{text[:12]}...({len(text)} digits)"


def _mode(text: str, what: str) -> SubscriptionMode:
    try:
        return SubscriptionMode(text)
    except ValueError:
        raise QueryError(f"{what}: unknown subscription mode {text[:40]!r}") from None


def _subscription(s: Any, what: str) -> SubscriptionInfo:
    return SubscriptionInfo(
        _field(s, "id", str, what),
        _mode(_field(s, "mode", str, what), what),
        _field(s, "queue_size", int, what, least=1),
        _field(s, "queued", int, what),
        node=_field(s, "node", str, what, optional=True),
        host=_field(s, "host", str, what, optional=True),
    )


def _retention(body: Any, what: str) -> Retention:
    if not isinstance(body, dict):
        raise QueryError(f"{what}: 'retention' is not an object")
    try:
        return Retention(**body)
    except (TypeError, ValueError) as exc:
        raise QueryError(f"{what}: bad 'retention' ({exc})") from None


def _limits(body: Any, what: str) -> BufferLimits | None:
    if body is None:
        return None
    names = (
        "flow_registrations",
        "observe_registrations",
        "queue_budget",
        "flow_queue_max",
        "large_push_per_holder",
        "large_push_total",
    )
    numbers = {name: _field(body, name, int, what) for name in names}
    inbox = _field(body, "control_inbox_bytes", int, what, optional=True)  # newer producers
    return BufferLimits(
        **numbers,
        holder_share=_field(body, "holder_share", str, what),
        control_inbox_bytes=inbox or 0,
    )


# Rewinds read from one buffer's description at most (a producer lists its last 16).
_REWINDS_READ = 64


def _rewind(body: Any, what: str) -> Rewind:
    return Rewind(
        _field(body, "after_ns", int, what),
        _field(body, "count", int, what),
        _field(body, "first_ns", int, what, optional=True),
        _field(body, "last_ns", int, what, optional=True),
        _field(body, "cause", str, what),
    )


def _buffer(b: Any, what: str) -> BufferInfo:
    name = _field(b, "buffer", str, what)
    what = f"{what}, buffer {name[:64]!r}"
    subs = _field(b, "subscriptions", list, what)
    skipped = _field(b, "skipped", dict, what, optional=True) or {}
    return BufferInfo(
        service=_field(b, "service", str, what),
        buffer=name,
        kind=_field(b, "kind", str, what),
        retention=_retention(_field(b, "retention", dict, what), what),
        count=_field(b, "count", int, what),
        payload_bytes=_field(b, "payload_bytes", int, what),
        oldest_ns=_field(b, "oldest_ns", int, what, optional=True),
        newest_ns=_field(b, "newest_ns", int, what, optional=True),
        rate_hz=_field(b, "rate_hz", float, what),
        puts=_field(b, "puts", int, what),
        refused=_field(b, "refused", int, what),
        rejected=_field(b, "rejected", int, what),
        subscriptions=tuple(_subscription(s, what) for s in subs),
        skipped={_key(k, what): _field(skipped, k, int, what) for k in skipped},
        refused_subscriptions=_field(b, "refused_subscriptions", int, what, optional=True) or 0,
        limits=_limits(b.get("limits"), what),
        dropped_messages=_field(b, "dropped_messages", int, what, optional=True) or 0,
        bad_messages=_field(b, "bad_messages", int, what, optional=True) or 0,
        rewinds=tuple(
            _rewind(r, what)
            for r in (_field(b, "rewinds", list, what, optional=True) or [])[:_REWINDS_READ]
        ),
    )


def decode_service_info(raw: bytes, start_ns: int, end_ns: int, *, service: str) -> ServiceInfo:
    """A service's ``@info`` reply, asked at ``start_ns`` and answered by ``end_ns`` (local
    clock), as a ``ServiceInfo``; QueryError (one line) if it is not a valid description."""
    what = f"the description of {service[:64]!r}"
    body = decode_json(raw, what)
    clock_ns = _field(body, "clock_ns", int, what)
    clock = body.get("clock")
    steps = lead = None
    if isinstance(clock, dict):
        steps = _field(clock, "steps", int, what)
        lead = _field(clock, "lead_ns", int, what, least=-_INT_END)
    sample = ClockSample.from_times(start_ns, clock_ns, end_ns)
    named = _field(body, "service", str, what)
    if named != service:  # a peer's reply on another key (or on ``*``) may not pose as it
        raise QueryError(f"{what}: it names itself {printable(named, 64)!r}")
    return ServiceInfo(
        service=named,
        host=_field(body, "host", str, what),
        pid=_field(body, "pid", int, what),
        clock_ns=clock_ns,
        buffers=tuple(_buffer(b, what) for b in _field(body, "buffers", list, what)),
        clock_offset_ns=sample.offset_ns,
        round_trip_ns=sample.round_trip_ns,
        clock_steps=steps,
        clock_lead_ns=lead,
        threads=_names(body.get("threads")),
        listen=_names(body.get("listen")) or (),
        dropped_queries=(
            _field(body, "dropped_queries", int, what) if "dropped_queries" in body else 0
        ),
    )


def _key(key: str, what: str) -> str:
    _check_text(key, f"{what}: a key")
    return key


def _names(value: Any) -> tuple[str, ...] | None:
    """A list of printable strings as a tuple (at most ``MAX_THREADS``); None for anything
    else (an old or odd peer)."""
    if not isinstance(value, list):
        return None
    names = value[:MAX_THREADS]
    if all(is_text(v) for v in names):
        return tuple(names)
    return None


def decode_instance(raw: bytes, service: str) -> dict[str, Any]:
    """What the one-producer-per-name check needs of an ``@info`` reply: host, pid,
    instance and start time, typed; QueryError if the reply is not ``service``'s."""
    what = f"the description of {service[:64]!r}"
    body = decode_json(raw, what)
    if _field(body, "service", str, what) != service:
        raise QueryError(f"{what}: the reply names another service")
    return {
        "host": _field(body, "host", str, what),
        "pid": _field(body, "pid", int, what),
        "instance": _field(body, "instance", str, what),
        "started_ns": _field(body, "started_ns", int, what),
    }
