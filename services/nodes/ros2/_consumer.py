"""Closing the loop through a ROS 2 node's own results, pure: no Zenoh, no threads, no clock.

A ROS 2 vision node (a detector, a tracker) that copies its input image's ``header`` into
its results can tell the bridge, without knowing it, when it is done with an image: the
result whose ``header.stamp`` equals the image's. :class:`Outstanding` keeps the images
published to the node that are still without such a result (at most ``N``, the node's
``--consumer-queue``), the oldest with the deadline after which it frees its slot anyway
(``--consumer-timeout-ms`` from its turn: see there); :class:`DoneTopic` learns the result
topic's message type and type hash from the publishers' liveliness tokens (so any type whose
first field is a ``std_msgs/Header`` will do); :func:`decode_header` reads only that
leading header.

Matching is on the stamp alone: frame ids differ between nodes (``camera`` vs
``camera_optical_frame``) and carry no identity; the bridge's images have strictly
increasing stamps, so a stamp names one image.
"""

from __future__ import annotations

import struct
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, fields

from middleware import printable

from ._rmw import DEFAULT_DEPTH, MAX_REMARKS, REMARK_CHARS, EntityKind, History, parse_endpoint

# CDR encapsulation identifiers (first two bytes): plain CDR, big- and little-endian.
_CDR_BE, _CDR_LE = b"\x00\x00", b"\x00\x01"
_ENCAPSULATION_BYTES = 4
# A frame_id longer than this is no frame name (tf2 frame ids are short): a bad message.
MAX_FRAME_ID_BYTES = 4096
# The most of a result decode_header reads: a queued result keeps no more.
HEADER_MAX_BYTES = _ENCAPSULATION_BYTES + 12 + MAX_FRAME_ID_BYTES
# Expired stamps remembered, so that a result arriving after its timeout is told apart
# from one that matches no image of ours at all.
EXPIRED_MEMORY = 256


class HeaderError(ValueError):
    """A result whose leading ``std_msgs/Header`` cannot be read: the text says why."""


@dataclass(frozen=True, slots=True)
class Header:
    """The leading ``std_msgs/Header`` of a result message."""

    stamp_ns: int
    frame_id: str


def decode_header(raw: bytes) -> Header:
    """The ``std_msgs/Header`` a CDR message starts with (stamp sec/nanosec, frame_id).

    Fields of a plain-CDR struct follow each other aligned to their size from the end of the
    4-byte encapsulation header: ``int32 sec`` at 0, ``uint32 nanosec`` at 4, the frame id's
    ``uint32`` length (with its NUL) at 8 and its bytes from 12. HeaderError for anything
    else, so that a peer's bytes never raise anything but that.
    """
    if len(raw) < _ENCAPSULATION_BYTES + 12:
        raise HeaderError(f"{len(raw)} bytes cannot hold a CDR std_msgs/Header")
    kind = bytes(raw[:2])
    if kind not in (_CDR_BE, _CDR_LE):
        raise HeaderError(f"CDR encapsulation {kind.hex()} (expected 0000 or 0001, plain CDR)")
    order = "<" if kind == _CDR_LE else ">"
    sec, nanosec, length = struct.unpack_from(order + "iII", raw, _ENCAPSULATION_BYTES)
    if nanosec >= 1_000_000_000 or sec < 0:  # the rule of every stamp the bridge reads
        raise HeaderError(f"header.stamp sec={sec} nanosec={nanosec} is not a time")
    start = _ENCAPSULATION_BYTES + 12
    if not 1 <= length <= MAX_FRAME_ID_BYTES or start + length > len(raw):
        raise HeaderError(f"header.frame_id of {length} bytes in a {len(raw)}-byte message")
    text = bytes(raw[start : start + length])
    if text[-1] != 0:
        raise HeaderError("header.frame_id is not NUL-terminated")
    try:
        frame_id = text[:-1].decode()
    except UnicodeDecodeError as exc:
        raise HeaderError(f"header.frame_id is not UTF-8: {exc}") from exc
    return Header(sec * 1_000_000_000 + nanosec, frame_id)


def ros_type_of(dds_type: str) -> str:
    """``vision_msgs::msg::dds_::Detection2DArray_`` → ``vision_msgs/msg/Detection2DArray``;
    ValueError for a name that is not a DDS message type name."""
    parts = dds_type.split("::")
    if (
        len(parts) != 4
        or parts[2] != "dds_"
        or not parts[3].endswith("_")
        or not all(p.replace("_", "a").isalnum() for p in (parts[0], parts[1], parts[3]))
        or len(parts[3]) < 2
    ):
        raise ValueError(f"{dds_type!r} is not a DDS type name (pkg::msg::dds_::Name_)")
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


HEADER_TYPE = "std_msgs/msg/Header"
# Result types listened to on the result topic at most (a node publishes one).
MAX_RESULT_TYPES = 8


@dataclass(frozen=True, slots=True)
class ResultType:
    """The result topic's type as its publishers announce it."""

    ros_type: str
    type_hash: str


class DoneTopic:
    """Learns the result topic's types from the ROS graph's publisher tokens.

    Feed it every liveliness token (one caller at a time). Each type (and hash) a publisher
    of the topic announces is kept, up to ``MAX_RESULT_TYPES``; the loop's one subscription
    names the first in its token and takes every type on the topic, so a token anyone can
    declare never chooses which of the node's results are heard (tokens of made-up types
    declared first would otherwise shut the loop for good). Results are matched by their
    leading header alone, so a type that has none costs counted ``bad-result`` skips.
    """

    def __init__(self, topic: str, first_field: Callable[[str], str | None] | None = None) -> None:
        self.topic = topic
        # The type of a known message type's first field (None: a type the bridge does not
        # know, e.g. the node's own package's): one that is no Header is said at once.
        self._first_field = first_field or (lambda _ros_type: None)
        self.found: list[ResultType] = []
        self._said: set[tuple[str, str]] = set()

    def feed(self, token: str) -> str | None:
        """A one-line remark when a token names a type that is not listened to, else None."""
        endpoint = parse_endpoint(token)
        if endpoint is None or endpoint.kind is not EntityKind.PUBLISHER:
            return None
        if endpoint.topic != self.topic:
            return None
        try:
            ros_type = ros_type_of(endpoint.dds_type)
        except ValueError as exc:
            return self._once(endpoint.dds_type, endpoint.type_hash, f"ignored: {exc}")
        seen = ResultType(ros_type, endpoint.type_hash)
        if seen in self.found:
            return None
        if len(self.found) >= MAX_RESULT_TYPES:
            return self._once(
                endpoint.dds_type,
                endpoint.type_hash,
                f"a publisher announces {ros_type} ({endpoint.type_hash}); the bridge already "
                f"knows {MAX_RESULT_TYPES} types on this topic (it hears every type)",
            )
        self.found.append(seen)
        first = self._first_field(ros_type)
        if first is not None and first != HEADER_TYPE:
            # Listened to all the same (a type name may be redefined), but its results will
            # be ``bad-result`` or ``unmatched-result``: only the topic's other publishers'
            # results can free a slot (a lying peer's token does not stop the node's own).
            return self._once(
                endpoint.dds_type,
                endpoint.type_hash,
                f"a publisher announces {ros_type}, whose first field is {first}, not a "
                f"{HEADER_TYPE} with the image's stamp: no result of that type frees a slot "
                "(if it is the node's, every image waits --consumer-timeout-ms); publish a "
                "type that starts with the image's Header (as vision_msgs/msg/Detection2DArray)",
            )
        return None

    def _once(self, dds_type: str, type_hash: str, text: str) -> str | None:
        if (dds_type, type_hash) in self._said or len(self._said) > MAX_REMARKS:
            return None
        self._said.add((dds_type, type_hash))
        if len(self._said) > MAX_REMARKS:  # a peer's made-up types: bounded lines and memory
            return f"{self.topic}: {MAX_REMARKS} ignored types said; further ones are not logged"
        return printable(f"{self.topic}: {text}", REMARK_CHARS)


class InputDepthCheck:
    """Says once per node when a subscription of the node's input topic keeps fewer images
    than the node may hold (``--consumer-queue``): its middleware then drops images the
    bridge counts as outstanding, each holding a slot until the timeout (a "latest image
    only" detector subscribes with KEEP_LAST 1). Read from the subscription's liveliness
    token, whose QoS chunk carries its history and depth. Feed it every token (one caller
    at a time); pure, no Zenoh."""

    def __init__(self, topic: str, capacity: int) -> None:
        self.topic = topic
        self.capacity = capacity
        self._said: set[str] = set()

    def feed(self, token: str) -> str | None:
        endpoint = parse_endpoint(token)
        if endpoint is None or endpoint.kind is not EntityKind.SUBSCRIPTION:
            return None
        if endpoint.topic != self.topic or endpoint.session_id in self._said:
            return None
        depth = keep_last_depth(token)
        if depth is None or depth >= self.capacity or len(self._said) >= MAX_REMARKS:
            return None
        self._said.add(endpoint.session_id)
        return (
            f"a subscription of {self.topic} keeps {depth} image(s) (KEEP_LAST {depth}), "
            f"fewer than --consumer-queue {self.capacity}: images its node drops unread hold "
            f"their slot until --consumer-timeout-ms; subscribe with a depth of at least "
            f"{self.capacity}, or give --consumer-queue {max(1, depth)}"
        )


def keep_last_depth(token: str) -> int | None:
    """The KEEP_LAST depth in a liveliness token's QoS chunk (``rel:dur:history,depth:...``,
    an empty field rmw_zenoh's default); None for KEEP_ALL or a chunk that is not one."""
    parts = token.split("/")
    if len(parts) < 13:
        return None
    fields = parts[12].split(":")
    if len(fields) < 3:
        return None
    history, _, depth = fields[2].partition(",")
    if history not in ("", str(History.KEEP_LAST.value)):
        return None  # KEEP_ALL (or unknown): keeps what comes
    if not depth:
        return DEFAULT_DEPTH
    return int(depth) if depth.isdigit() and len(depth) < 10 else None


@dataclass(frozen=True, slots=True)
class ConsumerCounts:
    """What became of the images published to the node, and of its results."""

    published: int = 0
    answered: int = 0
    timed_out: int = 0
    late: int = 0  # results for an image whose slot had already timed out
    unmatched: int = 0  # results whose stamp names no image of ours
    bad: int = 0  # results whose header cannot be read
    outstanding: int = 0

    def text(self) -> str:
        """For a log line: ``published 3, answered 2, ...``."""
        parts = (f"{f.name.replace('_', ' ')} {getattr(self, f.name)}" for f in fields(self))
        return ", ".join(parts)


@dataclass(frozen=True, slots=True)
class Resolved:
    """An image that left the node's slots: answered (with the result's arrival) or not."""

    stamp_ns: int
    published_ns: int
    resolved_ns: int
    answered: bool


class Outstanding:
    """The images published to the node and still without a result (at most ``capacity``).

    The timeout bounds the node's time for one image, not its queue: a node works on its
    images in order, so an image's clock starts when the one before it left the slots (or
    when it was published, if later). Counted from each image's publishing, the images
    queued behind a node slower than timeout / N timed out while it still worked through
    them; each freed slot let another image in, and the node's real backlog grew past N
    while the mediator saw at most N. A node that never answers frees one slot per timeout.

    Times are the caller's monotonic nanoseconds. Not thread-safe: callers serialise.
    """

    def __init__(self, capacity: int, timeout_ns: int) -> None:
        if capacity < 1 or timeout_ns < 1:
            raise ValueError(f"capacity {capacity} and timeout {timeout_ns} ns must be >= 1")
        self.capacity = capacity
        self.timeout_ns = timeout_ns
        self._open: OrderedDict[int, int] = OrderedDict()  # stamp -> published at
        self._head_ns = 0  # when the oldest open image's clock started
        self._expired: OrderedDict[int, None] = OrderedDict()
        self._published = self._answered = self._timed_out = 0
        self._late = self._unmatched = self._bad = 0

    def __len__(self) -> int:
        return len(self._open)

    def add(self, stamp_ns: int, now_ns: int) -> bool:
        """Record an image about to be published; False if its stamp is open already or
        every slot is taken (the caller then does not publish it)."""
        if stamp_ns in self._open or len(self._open) >= self.capacity:
            return False
        if not self._open:
            self._head_ns = now_ns
        self._open[stamp_ns] = now_ns
        self._published += 1
        return True

    def withdraw(self, stamp_ns: int) -> None:
        """Forget an image whose publishing failed (it never reached the node)."""
        head = self._is_head(stamp_ns)
        if self._open.pop(stamp_ns, None) is not None:
            self._published -= 1
            if head:
                self._next_head(self._head_ns)

    def answer(self, stamp_ns: int, now_ns: int) -> Resolved | str:
        """A result with this stamp arrived: the image it answers, or why none (``late``:
        its slot had timed out; ``unmatched``: no image of ours, or answered already)."""
        head = self._is_head(stamp_ns)
        published = self._open.pop(stamp_ns, None)
        if head:
            self._next_head(now_ns)
        if published is None:
            if stamp_ns in self._expired:
                self._late += 1
                return "late"
            self._unmatched += 1
            return "unmatched"
        self._answered += 1
        return Resolved(stamp_ns, published, now_ns, True)

    def nearest(self, stamp_ns: int) -> int | None:
        """The stamp of the image without a result nearest to ``stamp_ns`` (None: none)."""
        return min(self._open, key=lambda open_ns: abs(open_ns - stamp_ns), default=None)

    def bad_result(self) -> None:
        self._bad += 1

    def expire(self, now_ns: int) -> list[Resolved]:
        """The images whose result did not come within the timeout (their slots free)."""
        gone: list[Resolved] = []
        while self._open and now_ns - self._head_ns >= self.timeout_ns:
            stamp, published = self._open.popitem(last=False)
            self._next_head(self._head_ns + self.timeout_ns)
            self._expired[stamp] = None
            if len(self._expired) > EXPIRED_MEMORY:
                self._expired.popitem(last=False)
            gone.append(Resolved(stamp, published, now_ns, False))
        self._timed_out += len(gone)
        return gone

    def next_deadline_ns(self) -> int | None:
        """When the oldest open image times out (None: none is open)."""
        if not self._open:
            return None
        return self._head_ns + self.timeout_ns

    def _is_head(self, stamp_ns: int) -> bool:
        return bool(self._open) and next(iter(self._open)) == stamp_ns

    def _next_head(self, left_ns: int) -> None:
        """The head left the slots at ``left_ns``: the next image's clock starts then, or
        at its publishing if that was later."""
        if self._open:
            self._head_ns = max(left_ns, next(iter(self._open.values())))

    def counts(self) -> ConsumerCounts:
        return ConsumerCounts(
            self._published,
            self._answered,
            self._timed_out,
            self._late,
            self._unmatched,
            self._bad,
            len(self._open),
        )


class GateBook:
    """What the bridge owes its gate subscription, pure (the caller serialises calls).

    Every image the feed brings is resolved once (answered, timed out, not publishable), and
    each resolution is *owed* one take of the gate, whose queue then holds exactly the
    images the node has not answered. Two mismatches can only come from the two
    subscriptions registering or re-registering at different moments (start, a producer
    restart), and both are settled after ``timeout_ns``:

    - a debt no gate notification comes for (the feed saw a put the gate did not): kept, it
      would free the next image's slot the moment it arrives; it is cancelled.
    - a *deficit*, fewer gate notifications than images the node holds (the feed saw a put
      the gate did not, and its debt was paid with the notification of another image, one
      the node still holds, before the timeout could cancel it): kept, the mediator would
      see the node one image less busy for good. Once it has lasted the whole timeout, as
      many resolutions to come take nothing (``spare``).
    - a *surplus*, gate notifications no image accounts for (the gate saw a put the feed did
      not): kept, it would hold a slot for ever; it is freed once it has lasted the whole
      timeout (an image on its way between the feed and the ledger is one only briefly).
    """

    def __init__(self, timeout_ns: int) -> None:
        self.timeout_ns = timeout_ns
        self.debt = 0
        self.spare = 0  # resolutions still to take nothing for: a deficit found
        self._debt_since_ns: int | None = None
        self._surplus_since_ns: int | None = None
        self._deficit_since_ns: int | None = None

    def owe(self, count: int, now_ns: int) -> int:
        """``count`` images were resolved: as many gate takes are due, but for those a
        deficit spares; how many it spared (images the gate never counted)."""
        spared = min(self.spare, max(0, count))
        self.spare -= spared
        count -= spared
        if count > 0 and not self.debt:
            self._debt_since_ns = now_ns
        self.debt += max(0, count)
        return spared

    def taken(self, count: int, now_ns: int) -> int:
        """``count`` gate notifications were taken for the debt; the debt cancelled (> 0
        once what is still owed has waited longer than the timeout for its notification)."""
        self.debt = max(0, self.debt - count)
        if not self.debt:
            self._debt_since_ns = None
            return 0
        if self._debt_since_ns is not None and now_ns - self._debt_since_ns > self.timeout_ns:
            cancelled, self.debt, self._debt_since_ns = self.debt, 0, None
            return cancelled
        return 0

    def surplus(self, gate_queued: int, accounted: int, now_ns: int) -> int:
        """Gate notifications to free now: ``gate_queued`` minus the ``accounted`` images
        (open in the ledger or waiting in the feed), once that surplus has lasted the
        timeout; 0 while a debt is being paid or the surplus is young. A deficit (fewer
        than accounted) that lasted the timeout sets ``spare``; a debt being paid leaves
        its clock running (the deficit goes on through each take)."""
        extra = gate_queued - accounted if not self.debt else 0
        if not self.debt:
            if extra >= 0:
                self._deficit_since_ns = None
            elif self._deficit_since_ns is None:
                self._deficit_since_ns = now_ns
            elif now_ns - self._deficit_since_ns > self.timeout_ns:
                self.spare, self._deficit_since_ns = max(self.spare, -extra), None
        if extra <= 0:
            self._surplus_since_ns = None
            return 0
        if self._surplus_since_ns is None:
            self._surplus_since_ns = now_ns
            return 0
        if now_ns - self._surplus_since_ns <= self.timeout_ns:
            return 0
        self._surplus_since_ns = None
        return extra
