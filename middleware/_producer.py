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
import logging
import secrets
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import zenoh

from ._buffer import TimeSeries
from ._element_check import ElementCheck
from ._errors import ClosedError, FlowControlRefused, FramegateError
from ._executor import BUDGET as _BUDGET
from ._executor import Executor, Wake, remaining_s
from ._inbox import ACK_MAX_BYTES, TOKEN_INBOX, AckInbox, TokenInbox, control_inbox_bytes
from ._ledger_producer import RegistrationKey
from ._liveliness import LiveQuery
from ._protocol_events import Event, Publish, Retire
from ._protocol_producer import RESYNC_TOKENS, ProducerProtocol
from ._rate import PutRate
from ._records import BufferInfo, DataObject, Retention, Rewind, SubscriptionInfo
from ._wire import Keys
from ._xml import XmlLimits

log = logging.getLogger("framegate.middleware")

# Elements stamped further ahead of this process's clock are refused: a stamp a consumer
# cannot bound must never reach it (docs/time.md).
HORIZON_NS = 10_000_000_000
# A put that waits for credit looks again at least this often (it is woken at once when an
# ack arrives; this only bounds what a missed wake-up could cost).
_WAIT_S = 0.1
# Rewinds ``info`` lists (each one is also counted in ``skipped``).
_REWINDS_KEPT = 16


@dataclass
class _Counters:
    puts: int = 0
    refused: int = 0
    rejected: int = 0
    skipped: dict[str, int] = field(default_factory=dict)
    # When puts came and how many elements each held: a batch is one event (``_rate``).
    put_rate: PutRate = field(default_factory=PutRate)
    # The latest rewinds, for ``info``; older ones stay counted in ``skipped``.
    rewinds: deque[Rewind] = field(default_factory=lambda: deque(maxlen=_REWINDS_KEPT))


class Producer:
    """A buffer offered by this process. Create with ``Node.offer``.

    Threads: Zenoh's threads only append acks and tokens to two bounded inboxes; the
    executor, or a caller that needs current credit, feeds them to the protocol in bounded
    batches. ``_lock`` (with ``_cond``) guards the protocol and the counters, ``_send_lock``
    orders sending; which thread takes which, and in what order: docs/threads.md.
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
        executor: Executor,
        horizon_ns: int = HORIZON_NS,
    ) -> None:
        self.service = service
        self.buffer = buffer
        self.kind = kind
        self.series = TimeSeries(retention)
        self.inline_max_bytes = inline_max_bytes
        self.horizon_ns = horizon_ns
        self._check = ElementCheck(self.name_of(service, buffer), kind, xml_limits, horizon_ns)
        self._session = session
        self._executor = executor
        self.scheduled = False  # the executor's flag (see ``Source``)
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
        self._on_change: Callable[[], object] | None = None
        self._wake = Wake(self, self._cond, executor, lambda: len(self._acks))
        # Acks are fed by whoever needs credit next (a put, ``info``, the executor before a
        # resend); only a waiting put, or a backlog, wakes anyone (``Wake``).
        self._acks = AckInbox(
            max_bytes=ACK_MAX_BYTES,
            signal=self._wake.signal,
            plausible=self._protocol.plausible_ack,
            retired=self._protocol.retired_epoch,
            on_retired=self._signal,
        )
        # A token (a key, no payload) is the executor's at once: a subscriber awaits a greeting.
        self._token_keys = keys.subscription_tokens(service, buffer)
        self._lost = (0, 0)  # see ``_feed``
        self._resync: LiveQuery | None = None  # in flight (the executor's)
        self._tokens = TokenInbox(capacity=TOKEN_INBOX, signal=self._signal)
        # Its deadlines are read on the executor thread from now on: every field is set.
        executor.add(self)
        self._acks.declare(session, keys.acks(service, buffer))
        # Declared last: its callback (history included) may run at once.
        self._tokens.declare(session, self._token_keys, liveliness=True)

    @property
    def name(self) -> str:
        return self.name_of(self.service, self.buffer)

    @staticmethod
    def name_of(service: str, buffer: str) -> str:
        return f"{service}/{buffer}"

    def _signal(self) -> None:
        """(Zenoh's thread) New input: the executor's turn (a lock only when not yet due)."""
        if not self.scheduled:
            self._executor.signal(self)

    # -- input (on the executor, or inline on a caller that needs current credit) ----------
    def _feed(self, budget: int) -> bool:
        """(under _lock) Feed the protocol at most ``budget`` acks and as many tokens; True
        if anything changed for a waiting put (credit freed, a subscriber came or went)."""
        # Signs of lost token events (``ProducerProtocol.tokens_lost``): churn overflowed
        # the token inbox, or the ack inbox dropped acks of a registration we retired.
        lost = (self._tokens.dropped, self._acks.retired)
        if not (self._acks or self._tokens) and lost == self._lost:
            return False  # every put asks: nothing came is the common case
        changed = False
        ack = self._protocol.ack
        now = time.monotonic_ns()
        for message in self._acks.take(budget):
            changed |= ack(message.key, message.payload, now, message.ack)
        for message in self._tokens.take(budget):
            self._protocol.token(message.key, message.alive, now)
            changed = True
        if lost != self._lost:
            self._lost = lost
            self._protocol.tokens_lost(now)
        return changed

    def run_ready(self, budget: int) -> bool:
        """(the executor) A bounded batch of input; the events it produced carried out."""
        if self._resync is not None and not self._closed:  # its end may come after close
            self._resync_step(time.monotonic_ns())
        with self._send_lock:
            with self._lock:
                if self._closed:
                    return False
                changed = self._feed(budget)
                if changed and self._wake.threads:
                    self._cond.notify_all()
                events = self._protocol.events()
            self._carry_out(events)
        if changed and self._on_change is not None:
            self._on_change()
        return len(self._tokens) > 0 or len(self._acks) >= budget

    def on_change(self, fn: Callable[[], object] | None) -> None:
        """Run ``fn()`` on the executor when input changed what a put would see (credit
        freed, a subscriber came or went); while set, acks wake the executor."""
        with self._cond:
            self._on_change = fn
            self._wake.executor_owned = fn is not None

    def next_deadline_ns(self) -> int | None:
        with self._lock:
            due = self._protocol.next_deadline_ns()
        awaited = self._resync.deadline_ns if self._resync is not None else None  # its timeout
        return min((d for d in (due, awaited) if d is not None), default=None)

    def _resync_step(self, now_ns: int) -> None:
        """(the executor, never waiting) A resync after lost token events: its liveliness
        query goes out when due; its answer is fed once it ended (Zenoh's end wakes us)."""
        query = self._resync
        if query is None:
            with self._lock:
                if not self._protocol.resync_due(now_ns):
                    return
                self._protocol.resync_begin()  # token events fed from now on are newer
            keys, limit = self._token_keys, RESYNC_TOKENS  # a peer may declare more
            self._resync = LiveQuery(
                self._session, keys, timeout_s=1.0, limit=limit, on_end=self._signal
            )
        elif query.done(now_ns):
            self._resync = None
            live, whole = query.answer()
            with self._lock:
                self._protocol.resync(live, time.monotonic_ns(), ended=whole)

    def on_deadline(self, now_ns: int) -> None:
        """(the executor) Resends that are due, once a batch of waiting acks has been fed
        (more than a batch is a backlog, fed turn by turn: ``Wake``); a resync's step."""
        self._resync_step(now_ns)
        with self._send_lock:
            with self._lock:
                if self._closed:
                    return
                if self._feed(_BUDGET) and self._wake.threads:
                    self._cond.notify_all()
                self._protocol.tick(now_ns)
                events = self._protocol.events()
            self._carry_out(events)

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
            raise ClosedError(f"buffer {self.name} is closed")
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
            raise ClosedError(f"buffer {self.name} is closed")
        if not elements:
            return 0
        try:
            checked = self._check.batch(elements)
        except FramegateError:
            with self._lock:
                self._counters.rejected += 1
            raise
        return self._put(checked, wait_s)

    def _put(self, elements: tuple[DataObject, ...], wait_s: float) -> int:
        count = len(elements)
        send_lock = self._send_lock
        deadline = time.monotonic() + wait_s if wait_s > 0 else 0.0
        waited = False
        try:
            while True:
                # A put without wait_s waits for a send in progress, as before; one with a
                # deadline waits for it no longer than that. Uncontended (the common case)
                # it is taken at once, without reading the clock.
                if not send_lock.acquire(False) and not send_lock.acquire(
                    timeout=max(0.0, deadline - time.monotonic()) if wait_s > 0 else -1
                ):
                    with self._lock:
                        self._counters.refused += count
                        refusal = self._protocol.admit(count, may_wait=False)
                    raise FlowControlRefused(
                        refusal.message(elements[0].timestamp_ns)
                        if refusal is not None
                        else f"{self.name}: could not send within wait_s={wait_s:g}"
                    )
                try:
                    with self._lock:
                        self._feed(_BUDGET)  # credit as of now
                        may_wait = wait_s > 0 and deadline > time.monotonic()
                        refusal = self._protocol.admit(count, may_wait=may_wait)
                        if refusal is None:
                            notified = self._store(elements)
                        else:
                            if wait_s > 0:
                                # An element that can never be stored is not waited for
                                # (``_store`` checks it in any case).
                                try:
                                    self.series.check_extend(elements)
                                except FramegateError:
                                    self._counters.rejected += count
                                    raise
                            if not refusal.wait:
                                self._counters.refused += count
                        events = self._protocol.events()
                    if events:
                        self._carry_out(events)
                finally:
                    send_lock.release()
                if refusal is None:
                    return notified
                if not refusal.wait:
                    raise FlowControlRefused(refusal.message(elements[0].timestamp_ns))
                # Not stored: wait for credit outside _send_lock (the executor keeps sending).
                waited = True
                with self._cond:
                    self._wake.wait(
                        lambda: self._has_room(count), min(remaining_s(deadline), _WAIT_S)
                    )
        finally:
            if waited:
                self._wake.left_over(len(self._acks) + len(self._tokens))

    def _has_room(self, count: int) -> bool:
        """(under _lock) Whether ``count`` elements fit now, after feeding a batch."""
        self._feed(_BUDGET)
        return self._protocol.admit(count, may_wait=False) is None

    def _checked(self, timestamp_ns: int, payload: bytes, metadata: bytes | str) -> DataObject:
        try:
            return self._check(timestamp_ns, payload, metadata)
        except FramegateError:
            with self._lock:
                self._counters.rejected += 1
            raise

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
        self._counters.put_rate.add(now, len(elements))
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
                if event.control:
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
                if event.epoch is not None:  # a notification (a control is not resent)
                    with self._lock:
                        self._protocol.send_failed(event.key, event.epoch)

    def discard_after(self, timestamp_ns: int, reason: str) -> int:
        """Remove the elements stamped after ``timestamp_ns`` (at most ``horizon_ns`` back
        from the newest), so that later puts may be stamped from there on; how many. Counted
        in ``info`` as skipped by ``reason`` and recorded as a ``Rewind``; logged. The caller
        decides it from its source's own restart and clock records, never from one element.
        Subscribers keep what was pushed to them; a fetch of a removed one finds nothing.
        """
        with self._lock:
            newest = self.series.newest_ns
            if newest is not None:
                timestamp_ns = max(timestamp_ns, newest - self.horizon_ns)
            removed = self.series.discard_after(timestamp_ns)
            if removed:
                skipped = self._counters.skipped
                skipped[reason] = skipped.get(reason, 0) + len(removed)
                self._counters.rewinds.append(Rewind.of(timestamp_ns, removed, reason))
        if removed:
            log.warning("%s: %d elements after %d removed (%s)", self.name, len(removed),
                        timestamp_ns, reason)  # fmt: skip
        return len(removed)

    def count_skip(self, reason: str, count: int = 1) -> None:
        """Count ``count`` elements the service chose not to put, e.g. ``late`` frames a
        camera could not produce in time; ``info`` shows them by reason."""
        with self._lock:
            skipped = self._counters.skipped
            skipped[reason] = skipped.get(reason, 0) + count

    # -- reading state -------------------------------------------------------------------
    def subscriptions(self) -> list[SubscriptionInfo]:
        """Every live subscription (registration) as this producer counts it."""
        with self._lock:
            self._feed(_BUDGET)
            return self._protocol.subscriptions()

    def wait_for_subscribers(self, count: int, *, timeout_s: float) -> bool:
        """Wait until at least ``count`` subscriptions are registered."""
        deadline = time.monotonic() + timeout_s

        def enough() -> bool:
            self._feed(_BUDGET)
            return len(self._protocol.registrations()) >= count

        try:
            with self._cond:
                while not self._wake.wait(enough, remaining_s(deadline)):
                    if time.monotonic() >= deadline:
                        return False
                return True
        finally:
            self._wake.left_over(len(self._acks) + len(self._tokens))

    def info(self) -> BufferInfo:
        """Retention, size, span, rate, counters and subscriptions."""
        with self._lock:
            self._feed(_BUDGET)
            c = self._counters
            rate = c.put_rate.hz(time.monotonic_ns())
            puts, refused, rejected = c.puts, c.refused, c.rejected
            skipped, rewinds = dict(c.skipped), tuple(c.rewinds)
            subs = tuple(self._protocol.subscriptions())
            protocol = replace(self._protocol.counters)  # a copy: read outside the lock
            foreign = self._protocol.foreign_acks + self._acks.foreign  # either drops one
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
            rewinds=rewinds,
            limits=replace(self._protocol.limits(), control_inbox_bytes=control_inbox_bytes()),
            dropped_messages=self._acks.dropped + self._tokens.dropped,
            bad_messages=protocol.bad_messages,
            foreign_acks=foreign,
            collapsed_tokens=self._tokens.collapsed,
        )

    def close(self) -> None:
        """Stop serving; subscribers see the service token go."""
        if self._closed:
            return
        self._executor.remove(self)
        self._acks.close()
        self._tokens.close()
        with self._send_lock:
            with self._cond:
                self._closed = True
                self._protocol.close()
                events = self._protocol.events()
                self._cond.notify_all()
            self._carry_out(events)
