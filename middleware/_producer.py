"""The producer side of a named buffer: storage, flow control and notifications.

Buffering rule (the paper's, §4.1): each subscription has a notification queue of the size it
chose. A notification is queued when an element is stored and leaves the queue when the client
*takes* it (``Subscription.take``); the element the client is still processing does not count.
While any flow-controlled subscription's queue is full, ``put`` refuses: the element is not
stored and the producer learns at once (a camera drops the frame and counts it), or waits up
to ``wait_s`` (a lossless replay source). Observers never hold the producer back.

Flow control lives above Zenoh (credits: queued = sent - acknowledged), because a full Zenoh
FIFO would stall the whole link, not just one subscription. Every decision is the sans-IO
``ProducerProtocol`` (``_protocol_producer``); this module feeds it and carries out its
events.
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
from ._clock import now_ns
from ._errors import DuplicateTimestampError, FlowControlRefused, FramegateError, SchemaError
from ._inbox import Inbox, Receiver
from ._ledger_producer import Registration, RegistrationKey
from ._loop import NodeLoop
from ._protocol_producer import Event, ProducerProtocol, Publish, Retire
from ._records import BufferInfo, DataObject, Retention, SubscriptionInfo
from ._shapes import ShapeChecker
from ._wire import Keys
from ._xml import XmlLimits

log = logging.getLogger("framegate.middleware")

# Elements stamped further ahead of this process's clock are refused: a stamp a consumer
# cannot bound must never reach it (see the README's time model).
HORIZON_NS = 10_000_000_000
# Rate over the last this-many puts.
_RATE_WINDOW = 64
# A put that waits for credit looks again at least this often.
_WAIT_S = 0.1
# Acks honest subscribers can send between two drains: coalesced, at most a few per
# registration and queue window (see ``AckPolicy``) plus a re-ack each per 0.5 s. A lost
# ack costs nothing: acks are cumulative and repeated.
_ACK_INBOX = 8192


@dataclass
class _Counters:
    puts: int = 0
    refused: int = 0
    rejected: int = 0
    skipped: dict[str, int] = field(default_factory=dict)
    put_times: deque[int] = field(default_factory=lambda: deque(maxlen=_RATE_WINDOW))


class Producer:
    """A buffer offered by this process. Create with ``Node.offer``.

    Threads (see the README's *Threads*): ``_on_token`` runs on zenoh-python's callback
    thread (tokens are rare); it feeds the protocol under ``_lock`` and wakes whoever waits,
    and never calls Zenoh. Acks wait in the ``Inbox`` (a Zenoh channel) until ``put``
    drains them with ``try_recv`` before deciding credit; a put that waits for credit
    blocks in the channel's ``recv`` (the *receiver*; the loop rings its doorbell at its
    deadline), and with no put waiting the node's loop drains them. ``_lock`` (with
    ``_cond`` on it) guards the protocol, the counters, the rate window and the inbox's
    ``Receiver``; the inbox is drained under it while no receiver blocks in ``recv``.
    ``_send_lock`` serialises carrying out the protocol's events (``put`` on the caller's
    thread, ``on_deadline`` on the node's loop), so the messages of one registration leave
    in order and a ``publisher.put`` that blocks holds only ``_send_lock``. Lock order:
    ``_send_lock``, then ``_lock``.
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
        loop: NodeLoop,
        horizon_ns: int = HORIZON_NS,
    ) -> None:
        self.service = service
        self.buffer = buffer
        self.kind = kind
        self.series = TimeSeries(retention)
        self.inline_max_bytes = inline_max_bytes
        self.horizon_ns = horizon_ns
        self._horizon_at_ns = 0  # the largest stamp accepted without reading the clock
        # Validates each element's metadata, in full once per document shape.
        self._metadata = ShapeChecker(kind, xml_limits)
        self._session = session
        self._loop = loop
        # A new epoch per producer instance; each registration gets "<epoch>.<n>".
        self.epoch = secrets.token_hex(6)
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._send_lock = threading.Lock()
        self._protocol = ProducerProtocol(
            keys, service, buffer, self.epoch, inline_max_bytes=inline_max_bytes
        )
        self._publishers: dict[RegistrationKey, Any] = {}
        self._counters = _Counters()
        self._closed = False
        # Events produced by Zenoh input (greetings, refusals, retired publishers) wait for
        # the loop or the next put; this says whether any do.
        self._events_waiting = False
        self._acks = Inbox(
            session,
            keys.acks(service, buffer),
            capacity=_ACK_INBOX,
            doorbell_key=keys.ack(service, buffer, "doorbell"),
        )
        # A put blocked in the ack inbox's recv, and when it wants the doorbell.
        self._receiver = Receiver(self._acks, self._cond, loop)
        # Declared last: its callback (history included) may run at once.
        self._token_sub = session.liveliness().declare_subscriber(
            keys.subscription_tokens(service, buffer),
            zenoh.handlers.Callback(self._on_token),
            history=True,
        )
        loop.add(self)

    @property
    def name(self) -> str:
        return f"{self.service}/{self.buffer}"

    # -- Zenoh input (zenoh-python's callback threads: short, never call Zenoh) -----------
    def _on_token(self, sample: zenoh.Sample) -> None:
        alive = sample.kind == zenoh.SampleKind.PUT
        with self._cond:
            self._protocol.token(str(sample.key_expr), alive, time.monotonic_ns())
            self._events_waiting = True
            self._receiver.wake()  # a waiting put looks again (a gone subscriber frees it)
            self._cond.notify_all()
        self._loop.poke(0)

    # -- acks (under _lock, on the thread that needs them) ---------------------------------
    def _drain_acks(self) -> None:
        """(under _lock) Feed the protocol every ack waiting in the inbox, unless a put
        blocks in its ``recv``: then they are that put's to take."""
        if self._receiver.active:
            return
        freed = False
        ack = self._protocol.ack
        now = 0
        for sample in self._acks.drain():
            now = now or time.monotonic_ns()
            freed |= ack(str(sample.key_expr), sample.payload.to_bytes(), now)
        if freed:
            self._cond.notify_all()

    def _wait_acks(self, wait_s: float) -> None:
        """(holding _lock through ``_cond``) Wait up to ``wait_s`` for acks, fed to the
        protocol when this returns (see ``Receiver.wait``)."""
        sample = self._receiver.wait(wait_s)
        if sample is not None:
            self._protocol.ack(str(sample.key_expr), sample.payload.to_bytes(), time.monotonic_ns())
        self._drain_acks()
        self._cond.notify_all()  # news for other waiters, or their turn to receive

    # -- the node's loop ---------------------------------------------------------------------
    def next_deadline_ns(self) -> int | None:
        if self._events_waiting:
            return 0
        with self._lock:
            due = self._protocol.next_deadline_ns()
            other = self._receiver.deadline_ns()
        if other is not None and (due is None or other < due):
            return other
        return due

    def on_deadline(self, now_ns: int) -> None:
        """Resends that are due and events Zenoh input produced, sent from the node's loop;
        acks drained if no put waits for them; a waiting put's doorbell rung at its
        deadline."""
        with self._send_lock:
            with self._lock:
                if self._closed:
                    return
                ring, _ = self._receiver.due(now_ns)
                self._drain_acks()  # before resending (a no-op while a put receives)
                self._protocol.tick(now_ns)
                events = self._take_events()
            self._carry_out(events)
        if ring:
            self._receiver.ring()

    def _take_events(self) -> list[Event]:
        """(under _lock)"""
        self._events_waiting = False
        return self._protocol.events()

    # -- producing -------------------------------------------------------------------------
    def put(
        self, timestamp_ns: int, payload: bytes, metadata: bytes | str, *, wait_s: float = 0.0
    ) -> int:
        """Store an element and notify subscribers; how many flow-controlled subscriptions
        were notified (0: no consumer will be told of it, e.g. one whose subscription just
        lapsed).

        Raises SchemaError (metadata), DuplicateTimestampError, PayloadTooLargeError, or
        FlowControlRefused when a flow-controlled queue stays full for ``wait_s`` seconds.
        A refused or rejected element is not stored.
        """
        if self._closed:
            raise FramegateError(f"buffer {self.name} is closed")
        return self._put((self._checked(timestamp_ns, payload, metadata),), wait_s)

    def put_many(
        self, elements: Sequence[tuple[int, bytes, bytes | str]], *, wait_s: float = 0.0
    ) -> int:
        """Store a batch of ``(timestamp_ns, payload, metadata)`` elements, timestamps
        strictly increasing, and notify each subscriber once for all of them.

        The queue counts elements: the batch is refused, whole, while a flow-controlled
        subscriber has fewer than ``len(elements)`` free places (after ``wait_s``); a
        batch larger than a subscriber's queue can never fit. Each element is stored on its
        own, so queries see them exactly as if each had been ``put``. All or nothing: a
        refused or rejected batch stores no element. Raises and returns like ``put``.
        """
        if self._closed:
            raise FramegateError(f"buffer {self.name} is closed")
        if not elements:
            return 0
        checked = tuple(self._checked(t, p, m) for t, p, m in elements)
        for before, after in itertools.pairwise(checked):
            if after.timestamp_ns <= before.timestamp_ns:
                with self._lock:
                    self._counters.rejected += 1
                raise DuplicateTimestampError(
                    f"put_many: timestamp {after.timestamp_ns} follows {before.timestamp_ns} "
                    "in the batch; timestamps must strictly increase"
                )
        return self._put(checked, wait_s)

    def _put(self, elements: tuple[DataObject, ...], wait_s: float) -> int:
        if wait_s > 0:
            # Checked before waiting too, so that an element that can never be stored is not
            # waited for (``_store`` checks it in any case).
            try:
                self.series.check_extend(elements)
            except FramegateError:
                with self._lock:
                    self._counters.rejected += len(elements)
                raise
        count = len(elements)
        deadline = time.monotonic() + wait_s
        while True:
            with self._send_lock:
                with self._cond:
                    self._drain_acks()
                    full = self._protocol.full(count)
                    if full is None:
                        notified = self._store(elements)
                    else:
                        self._protocol.tick(time.monotonic_ns())  # a waiting put heals losses
                    events = self._take_events()
                self._carry_out(events)
            if full is None:
                return notified
            # Not stored: wait for credit outside _send_lock (the loop keeps sending).
            with self._cond:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or count > full.key.queue_size:
                    self._counters.refused += count
                    raise FlowControlRefused(self._refusal(full, elements))
                self._drain_acks()
                if self._protocol.full(count) is not None:
                    self._wait_acks(min(remaining, _WAIT_S))

    def _refusal(self, full: Registration[Any], elements: tuple[DataObject, ...]) -> str:
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
            # The clock is read only when a stamp passes the last bound seen (stamps are
            # near now, so that is about once per horizon).
            if timestamp_ns > self._horizon_at_ns and timestamp_ns > self._horizon_now():
                raise SchemaError(
                    f"timestamp {timestamp_ns} is {(timestamp_ns - now_ns()) / 1e9:.1f} s ahead "
                    f"of this process's clock; {self.name} refuses elements more than "
                    f"{self.horizon_ns / 1e9:g} s ahead (stamp with middleware.now_ns())"
                )
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

    def _horizon_now(self) -> int:
        self._horizon_at_ns = now_ns() + self.horizon_ns
        return self._horizon_at_ns

    def _store(self, elements: tuple[DataObject, ...]) -> int:
        """(under _lock) Append, count, and let the protocol notify; the flow-controlled
        subscriptions notified."""
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
        return self._protocol.put_many(elements, now)

    def _carry_out(self, events: list[Event]) -> None:
        """(under _send_lock, not _lock) Send what the protocol decided; a notification that
        fails to leave stays outstanding."""
        for event in events:
            if type(event) is Retire:
                publisher = self._publishers.pop(event.key, None)
                if publisher is not None:
                    with contextlib.suppress(zenoh.ZError):
                        publisher.undeclare()
                continue
            assert type(event) is Publish
            try:
                if event.epoch is None:  # a control message: rare, never blocks
                    self._session.put(
                        event.keyexpr,
                        event.payload,
                        attachment=event.attachment,
                        congestion_control=zenoh.CongestionControl.DROP,
                        # Whose it is: a subscriber trusts a refusal only from our session.
                        source_info=zenoh.SourceInfo(self._session.id, 0),
                    )
                    continue
                publisher = self._publishers.get(event.key)
                if publisher is None:
                    publisher = self._session.declare_publisher(
                        event.keyexpr,
                        congestion_control=zenoh.CongestionControl.BLOCK
                        if event.block
                        else zenoh.CongestionControl.DROP,
                    )
                    self._publishers[event.key] = publisher
                publisher.put(event.payload, attachment=event.attachment)
            except zenoh.ZError as exc:
                log.warning(
                    "%s: a notification to %s failed (%s); it will be sent again",
                    self.name,
                    event.key.sub_id,
                    exc,
                )
                if event.epoch is not None:
                    with self._lock:
                        self._protocol.send_failed(event.key, event.epoch)

    def discard_after(self, timestamp_ns: int, reason: str) -> int:
        """Remove the elements stamped after ``timestamp_ns`` so that later puts may be
        stamped from there on; how many there were. Counted in ``info`` as skipped by
        ``reason`` and logged.

        For a stage whose input started over earlier in time (a camera restarted after its
        clock was stepped back, a rogue's future stamp): the removed elements came from a
        clock now known to be wrong. Subscribers that were notified of them keep what was
        pushed to them; a fetch of a removed one finds nothing.
        """
        with self._lock:
            removed = self.series.discard_after(timestamp_ns)
            if removed:
                skipped = self._counters.skipped
                skipped[reason] = skipped.get(reason, 0) + len(removed)
        if removed:
            log.warning(
                "%s: %d elements stamped after %d removed (%s): stamps continue from there",
                self.name,
                len(removed),
                timestamp_ns,
                reason,
            )
        return len(removed)

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
            self._drain_acks()
            return self._protocol.fill()

    def subscriptions(self) -> list[SubscriptionInfo]:
        """Every live subscription (registration) as this producer counts it."""
        with self._lock:
            self._drain_acks()
            return self._protocol.subscriptions()

    def wait_for_subscribers(self, count: int, *, timeout_s: float) -> bool:
        """Wait until at least ``count`` subscriptions are registered."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while len(self._protocol.registrations()) < count:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._cond.wait(remaining)
            return True

    def wait_fill_below(self, limit: float, *, timeout_s: float) -> bool:
        """Wait until ``fill()`` < ``limit`` (e.g. a consumer took a notification)."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            self._drain_acks()
            while self._protocol.fill() >= limit:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._wait_acks(min(remaining, _WAIT_S))
            return True

    def info(self) -> BufferInfo:
        """Retention, size, span, rate, counters and subscriptions."""
        with self._lock:
            self._drain_acks()
            c = self._counters
            times = list(c.put_times)
            puts, refused, rejected = c.puts, c.refused, c.rejected
            skipped = dict(c.skipped)
            subs = tuple(self._protocol.subscriptions())
            protocol = self._protocol.counters
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
            refused_subscriptions=protocol.refused_registrations,
            limits=self._protocol.limits(),
        )

    def close(self) -> None:
        """Stop serving; subscribers see the service token go."""
        if self._closed:
            return
        self._loop.remove(self)
        with self._send_lock:
            with self._cond:
                self._closed = True
                self._protocol.close()
                events = self._take_events()
                self._cond.notify_all()
            self._carry_out(events)
        self._acks.close()
        with contextlib.suppress(zenoh.ZError):
            self._token_sub.undeclare()


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
