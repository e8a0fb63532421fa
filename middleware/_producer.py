"""The producer side of a named buffer: storage, flow control and notifications.

Buffering rule (the paper's, §4.1): each subscription has a notification queue of the size it
chose. A notification is queued when an element is stored and leaves the queue when the client
*takes* it (``Subscription.take``); the element the client is still processing does not count.
While any flow-controlled subscription's queue is full, ``put`` refuses: the element is not
stored and the producer learns at once (a camera drops the frame and counts it), or waits up
to ``wait_s`` (a lossless replay source). Observers never hold the producer back.

Flow control lives above Zenoh (credits: queued = sent - acknowledged), because a full Zenoh
FIFO would stall the whole link, not just one subscription.
"""

from __future__ import annotations

import contextlib
import logging
import secrets
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import zenoh

from ._buffer import TimeSeries
from ._errors import FlowControlRefused, FramegateError, SchemaError
from ._records import BufferInfo, DataObject, Retention, SubscriptionInfo, SubscriptionMode
from ._wire import Keys, decode_ack, encode_notification_header, parse_subscription_token
from ._xml import XmlLimits, metadata_timestamp_ns, validate_metadata

log = logging.getLogger("framegate.middleware")

# Metadata rides along with notifications up to this size.
_INLINE_METADATA_MAX = 8 * 1024
# Rate over the last this-many puts.
_RATE_WINDOW = 64


@dataclass
class _Sub:
    sub_id: str
    mode: SubscriptionMode
    queue_size: int
    push_max_bytes: int
    # Each registration counts from 1 under its own epoch: a token that drops and returns
    # (a lapsed lease) must not look like a replay of the old sequence to the subscriber.
    epoch: str = ""
    sent: int = 0
    acked: int = 0
    publisher: Any = None

    @property
    def queued(self) -> int:
        return self.sent - self.acked

    def info(self) -> SubscriptionInfo:
        return SubscriptionInfo(self.sub_id, self.mode, self.queue_size, self.queued)


@dataclass
class _Counters:
    puts: int = 0
    refused: int = 0
    rejected: int = 0
    bad_messages: int = 0
    put_times: deque[int] = field(default_factory=lambda: deque(maxlen=_RATE_WINDOW))


class Producer:
    """A buffer offered by this process. Create with ``Node.offer``."""

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        service: str,
        buffer: str,
        *,
        kind: str,
        retention: Retention,
        inline_max_bytes: int,
        xml_limits: XmlLimits,
    ) -> None:
        self.service = service
        self.buffer = buffer
        self.kind = kind
        self.series = TimeSeries(retention)
        self.inline_max_bytes = inline_max_bytes
        self._xml_limits = xml_limits
        self._session = session
        self._keys = keys
        # A new epoch per producer instance: subscribers reset their counters when it changes.
        self.epoch = secrets.token_hex(6)
        self._cond = threading.Condition()
        self._subs: dict[str, _Sub] = {}
        self._registrations = 0
        self._counters = _Counters()
        self._closed = False
        # Callbacks run on Zenoh's thread (indirect=False): short, and they never block.
        self._token_sub = session.liveliness().declare_subscriber(
            keys.subscription_tokens(service, buffer),
            zenoh.handlers.Callback(self._on_token, indirect=False),
            history=True,
        )
        self._ack_sub = session.declare_subscriber(
            keys.acks(service, buffer), zenoh.handlers.Callback(self._on_ack, indirect=False)
        )

    @property
    def name(self) -> str:
        return f"{self.service}/{self.buffer}"

    # -- Zenoh callbacks ---------------------------------------------------------------
    def _on_token(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            sub_id, mode, queue_size, push_max_bytes = parse_subscription_token(key)
        except ValueError:
            self._counters.bad_messages += 1
            return
        with self._cond:
            if sample.kind == zenoh.SampleKind.PUT:
                if sub_id not in self._subs:
                    self._registrations += 1
                    self._subs[sub_id] = _Sub(
                        sub_id,
                        mode,
                        queue_size,
                        push_max_bytes,
                        epoch=f"{self.epoch}.{self._registrations}",
                    )
            else:
                gone = self._subs.pop(sub_id, None)
                if gone is not None:
                    log.info(
                        "%s: subscription %s gone; no longer waiting for it", self.name, sub_id
                    )
            self._cond.notify_all()

    def _on_ack(self, sample: zenoh.Sample) -> None:
        sub_id = str(sample.key_expr).rsplit("/", 1)[-1]
        try:
            epoch, seq = decode_ack(sample.payload.to_bytes())
        except Exception:  # garbage on our ack key must never hurt the producer
            self._counters.bad_messages += 1
            return
        with self._cond:
            sub = self._subs.get(sub_id)
            if sub is None or epoch != sub.epoch:
                return
            # Cumulative and clamped: duplicates, reordering and lies cannot push it past sent.
            sub.acked = max(sub.acked, min(seq, sub.sent))
            self._cond.notify_all()

    # -- producing -----------------------------------------------------------------------
    def put(
        self, timestamp_ns: int, payload: bytes, metadata: bytes | str, *, wait_s: float = 0.0
    ) -> None:
        """Store an element and notify subscribers.

        Raises SchemaError (metadata), DuplicateTimestampError, PayloadTooLargeError, or
        FlowControlRefused when a flow-controlled queue stays full for ``wait_s`` seconds.
        A refused or rejected element is not stored.
        """
        if self._closed:
            raise FramegateError(f"buffer {self.name} is closed")
        try:
            _check_types(timestamp_ns, payload, metadata)
        except SchemaError:
            self._counters.rejected += 1
            raise
        meta = metadata.encode("utf-8") if isinstance(metadata, str) else bytes(metadata)
        if not isinstance(payload, bytes):
            payload = bytes(payload)
        try:
            root = validate_metadata(meta, self.kind, self._xml_limits)
            declared = metadata_timestamp_ns(root)
            if declared != timestamp_ns:
                raise SchemaError(
                    f"metadata says timestamp_ns={declared} but the element's key is {timestamp_ns}"
                )
            self.series.check_put(timestamp_ns, len(payload))
        except FramegateError:
            self._counters.rejected += 1
            raise
        element = DataObject(timestamp_ns, payload, meta)
        deadline = time.monotonic() + wait_s
        with self._cond:
            while (full := self._full_subscription()) is not None:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    self._counters.refused += 1
                    raise FlowControlRefused(
                        f"{self.name}: subscriber {full.sub_id} has {full.queued}/"
                        f"{full.queue_size} notifications queued; element {timestamp_ns} "
                        "was not stored (drop it, or put with wait_s to wait)"
                    )
                self._cond.wait(remaining)
            try:
                self.series.append(element)
            except FramegateError:
                self._counters.rejected += 1
                raise
            self._counters.puts += 1
            self._counters.put_times.append(time.monotonic_ns())
            # Sent in order under the lock; flow-control notifications are credit-limited,
            # so BLOCK cannot pile up, and observers use DROP so they never slow us down.
            for sub in list(self._subs.values()):
                sub.sent += 1
                self._notify(sub, element)

    def _notify(self, sub: _Sub, element: DataObject) -> None:
        if sub.publisher is None:
            congestion = (
                zenoh.CongestionControl.BLOCK
                if sub.mode is SubscriptionMode.FLOW
                else zenoh.CongestionControl.DROP
            )
            sub.publisher = self._session.declare_publisher(
                self._keys.notify(self.service, self.buffer, sub.sub_id),
                congestion_control=congestion,
            )
        limit = self.inline_max_bytes if sub.push_max_bytes < 0 else sub.push_max_bytes
        pushed = len(element.payload) <= limit
        header = encode_notification_header(
            sub.epoch,
            sub.sent,
            element,
            with_metadata=len(element.metadata) <= _INLINE_METADATA_MAX,
            pushed=pushed,
        )
        try:
            # The payload travels as the Zenoh payload itself: no extra copy into msgpack,
            # and large ones go through Zenoh's shared memory on one host.
            sub.publisher.put(element.payload if pushed else b"", attachment=header)
        except zenoh.ZError as exc:
            log.warning("%s: notification to %s failed: %s", self.name, sub.sub_id, exc)

    def _full_subscription(self) -> _Sub | None:
        for sub in self._subs.values():
            if sub.mode is SubscriptionMode.FLOW and sub.queued >= sub.queue_size:
                return sub
        return None

    # -- reading state -------------------------------------------------------------------
    def fill(self) -> float:
        """The fullest flow-controlled subscription's queued/N in [0, 1]; 0 with none.

        This is the paper's load indicator, read by the mediator.
        """
        with self._cond:
            fills = [s.info().fill for s in self._subs.values() if s.mode is SubscriptionMode.FLOW]
        return max(fills, default=0.0)

    def subscriptions(self) -> list[SubscriptionInfo]:
        """Every live subscription as this producer counts it."""
        with self._cond:
            return [s.info() for s in self._subs.values()]

    def wait_for_subscribers(self, count: int, timeout_s: float) -> bool:
        """Wait until at least ``count`` subscriptions are registered."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while len(self._subs) < count:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._cond.wait(remaining)
            return True

    def wait_fill_below(self, limit: float, timeout_s: float) -> bool:
        """Wait until ``fill()`` < ``limit`` (e.g. a consumer took a notification)."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                fills = [
                    s.info().fill for s in self._subs.values() if s.mode is SubscriptionMode.FLOW
                ]
                if max(fills, default=0.0) < limit:
                    return True
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._cond.wait(remaining)

    def info(self) -> BufferInfo:
        """Retention, size, span, rate, counters and subscriptions."""
        c = self._counters
        times = list(c.put_times)
        rate = (len(times) - 1) / ((times[-1] - times[0]) / 1e9) if len(times) > 1 else 0.0
        if times and time.monotonic_ns() - times[-1] > 5 * 1e9:
            rate = 0.0  # stale: nothing put for a while
        return BufferInfo(
            service=self.service,
            buffer=self.buffer,
            kind=self.kind,
            retention=self.series.retention,
            count=len(self.series),
            payload_bytes=self.series.total_bytes,
            oldest_ns=self.series.oldest_ns,
            newest_ns=self.series.newest_ns,
            rate_hz=rate,
            puts=c.puts,
            refused=c.refused,
            rejected=c.rejected,
            subscriptions=tuple(self.subscriptions()),
        )

    def close(self) -> None:
        """Stop serving; subscribers see the service token go."""
        if self._closed:
            return
        self._closed = True
        with self._cond:
            subs = list(self._subs.values())
            self._subs.clear()
            self._cond.notify_all()
        for entity in [self._token_sub, self._ack_sub] + [s.publisher for s in subs]:
            if entity is not None:
                with contextlib.suppress(zenoh.ZError):
                    entity.undeclare()


def _check_types(timestamp_ns: object, payload: object, metadata: object) -> None:
    """Wrong-typed arguments get a message, not a TypeError from deep inside."""
    if not isinstance(timestamp_ns, int) or isinstance(timestamp_ns, bool):
        raise SchemaError(
            f"timestamp_ns must be an int (ns since the epoch), got {type(timestamp_ns).__name__}"
        )
    if not 0 <= timestamp_ns < 2**63:
        raise SchemaError(f"timestamp_ns {timestamp_ns} is outside 0 .. 2**63-1")
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise SchemaError(f"payload must be bytes, got {type(payload).__name__}")
    if not isinstance(metadata, bytes | bytearray | str):
        raise SchemaError(f"metadata must be XML as bytes or str, got {type(metadata).__name__}")
