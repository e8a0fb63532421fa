"""The producer side of a named buffer: storage, flow control and notifications.

Buffering rule (the paper's, §4.1): each subscription has a notification queue of the size it
chose. A notification is queued when an element is stored and leaves the queue when the client
*takes* it (``Subscription.take``); the element the client is still processing does not count.
While any flow-controlled subscription's queue is full, ``put`` refuses: the element is not
stored and the producer learns at once (a camera drops the frame and counts it), or waits up
to ``wait_s`` (a lossless replay source). Observers never hold the producer back.

Flow control lives above Zenoh (credits: queued = sent - acknowledged), because a full Zenoh
FIFO would stall the whole link, not just one subscription. The protocol itself (which
message does what in which state) is the pure ``ProducerLedger`` in ``_ledger_producer``;
this module only feeds it from Zenoh and sends what it returns.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import secrets
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import zenoh

from ._buffer import TimeSeries
from ._errors import DuplicateTimestampError, FlowControlRefused, FramegateError, SchemaError
from ._ledger_producer import ProducerLedger, Registration, RegistrationKey, Send
from ._records import BufferInfo, DataObject, Retention, SubscriptionInfo, SubscriptionMode
from ._shapes import ShapeChecker
from ._wire import (
    Keys,
    decode_ack,
    encode_batch_header,
    encode_notification_header,
    parse_subscription_token,
)
from ._xml import XmlLimits

log = logging.getLogger("framegate.middleware")

# Metadata rides along with notifications up to this size.
_INLINE_METADATA_MAX = 8 * 1024
# Rate over the last this-many puts.
_RATE_WINDOW = 64
# How often outstanding notifications are checked for resending (and retired publishers
# undeclared) when no put does it.
_TICK_S = 0.1


@dataclass
class _Counters:
    puts: int = 0
    refused: int = 0
    rejected: int = 0
    bad_messages: int = 0
    skipped: dict[str, int] = field(default_factory=dict)
    put_times: deque[int] = field(default_factory=lambda: deque(maxlen=_RATE_WINDOW))


class Producer:
    """A buffer offered by this process. Create with ``Node.offer``.

    Threads: ``_on_token`` and ``_on_ack`` run on Zenoh's threads; they parse, then take
    ``_lock`` only to feed the ledger, and never call Zenoh. ``_lock`` (with ``_cond`` on it)
    guards the ledger, the publishers, the counters and the rate window; nothing holds it
    while calling Zenoh. ``_send_lock`` serialises sending (``put`` on the caller's threads
    and the ``fg-resend`` thread, which resends outstanding notifications and undeclares the
    publishers of withdrawn registrations): notifications of one registration leave in seq
    order, and a ``publisher.put`` that blocks (flow control uses ``BLOCK``) holds only
    ``_send_lock``, which no Zenoh callback takes. Lock order: ``_send_lock``, then ``_lock``.
    """

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
        # Validates each element's metadata, in full once per document shape.
        self._metadata = ShapeChecker(kind, xml_limits)
        self._session = session
        self._keys = keys
        # A new epoch per producer instance; each registration gets "<epoch>.<n>".
        self.epoch = secrets.token_hex(6)
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._send_lock = threading.Lock()
        self._ledger: ProducerLedger[DataObject] = ProducerLedger(self.epoch)
        self._publishers: dict[RegistrationKey, Any] = {}
        self._retired: list[Any] = []
        self._counters = _Counters()
        self._closed = False
        self._stop = threading.Event()
        self._token_sub = session.liveliness().declare_subscriber(
            keys.subscription_tokens(service, buffer),
            zenoh.handlers.Callback(self._on_token, indirect=False),
            history=True,
        )
        self._ack_sub = session.declare_subscriber(
            keys.acks(service, buffer), zenoh.handlers.Callback(self._on_ack, indirect=False)
        )
        self._resender = threading.Thread(
            target=self._resend_loop, daemon=True, name=f"fg-resend-{service}/{buffer}"
        )
        self._resender.start()

    @property
    def name(self) -> str:
        return f"{self.service}/{self.buffer}"

    # -- Zenoh callbacks (Zenoh's threads: short, never call Zenoh) -------------------------
    def _on_token(self, sample: zenoh.Sample) -> None:
        try:
            key = RegistrationKey(*parse_subscription_token(str(sample.key_expr)))
        except ValueError:
            with self._lock:
                self._counters.bad_messages += 1
            return
        with self._cond:
            if sample.kind == zenoh.SampleKind.PUT:
                self._ledger.token_put(key, time.monotonic_ns())
            elif (gone := self._ledger.token_delete(key)) is not None:
                self._retire(gone)
                log.info("%s: subscription %s gone; no longer waiting for it", self.name, key)
            self._cond.notify_all()

    def _on_ack(self, sample: zenoh.Sample) -> None:
        sub_id = str(sample.key_expr).rsplit("/", 1)[-1]
        try:
            epoch, seq = decode_ack(sample.payload.to_bytes())
        except Exception:  # garbage on our ack key must never hurt the producer
            with self._lock:
                self._counters.bad_messages += 1
            return
        with self._cond:
            if self._ledger.ack(sub_id, epoch, seq, time.monotonic_ns()):
                self._cond.notify_all()

    def _retire(self, reg: Registration[DataObject]) -> None:
        """(under _lock) Its publisher is undeclared by the next sender, not on Zenoh's thread."""
        publisher = self._publishers.pop(reg.key, None)
        if publisher is not None:
            self._retired.append(publisher)

    # -- producing -------------------------------------------------------------------------
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
        self._put((self._checked(timestamp_ns, payload, metadata),), wait_s)

    def put_many(
        self, elements: Sequence[tuple[int, bytes, bytes | str]], *, wait_s: float = 0.0
    ) -> None:
        """Store a batch of ``(timestamp_ns, payload, metadata)`` elements, timestamps
        strictly increasing, and notify each subscriber once for all of them.

        The queue counts elements: the batch is refused, whole, while a flow-controlled
        subscriber has fewer than ``len(elements)`` free places (after ``wait_s``); a
        batch larger than a subscriber's queue can never fit. Each element is stored on its
        own, so queries see them exactly as if each had been ``put``. All or nothing: a
        refused or rejected batch stores no element. Raises like ``put``.
        """
        if self._closed:
            raise FramegateError(f"buffer {self.name} is closed")
        if not elements:
            return
        checked = tuple(self._checked(t, p, m) for t, p, m in elements)
        for before, after in itertools.pairwise(checked):
            if after.timestamp_ns <= before.timestamp_ns:
                with self._lock:
                    self._counters.rejected += 1
                raise DuplicateTimestampError(
                    f"put_many: timestamp {after.timestamp_ns} follows {before.timestamp_ns} "
                    "in the batch; timestamps must strictly increase"
                )
        self._put(checked, wait_s)

    def _put(self, elements: tuple[DataObject, ...], wait_s: float) -> None:
        # Checked now too, so that an element that can never be stored is not waited for.
        try:
            self.series.check_extend(elements)
        except FramegateError:
            with self._lock:
                self._counters.rejected += len(elements)
            raise
        count = len(elements)
        deadline = time.monotonic() + wait_s
        with self._send_lock:
            while True:
                with self._cond:
                    due, retired = self._ledger.tick(time.monotonic_ns()), self._drain_retired()
                    full = self._ledger.full(count)
                    if full is None:
                        sends = self._store(elements)
                        break
                    remaining = deadline - time.monotonic()
                    if remaining <= 0 or count > full.key.queue_size:
                        self._counters.refused += count
                        raise FlowControlRefused(self._refusal(full, elements))
                self._send_all(due)
                self._undeclare(retired)
                with self._cond:
                    if self._ledger.full(count) is not None:
                        self._cond.wait(min(remaining, _TICK_S))
            self._send_all(due + sends)
            self._undeclare(retired)

    def _refusal(self, full: Registration[DataObject], elements: tuple[DataObject, ...]) -> str:
        k, count, first = full.key, len(elements), elements[0].timestamp_ns
        if count == 1:
            return (
                f"{self.name}: subscriber {k.sub_id} has {full.queued}/{k.queue_size} "
                f"notifications queued; element {first} was not stored (drop it, or put "
                "with wait_s to wait)"
            )
        if count > k.queue_size:
            advice = f"it can never fit: put batches of at most {k.queue_size}"
        else:
            advice = "drop it, or put_many with wait_s to wait"
        return (
            f"{self.name}: subscriber {k.sub_id} has {full.queued}/{k.queue_size} "
            f"notifications queued, no room for a batch of {count}; no element of the batch "
            f"(from {first}) was stored ({advice})"
        )

    def _checked(self, timestamp_ns: int, payload: bytes, metadata: bytes | str) -> DataObject:
        # The common case (int, bytes, bytes) costs three type checks; the rest is converted.
        if not (type(payload) is bytes and type(metadata) is bytes and type(timestamp_ns) is int):
            try:
                _check_types(timestamp_ns, payload, metadata)
            except SchemaError:
                with self._lock:
                    self._counters.rejected += 1
                raise
            metadata = metadata.encode("utf-8") if isinstance(metadata, str) else bytes(metadata)
            payload = bytes(payload)
        meta: bytes = metadata  # type: ignore[assignment]
        try:
            if not 0 <= timestamp_ns < 2**63:
                _check_types(timestamp_ns, payload, meta)
            declared = self._metadata.timestamp_ns(meta)
            if declared != timestamp_ns:
                raise SchemaError(
                    f"metadata says timestamp_ns={declared} but the element's key is {timestamp_ns}"
                )
        except FramegateError:
            with self._lock:
                self._counters.rejected += 1
            raise
        return DataObject(timestamp_ns, payload, meta)

    def _store(self, elements: tuple[DataObject, ...]) -> list[Send[DataObject]]:
        """(under _lock) Append, count, and get the notifications to send."""
        try:
            # All or nothing: ``extend`` checks the batch (strictly increasing, checked by
            # the caller) against the series before appending any of it.
            self.series.extend(elements)
        except FramegateError:
            self._counters.rejected += len(elements)
            raise
        self._counters.puts += len(elements)
        now = time.monotonic_ns()
        self._counters.put_times.extend([now] * len(elements))
        return self._ledger.put_many(elements, now)

    def _drain_retired(self) -> list[Any]:
        retired, self._retired = self._retired, []
        return retired

    def _send_all(self, sends: list[Send[DataObject]]) -> None:
        """(under _send_lock, not _lock) Send notifications; a failure keeps them outstanding."""
        for send in sends:
            try:
                self._send(send)
            except zenoh.ZError as exc:
                log.warning(
                    "%s: notification %d to %s failed (%s); it will be sent again",
                    self.name,
                    send.seq,
                    send.key.sub_id,
                    exc,
                )
                with self._lock:
                    self._ledger.send_failed(send.key, send.epoch)

    def _send(self, send: Send[DataObject]) -> None:
        key = send.key
        with self._lock:
            publisher = self._publishers.get(key)
            live = self._ledger.get(key) is not None
        if not live:
            return  # withdrawn since
        if publisher is None:
            congestion = (
                zenoh.CongestionControl.BLOCK
                if key.mode is SubscriptionMode.FLOW
                else zenoh.CongestionControl.DROP
            )
            publisher = self._session.declare_publisher(
                self._keys.notify(self.service, self.buffer, key.sub_id),
                congestion_control=congestion,
            )
            with self._lock:
                if self._ledger.get(key) is not None:
                    self._publishers[key] = publisher
                else:
                    self._retired.append(publisher)
        limit = self.inline_max_bytes if key.push_max_bytes < 0 else key.push_max_bytes
        if send.count > 1:
            payload, header = self._batch(send, limit)
            publisher.put(payload, attachment=header)
            return
        element = send.headers[0]
        # A resent notification carries no payload: the subscriber fetches if it needs it.
        pushed = not send.again and len(element.payload) <= limit
        header = encode_notification_header(
            send.epoch,
            send.seq,
            element.timestamp_ns,
            element.metadata if len(element.metadata) <= _INLINE_METADATA_MAX else None,
            pushed=pushed,
            acked=send.acked,
            descriptor=key.descriptor,
        )
        # The payload travels as the Zenoh payload itself: no extra copy into msgpack,
        # and large ones go through Zenoh's shared memory on one host.
        publisher.put(element.payload if pushed else b"", attachment=header)

    @staticmethod
    def _batch(send: Send[DataObject], limit: int) -> tuple[bytes, bytes]:
        """(Zenoh payload, attachment) of a batch notification: pushed only if every payload
        fits the push limit, then the payloads one after another."""
        elements = send.headers
        pushed = all(len(e.payload) <= limit for e in elements)
        header = encode_batch_header(
            send.epoch,
            send.seq,
            [e.timestamp_ns for e in elements],
            [e.metadata if len(e.metadata) <= _INLINE_METADATA_MAX else None for e in elements],
            [len(e.payload) for e in elements] if pushed else None,
            acked=send.acked,
            descriptor=send.key.descriptor,
        )
        payload = b"".join(e.payload for e in elements) if pushed else b""
        return payload, header

    @staticmethod
    def _undeclare(publishers: list[Any]) -> None:
        for publisher in publishers:
            with contextlib.suppress(zenoh.ZError):
                publisher.undeclare()

    def _resend_loop(self) -> None:
        while not self._stop.wait(_TICK_S):
            with self._send_lock:
                if self._closed:
                    return
                with self._lock:
                    due, retired = self._ledger.tick(time.monotonic_ns()), self._drain_retired()
                self._send_all(due)
                self._undeclare(retired)

    def count_skip(self, reason: str, count: int = 1) -> None:
        """Count ``count`` elements the service chose not to put, e.g. ``late`` frames a
        camera could not produce in time; ``info`` shows them by reason."""
        with self._lock:
            skipped = self._counters.skipped
            skipped[reason] = skipped.get(reason, 0) + count

    # -- reading state -------------------------------------------------------------------
    def fill(self) -> float:
        """The fullest flow-controlled subscription's queued/N in [0, 1]; 0 with none.

        This is the paper's load indicator, read by the mediator.
        """
        with self._lock:
            return self._ledger.fill()

    def subscriptions(self) -> list[SubscriptionInfo]:
        """Every live subscription (registration) as this producer counts it."""
        with self._lock:
            return [r.info() for r in self._ledger.registrations()]

    def wait_for_subscribers(self, count: int, *, timeout_s: float) -> bool:
        """Wait until at least ``count`` subscriptions are registered."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while len(self._ledger.registrations()) < count:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._cond.wait(remaining)
            return True

    def wait_fill_below(self, limit: float, *, timeout_s: float) -> bool:
        """Wait until ``fill()`` < ``limit`` (e.g. a consumer took a notification)."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._ledger.fill() >= limit:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._cond.wait(remaining)
            return True

    def info(self) -> BufferInfo:
        """Retention, size, span, rate, counters and subscriptions."""
        with self._lock:
            c = self._counters
            times = list(c.put_times)
            puts, refused, rejected = c.puts, c.refused, c.rejected
            skipped = dict(c.skipped)
            subs = tuple(r.info() for r in self._ledger.registrations())
        span_ns = times[-1] - times[0] if times else 0
        # Elements per second; a batch's elements share one time, so the span may be 0.
        rate = (len(times) - 1) / (span_ns / 1e9) if span_ns > 0 else 0.0
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
            puts=puts,
            refused=refused,
            rejected=rejected,
            subscriptions=subs,
            skipped=skipped,
        )

    def close(self) -> None:
        """Stop serving; subscribers see the service token go."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        with self._cond:
            gone = self._ledger.clear()
            for reg in gone:
                self._retire(reg)
            retired = self._drain_retired()
            self._cond.notify_all()
        self._resender.join(timeout=6.0)  # a BLOCK put gives up after 5 s
        for entity in [self._token_sub, self._ack_sub, *retired]:
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
