"""A service's ``@info`` reply both ways: what a service sends (``encode_service_info``) and
what reads it back into ``ServiceInfo`` and ``BufferInfo`` (``decode_service_info``).

The reply carries the records' one JSON form (``_records.json_form``, which ``framegate
ls --json`` and ``info --json`` print too), with three things spelt the wire's own way, as
every peer's decoder reads them: a subscription's id is ``id``, its ``taken_ns`` is left out
(this process's monotonic clock means nothing to a peer), and the clock's status is one
``clock`` object. A test checks that what is encoded decodes to the same records, so a
field added to a record and not read back here fails it.

Decoding goes through ``_decode``'s gate: a peer may answer anything, so every field is
read with its type and bounds, and any failure is one ``QueryError`` (see that module).
"""

from __future__ import annotations

import json
from typing import Any

from ._clock import ClockSample, ClockStatus
from ._config import NAME
from ._decode import INT_END, check_text, decode_json, is_text, printable, typed_field
from ._errors import QueryError
from ._records import (
    BufferInfo,
    BufferLimits,
    Retention,
    Rewind,
    ServiceInfo,
    SubscriptionInfo,
    SubscriptionMode,
    json_form,
)

# Thread names of a service read at most (``ServiceInfo.threads``).
MAX_THREADS = 256
# Rewinds read from one buffer's description at most (a producer lists its last 16).
_REWINDS_READ = 64
# Characters of a subscription's id, node and host that a description repeats, at most (the
# rest cut, marked with an ellipsis). A token may carry names of up to 1,024 characters,
# and 512 such tokens on each of two buffers, named in four-byte characters that JSON
# escaped as twelve bytes each, made a camera's description 5.9 MB: beyond what any client
# reads (``MAX_REPLY_BYTES``), so ``ls`` and ``info`` left the camera out and a mediator
# never learnt its clock (every frame ``clock-unmeasured``). Honest ids are 12 characters,
# node and host names a few dozen; clipped, and written as UTF-8, one buffer's description
# stays within ``BUFFER_DESCRIPTION_BYTES`` whatever peers declare.
SHOWN_TEXT = 64
BUFFER_DESCRIPTION_BYTES = 512 * 1024


# -- encoding ------------------------------------------------------------------------------
def _wire_buffer(info: BufferInfo) -> dict[str, Any]:
    data: dict[str, Any] = json_form(info)
    subs = data["subscriptions"]
    for i, sub in enumerate(subs):
        del sub["taken_ns"]
        for name in ("node", "host"):
            sub[name] = _shown(sub[name])
        subs[i] = {"id": _shown(sub.pop("subscription_id")), **sub}
    return data


def _shown(text: str | None) -> str | None:
    """A peer's name as a description repeats it: at most ``SHOWN_TEXT`` characters."""
    if text is None or len(text) <= SHOWN_TEXT:
        return text
    return text[:SHOWN_TEXT] + "\u2026"


def encode_service_info(
    info: ServiceInfo, clock: ClockStatus, *, instance: str, started_ns: int
) -> bytes:
    """A service's ``@info`` reply: ``info`` (its clock fields aside: ``clock`` says them),
    the process's clock status, and the instance and start that tell two instances of one
    name apart (``decode_instance``)."""
    body = {
        "service": info.service,
        "host": info.host,
        "pid": info.pid,
        "clock_ns": info.clock_ns,
        "clock": json_form(clock),
        "instance": instance,
        "started_ns": started_ns,
        "buffers": [_wire_buffer(b) for b in info.buffers],
        "listen": json_form(info.listen),
        "threads": json_form(info.threads),
        "dropped_queries": info.dropped_queries,
    }
    # UTF-8 as it is: JSON's \u escapes made a four-byte character of a peer's name twelve.
    return json.dumps(body, ensure_ascii=False).encode("utf-8")


# -- decoding ------------------------------------------------------------------------------
def decode_service_info(raw: bytes, start_ns: int, end_ns: int, *, service: str) -> ServiceInfo:
    """A service's ``@info`` reply, asked at ``start_ns`` and answered by ``end_ns`` (local
    clock), as a ``ServiceInfo``; QueryError (one line) if it is not a valid description."""
    what = f"the description of {service[:64]!r}"
    body = decode_json(raw, what)
    clock_ns = typed_field(body, "clock_ns", int, what)
    clock = body.get("clock")
    steps = lead = last_step = None
    if isinstance(clock, dict):
        steps = typed_field(clock, "steps", int, what)
        lead = typed_field(clock, "lead_ns", int, what, least=-INT_END)
        last_step = typed_field(clock, "last_step_ns", int, what, optional=True, least=-INT_END)
    sample = ClockSample.from_times(start_ns, clock_ns, end_ns)
    named = typed_field(body, "service", str, what)
    if named != service:  # a peer's reply on another key (or on ``*``) may not pose as it
        raise QueryError(f"{what}: it names itself {printable(named, 64)!r}")
    return ServiceInfo(
        service=named,
        host=typed_field(body, "host", str, what),
        pid=typed_field(body, "pid", int, what),
        clock_ns=clock_ns,
        buffers=_buffers(typed_field(body, "buffers", list, what), service, what),
        clock_offset_ns=sample.offset_ns,
        round_trip_ns=sample.round_trip_ns,
        clock_steps=steps,
        clock_lead_ns=lead,
        clock_last_step_ns=last_step,
        threads=_names(body.get("threads")),
        listen=_names(body.get("listen")) or (),
        dropped_queries=(
            typed_field(body, "dropped_queries", int, what) if "dropped_queries" in body else 0
        ),
    )


def decode_instance(raw: bytes, service: str) -> dict[str, Any]:
    """What the one-producer-per-name check needs of an ``@info`` reply: host, pid,
    instance and start time, typed; QueryError if the reply is not ``service``'s."""
    what = f"the description of {service[:64]!r}"
    body = decode_json(raw, what)
    if typed_field(body, "service", str, what) != service:
        raise QueryError(f"{what}: the reply names another service")
    return {
        "host": typed_field(body, "host", str, what),
        "pid": typed_field(body, "pid", int, what),
        "instance": typed_field(body, "instance", str, what),
        "started_ns": typed_field(body, "started_ns", int, what),
    }


def _buffers(raw: list[Any], service: str, what: str) -> tuple[BufferInfo, ...]:
    """A description's buffers: each the described service's own, each named once (a
    peer's description may not list another service's buffer, or one buffer twice: a
    recording of ``--all`` would hold it twice)."""
    buffers = tuple(_buffer(b, service, what) for b in raw)
    twice = first_repeated([b.buffer for b in buffers])
    if twice is not None:
        raise QueryError(f"{what}: it lists buffer {twice!r} more than once")
    return buffers


def first_repeated(names: list[str]) -> str | None:
    """The first name of ``names`` that comes again, in one pass: found with ``count`` per
    name, a peer's description of 13,707 buffers (3.8 MB) naming its last one twice took
    5.0 s to decode instead of 0.8."""
    seen: set[str] = set()
    for name in names:
        if name in seen:
            return name
        seen.add(name)
    return None


def _buffer(b: Any, service: str, what: str) -> BufferInfo:
    name = typed_field(b, "buffer", str, what)
    if not NAME.fullmatch(name):  # no producer offers it: a peer's ``../../etc``
        raise QueryError(f"{what}: {name[:64]!r} is no buffer name")
    what = f"{what}, buffer {name[:64]!r}"
    owner = typed_field(b, "service", str, what)
    if owner != service:
        raise QueryError(f"{what}: it names another service, {printable(owner, 64)!r}")
    subs = typed_field(b, "subscriptions", list, what)
    skipped = typed_field(b, "skipped", dict, what, optional=True) or {}

    def counter(key: str) -> int:  # counters newer producers report; 0 from older ones
        return typed_field(b, key, int, what, optional=True) or 0

    return BufferInfo(
        service=owner,
        buffer=name,
        kind=typed_field(b, "kind", str, what),
        retention=_retention(typed_field(b, "retention", dict, what), what),
        count=typed_field(b, "count", int, what),
        payload_bytes=typed_field(b, "payload_bytes", int, what),
        oldest_ns=typed_field(b, "oldest_ns", int, what, optional=True),
        newest_ns=typed_field(b, "newest_ns", int, what, optional=True),
        rate_hz=typed_field(b, "rate_hz", float, what),
        puts=typed_field(b, "puts", int, what),
        refused=typed_field(b, "refused", int, what),
        rejected=typed_field(b, "rejected", int, what),
        subscriptions=tuple(_subscription(s, what) for s in subs),
        skipped={_key(k, what): typed_field(skipped, k, int, what) for k in skipped},
        refused_subscriptions=counter("refused_subscriptions"),
        limits=_limits(b.get("limits"), what),
        dropped_messages=counter("dropped_messages"),
        bad_messages=counter("bad_messages"),
        foreign_acks=counter("foreign_acks"),
        collapsed_tokens=counter("collapsed_tokens"),
        rewinds=tuple(
            _rewind(r, what)
            for r in (typed_field(b, "rewinds", list, what, optional=True) or [])[:_REWINDS_READ]
        ),
    )


def _subscription(s: Any, what: str) -> SubscriptionInfo:
    return SubscriptionInfo(
        typed_field(s, "id", str, what),
        _mode(typed_field(s, "mode", str, what), what),
        typed_field(s, "queue_size", int, what, least=1),
        typed_field(s, "queued", int, what),
        node=typed_field(s, "node", str, what, optional=True),
        host=typed_field(s, "host", str, what, optional=True),
    )


def _mode(text: str, what: str) -> SubscriptionMode:
    try:
        return SubscriptionMode(text)
    except ValueError:
        raise QueryError(f"{what}: unknown subscription mode {text[:40]!r}") from None


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
    numbers = {name: typed_field(body, name, int, what) for name in names}
    inbox = typed_field(body, "control_inbox_bytes", int, what, optional=True)  # newer producers
    return BufferLimits(
        **numbers,
        holder_share=typed_field(body, "holder_share", str, what),
        control_inbox_bytes=inbox or 0,
    )


def _rewind(body: Any, what: str) -> Rewind:
    return Rewind(
        typed_field(body, "after_ns", int, what),
        typed_field(body, "count", int, what),
        typed_field(body, "first_ns", int, what, optional=True),
        typed_field(body, "last_ns", int, what, optional=True),
        typed_field(body, "cause", str, what),
    )


def _key(key: str, what: str) -> str:
    check_text(key, f"{what}: a key")
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
