"""Typed records that cross the middleware's public edge."""

from __future__ import annotations

import enum
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, fields, is_dataclass
from typing import Any


@dataclass(frozen=True, slots=True)
class DataObject:
    """One element of a buffer: its key, a binary payload and XML metadata.

    ``payload`` is held by reference, never copied by the buffer.
    """

    timestamp_ns: int
    payload: bytes
    metadata: bytes

    @property
    def size_bytes(self) -> int:
        """Payload plus metadata bytes: what retention by size counts."""
        return len(self.payload) + len(self.metadata)


@dataclass(frozen=True, slots=True)
class Retention:
    """How much a buffer keeps; the oldest elements are evicted first.

    ``max_age_ns`` is measured back from the newest element, so a paused producer keeps its
    history. ``max_payload_bytes`` refuses a single oversized element outright.
    """

    max_count: int | None = 1000
    max_bytes: int | None = 512 * 1024 * 1024
    max_age_ns: int | None = None
    max_payload_bytes: int = 64 * 1024 * 1024

    def __post_init__(self) -> None:
        # Whole numbers only (``type is int`` refuses bools too): a retention read from a
        # file or a peer may say 1.5, NaN or true, and a float count breaks eviction later.
        for name in ("max_count", "max_bytes", "max_age_ns", "max_payload_bytes"):
            value = getattr(self, name)
            if value is None and name != "max_payload_bytes":
                continue
            # Below 2^63 as every int on the wire: a peer's 10^400 is no retention, and
            # breaks whatever formats it as a float.
            if type(value) is not int or not 1 <= value < 2**63:
                none = "" if name == "max_payload_bytes" else " or None"
                got = repr(value) if len(repr(value)) <= 40 else f"{repr(value)[:24]}..."
                raise ValueError(
                    f"Retention.{name} must be an int in 1 .. 2^63 - 1{none}, got {got}"
                )


class SubscriptionMode(enum.Enum):
    """How a subscription relates to the producer.

    FLOW: takes part in flow control; while its queue is full the producer is refused
    (the paper's rule). OBSERVE: never holds the producer back; when its queue is full the
    oldest notification makes room for the newest (keep-last), counted as missed (for
    tools inspecting a running robot).
    """

    FLOW = "flow"
    OBSERVE = "observe"
    DEFAULT = FLOW


@dataclass(frozen=True, slots=True)
class Notification:
    """An availability notification: a new element exists in ``service/buffer``.

    ``element`` is filled when the producer sent the element inline (small payloads);
    otherwise fetch it with ``Subscription.fetch``. ``missed`` counts elements this
    subscription lost before this one: an observer's pushed out of its full queue, and,
    for either mode, those stored while its token had lapsed (docs/limits.md).
    ``epoch``: the registration it came with (``Subscription.registered_epoch`` names the
    one the producer greeted; a notification of another epoch is an old registration's, or
    a peer's that made one up).
    """

    service: str
    buffer: str
    timestamp_ns: int
    seq: int
    metadata: bytes | None = None
    element: DataObject | None = None
    missed: int = 0
    epoch: str = ""


@dataclass(frozen=True, slots=True)
class SubscriptionInfo:
    """A subscription as its producer sees it.

    ``taken_ns``: when the producer last learnt that the subscriber took something (an ack
    that freed credit), on this process's ``time.monotonic_ns`` clock; None if never, and
    for subscriptions reported by another process (its clock means nothing here).
    """

    subscription_id: str
    mode: SubscriptionMode
    queue_size: int
    queued: int
    taken_ns: int | None = None
    # The node (service name, or "" for an anonymous client) and host holding the
    # subscription, as its token says; None when the token does not say (older peers).
    node: str | None = None
    host: str | None = None

    @property
    def fill(self) -> float:
        """queued / queue_size in [0, 1]: the paper's load indicator."""
        return min(1.0, self.queued / self.queue_size)


def tightest_flow(subscriptions: Iterable[SubscriptionInfo]) -> SubscriptionInfo | None:
    """The flow-controlled subscription that will refuse the producer first (fewest free
    slots; the fullest of those), or None with none: whose ``fill`` is *the* load
    indicator (the mediator's load, the demo's)."""
    flows = [s for s in subscriptions if s.mode is SubscriptionMode.FLOW]
    return min(flows, key=lambda s: (s.queue_size - s.queued, -s.fill), default=None)


@dataclass(frozen=True, slots=True)
class Rewind:
    """Elements a producer removed because its input started over earlier in time
    (``Producer.discard_after``): every element stamped after ``after_ns``, ``count`` of
    them from ``first_ns`` to ``last_ns`` (None: there were none), and why."""

    after_ns: int
    count: int
    first_ns: int | None
    last_ns: int | None
    cause: str

    @classmethod
    def of(cls, after_ns: int, removed: Sequence[DataObject], cause: str) -> Rewind:
        """The record of ``removed`` (what ``discard_after(after_ns)`` took away)."""
        stamps = [e.timestamp_ns for e in removed]
        return cls(
            after_ns, len(stamps), min(stamps, default=None), max(stamps, default=None), cause
        )


@dataclass(frozen=True, slots=True)
class BufferLimits:
    """The limits a producer applies to subscriptions (docs/limits.md explains each).

    One holder (a token's ``<node>~<host>``) may hold at most half of what the other
    holders leave free of the queue budget and of each pool of slots."""

    # Every number as the producer applies it (its values live with the protocol's shares,
    # ``_protocol_shares``; none is repeated here).
    flow_registrations: int
    observe_registrations: int
    queue_budget: int
    # The largest flow queue one subscriber can get (a holder's share of an idle producer).
    flow_queue_max: int
    # Registrations that get payloads above the producer's inline limit pushed.
    large_push_per_holder: int
    large_push_total: int
    holder_share: str = "half of what other holders leave free"
    # The most the producer's control inboxes (acks, subscription tokens) hold, whatever a
    # peer sends; 0 where a producer does not say. Zenoh's own share comes on top
    # (docs/limits.md: its receive buffers, each local peer's shared-memory pool).
    control_inbox_bytes: int = 0


@dataclass(frozen=True, slots=True)
class BufferInfo:
    """What ``info`` reports of one buffer."""

    service: str
    buffer: str
    kind: str
    retention: Retention
    count: int
    payload_bytes: int
    oldest_ns: int | None
    newest_ns: int | None
    rate_hz: float
    puts: int
    refused: int
    rejected: int
    subscriptions: tuple[SubscriptionInfo, ...] = field(default=())
    # Elements the offering service chose not to put, by reason (e.g. the camera's
    # ``late``: a frame it could not produce in time), counted with ``Producer.count_skip``.
    skipped: dict[str, int] = field(default_factory=dict)
    # Subscription tokens this producer refused (a limit: slots or the queue budget).
    refused_subscriptions: int = 0
    # The latest rewinds (``Producer.discard_after``), oldest first: what was removed.
    rewinds: tuple[Rewind, ...] = field(default=())
    # The limits it refuses by (None from a peer that does not report them).
    limits: BufferLimits | None = None
    # Control messages (acks, subscription tokens) dropped on Zenoh's thread, before they
    # are buffered: larger than their format allows, an ack whose first byte is not an ack's
    # (garbage) or that repeats the last one of its key, or one arriving at a full inbox.
    dropped_messages: int = 0
    # Control messages read by the producer and ignored: an ack that passed the first byte
    # but does not decode, or a token no client could read back.
    bad_messages: int = 0
    # Acks ignored as of no live registration (from before a subscription re-registered, or
    # forged) or acking more than was sent (a forgery).
    foreign_acks: int = 0
    # Subscription tokens declared and withdrawn before the producer looked (churn): they
    # cost no registration (``TokenInbox``).
    collapsed_tokens: int = 0

    @property
    def name(self) -> str:
        """``service/buffer``."""
        return f"{self.service}/{self.buffer}"

    def to_json(self) -> dict[str, Any]:
        """This buffer as JSON values (``json_form``)."""
        return json_form(self)  # type: ignore[no-any-return]


@dataclass(frozen=True, slots=True)
class ServiceInfo:
    """A live service: its buffers, where it runs and its clock when it answered."""

    service: str
    host: str
    pid: int
    clock_ns: int
    buffers: tuple[BufferInfo, ...]
    clock_offset_ns: int | None = None
    round_trip_ns: int | None = None
    # Steps of the service's system clock it absorbed, and how far ahead of its system
    # clock it runs while slewing back (docs/time.md); None from old peers.
    clock_steps: int | None = None
    clock_lead_ns: int | None = None
    # The names of the service process's Python threads (docs/threads.md); None from old
    # peers.
    threads: tuple[str, ...] | None = None
    # What the service's process listens on, from its operating system (``tcp/HOST:PORT``);
    # empty from old peers.
    listen: tuple[str, ...] = ()
    # Queries the service ended unanswered because more were waiting than its inbox holds
    # (a flood: ``QueryInbox``); 0 from old peers.
    dropped_queries: int = 0
    # The size of the service's last clock step (+ forward, - backward; see ``clock_steps``),
    # last so that positional construction stays as it was; None from old peers.
    clock_last_step_ns: int | None = None

    def to_json(self) -> dict[str, Any]:
        """This service and its buffers as JSON values (``json_form``)."""
        return json_form(self)  # type: ignore[no-any-return]


def json_form(value: Any) -> Any:
    """A record (or what it holds) as JSON values: every dataclass field by its name, an enum
    by its value, a tuple as a list, and a subscription's ``fill`` beside its fields (the load
    indicator, so that no reader computes it again). The one JSON form of these records:
    ``framegate ls --json`` and ``info --json`` print it, the ``@info`` reply carries it
    (``_info_codec``), so a field added to a record is sent and shown with no other edit."""
    if is_dataclass(value) and not isinstance(value, type):
        out = {f.name: json_form(getattr(value, f.name)) for f in fields(value)}
        if isinstance(value, SubscriptionInfo):
            out["fill"] = value.fill
        return out
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, list | tuple):
        return [json_form(v) for v in value]
    if isinstance(value, dict):
        return {k: json_form(v) for k, v in value.items()}
    return value


# -- hot-path builders --------------------------------------------------------------------
# A frozen dataclass's generated ``__init__`` sets each field through
# ``object.__setattr__`` looked up per field: 0.38 us for a DataObject and 0.75 us for a
# Notification on a 2-core machine, built once per element put and twice per element taken.
# These set the slots directly (0.24 / 0.40 us) and give the same objects; a test checks
# that they set every field.
_new = object.__new__
_data_slots = tuple(vars(DataObject)[n].__set__ for n in ("timestamp_ns", "payload", "metadata"))
_note_slots = tuple(
    vars(Notification)[n].__set__
    for n in ("service", "buffer", "timestamp_ns", "seq", "metadata", "element", "missed", "epoch")
)


def data_object(
    timestamp_ns: int,
    payload: bytes,
    metadata: bytes,
    _new: Any = _new,
    _slots: tuple[Any, ...] = _data_slots,
) -> DataObject:
    """``DataObject(timestamp_ns, payload, metadata)``, faster (see above)."""
    obj = _new(DataObject)
    set_t, set_p, set_m = _slots
    set_t(obj, timestamp_ns)
    set_p(obj, payload)
    set_m(obj, metadata)
    return obj  # type: ignore[no-any-return]


def notification(
    service: str,
    buffer: str,
    timestamp_ns: int,
    seq: int,
    metadata: bytes | None,
    element: DataObject | None,
    missed: int,
    epoch: str,
    _new: Any = _new,
    _slots: tuple[Any, ...] = _note_slots,
) -> Notification:
    """``Notification(...)`` with every field given, faster (see above)."""
    obj = _new(Notification)
    s0, s1, s2, s3, s4, s5, s6, s7 = _slots
    s0(obj, service)
    s1(obj, buffer)
    s2(obj, timestamp_ns)
    s3(obj, seq)
    s4(obj, metadata)
    s5(obj, element)
    s6(obj, missed)
    s7(obj, epoch)
    return obj  # type: ignore[no-any-return]
