"""The client side of a subscription: a bounded notification queue with flow-control acks.

The queue lives here, in the subscriber's process; the producer mirrors its fill from the
acknowledgements (queued = sent - taken). A notification leaves the queue when ``take``
returns it; processing the element afterwards does not count against the queue. Every
decision (which notification is queued, which ignored, which ack is due and when) is the
sans-IO ``SubscriberProtocol`` in ``_protocol_subscriber``; this module only feeds it from
Zenoh and sends the acks it returns.
"""

from __future__ import annotations

import contextlib
import logging
import secrets
import socket
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from typing import Any

import zenoh

from ._errors import FramegateError, RegistrationRefused
from ._inbox import Inbox, Receiver
from ._ledger_subscriber import REACK_NS, Entry, SubscriberCounters
from ._loop import NodeLoop
from ._protocol_subscriber import RETRY_NS, Item, SubscriberProtocol
from ._records import DataObject, Notification, SubscriptionMode
from ._wire import Keys, holder_chunk

log = logging.getLogger("framegate.middleware")

# A push limit larger than any payload: everything travels with its notification.
PUSH_ALL = 2**31 - 1
_REACK_S = REACK_NS / 1e9
# With nobody taking, the node's loop drains the inbox every ``DRAIN_NS`` (0.25 s): what
# honest traffic can bring in between is the queue's credit plus a resend round or two of
# it, hence the inbox's capacity.
_INBOX_SLACK = 64  # greetings, refusals, doorbells


def inbox_capacity(queue_size: int) -> int:
    """Notifications honest traffic can leave in the inbox between two drains: the credit
    (N), and N again per resend round (every 0.5 s), with room to spare."""
    return 4 * queue_size + _INBOX_SLACK


class Subscription:
    """Availability notifications of one buffer. Create with ``Node.subscribe``.

    Survives restarts of the producing service: the producer re-registers this subscription
    from its liveliness token under a new epoch, and the protocol tracks every epoch it meets.

    Threads (see the README's *Threads*): no Python runs on Zenoh's threads for it.
    Notifications wait in the ``Inbox`` (a Zenoh channel) until a caller of ``take`` drains
    them with ``try_recv`` into the protocol, in one batch; a caller with nothing to take
    blocks in the channel's ``recv`` (the *receiver*, one at a time; others wait in
    ``_cond`` for its news), and the node's loop rings its doorbell at its deadline. With
    nobody taking, the node's loop drains (``on_deadline``). ``_lock`` guards the protocol,
    the inbox's ``Receiver`` and ``_waiting`` (callers blocked in ``_cond``); the inbox is
    drained under it, and only while no receiver blocks in ``recv``. Acks are
    computed under the lock and sent after releasing it: by ``take`` on the caller's
    thread, or by the node's loop when a delayed ack falls due and the caller has not come
    back (``on_deadline``).
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        service: str,
        buffer: str,
        *,
        queue_size: int,
        mode: SubscriptionMode,
        fetch: Callable[[str, int, float], DataObject],
        loop: NodeLoop,
        prefetch: tuple[Callable[[str, int, float], Any], Callable[[str, int, Any], DataObject]]
        | None = None,
        push_max_bytes: int = -1,
        holder: str | None = None,
        on_close: Callable[[Subscription], None] | None = None,
        producer_ids: Callable[[str], frozenset[str]] | None = None,
    ) -> None:
        self._protocol = SubscriberProtocol(mode, queue_size, push_max_bytes)
        self.service = service
        self.buffer = buffer
        self.queue_size = queue_size
        self.mode = mode
        self.subscription_id = secrets.token_hex(6)
        self._session = session
        self._keys = keys
        self._fetch = fetch
        self._prefetch = prefetch
        # Fetches started ahead (timestamp -> pending query), once the caller has fetched
        # an element that did not come along: at most ``queue_size`` in flight.
        self._fetching = False
        self._inflight: OrderedDict[int, Any] = OrderedDict()
        self.fetched_ahead = 0  # fetches answered by a query started ahead
        self._loop = loop
        self._on_close = on_close
        # The Zenoh sessions answering as a service: asked when a refusal must be judged.
        self._producer_ids = producer_ids
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._waiting = 0
        self._closed = False
        self._ack_publisher = session.declare_publisher(
            keys.ack(service, buffer, self.subscription_id),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        notify_key = keys.notify(service, buffer, self.subscription_id)
        self._inbox = Inbox(
            session, notify_key, capacity=inbox_capacity(queue_size), doorbell_key=notify_key
        )
        # A caller blocked in the inbox's recv, and when it wants the doorbell.
        self._receiver = Receiver(self._inbox, self._cond, loop)
        loop.add(self)
        self._holder = holder_chunk(holder, socket.gethostname())
        self._token_key = keys.subscription_token(
            service, buffer, self.subscription_id, mode, queue_size, push_max_bytes, self._holder
        )
        # Declared last: once the producer sees it, notifications may flow.
        self._token = session.liveliness().declare_token(self._token_key)

    @property
    def name(self) -> str:
        return f"{self.service}/{self.buffer}"

    @property
    def missed_total(self) -> int:
        """Notifications lost so far (observers only: flow control loses none)."""
        with self._lock:
            self._drain()
            return self._protocol.missed_total

    @property
    def counters(self) -> SubscriberCounters:
        """Notifications ignored so far, by reason (foreign, duplicate, out of order, ...)."""
        with self._lock:
            self._drain()
            return self._protocol.counters()

    @property
    def garbage(self) -> int:
        """Messages on this subscription's key that were not notifications."""
        with self._lock:
            self._drain()
            return self._protocol.garbage

    # -- Zenoh input (under _lock, on the thread that needs it) ------------------------------
    def _drain(self) -> None:
        """(under _lock) Feed the protocol every notification waiting in the inbox, unless a
        receiver blocks in ``recv``: then the input is its to take."""
        if self._receiver.active:
            return
        for sample in self._inbox.drain():
            self._feed(sample)

    def _feed(self, sample: zenoh.Sample) -> None:
        """(under _lock)"""
        attachment = sample.attachment
        raw = attachment.to_bytes() if attachment is not None else None
        protocol = self._protocol
        before = protocol.registrations
        payload = sample.payload
        # Control messages (the only ones whose sender matters) have an empty payload.
        protocol.receive(raw, payload, None if len(payload) else _sender(sample))
        if protocol.registrations > before > 0:
            log.info(
                "subscription to %s registered again (the producer restarted, or this "
                "subscription had lapsed)",
                self.name,
            )
        lapsed = protocol.lapse_news()
        if lapsed:
            log.warning(
                "subscription to %s had lapsed: %d elements stored meanwhile were never "
                "notified (counted in missed)",
                self.name,
                lapsed,
            )

    def _wait_input(self, wait_s: float) -> None:
        """(holding _lock through ``_cond``) Wait up to ``wait_s`` for Zenoh input, fed to
        the protocol when this returns: as the receiver, blocked in the inbox's ``recv``
        with the loop asked to ring the doorbell at the deadline; or, when another caller
        is the receiver already, in ``_cond`` for its news (see ``Receiver.wait``)."""
        self._waiting += 1
        try:
            sample = self._receiver.wait(wait_s)
        finally:
            self._waiting -= 1
        if sample is not None:
            self._feed(sample)
        self._drain()
        if self._waiting:  # news for them, or their turn to receive
            self._cond.notify_all()

    def trust_producer(self, session_ids: frozenset[str]) -> None:
        """The Zenoh sessions that answer as this subscription's service: only their
        refusals count (see ``SubscriberProtocol``)."""
        with self._lock:
            self._protocol.trust_producer(session_ids)

    @property
    def needs_producer(self) -> bool:
        """A refusal arrived that waits for ``trust_producer`` to be judged."""
        with self._lock:
            self._drain()
            return self._protocol.needs_producer

    def _refused(self, now_ns: int) -> None:
        """(not under _lock; the node's loop) Log a trusted refusal once, as an error naming
        its reason (the producer's message names the holder); declare the token again
        when the retry falls due, so a subscription refused for a limit registers once the
        holder it lost to leaves."""
        with self._lock:
            unjudged = self._protocol.needs_producer
        if unjudged and self._producer_ids is not None:
            self.trust_producer(self._producer_ids(self.service))
        with self._lock:
            news = self._protocol.refusal_news(now_ns)
            retry = self._protocol.retry_due(now_ns)
        if news is not None:
            log.error(
                "%s refused the subscription of %s: %s; retrying every %.0f s",
                self.name,
                self._holder,
                news,
                RETRY_NS / 1e9,
            )
        if retry and not self._closed:
            with contextlib.suppress(zenoh.ZError):
                self._token.undeclare()
                self._token = self._session.liveliness().declare_token(self._token_key)

    def wait_registered(self, timeout_s: float) -> bool:
        """Wait until the producer greets this subscription; RegistrationRefused if it
        refused it (naming the limit). False if neither came within ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            self._drain()
            while self._protocol.registered is None:
                if self._protocol.refusal is not None:
                    raise RegistrationRefused(
                        f"{self.name} refused this subscription: {self._protocol.refusal}"
                    )
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self._closed:
                    return False
                self._wait_input(remaining)
            return True

    # -- the node's loop ---------------------------------------------------------------------
    def next_deadline_ns(self) -> int | None:
        with self._lock:
            due = self._protocol.next_deadline_ns()
            other = self._receiver.deadline_ns()
        if other is not None and (due is None or other < due):
            return other
        return due

    def on_deadline(self, now_ns: int) -> None:
        """Drain the inbox if nobody takes; send a delayed ack that fell due with nobody
        taking since (see ``AckPolicy``); ring the receiver's doorbell at its deadline."""
        with self._lock:
            ring, drain = self._receiver.due(now_ns)
            if drain:
                self._drain()
                if self._waiting:
                    self._cond.notify_all()
            due = self._protocol.next_deadline_ns()
            ready = due is not None and due <= now_ns
            acks = self._protocol.acks(now_ns, idle=False) if ready else []
            refused = self._protocol.registered is None
        self._send_acks(acks)
        if refused:
            self._refused(now_ns)
        if ring:
            self._receiver.ring()

    @property
    def pending(self) -> int:
        """Notifications waiting in this process's queue."""
        with self._lock:
            self._drain()
            return len(self._protocol)

    def take(self, *, timeout_s: float | None = None) -> Notification | None:
        """Take the oldest notification (it leaves the queue now); None on timeout.

        A lost ack heals itself: acks are cumulative, and while waiting idle the subscriber
        repeats them once no ack has left for 0.5 s (the producer resends what it has not
        seen taken).
        """
        notes = self.take_many(1, timeout_s=timeout_s)
        return notes[0] if notes else None

    def take_many(self, max_count: int, *, timeout_s: float | None = None) -> list[Notification]:
        """Take up to ``max_count`` queued notifications, oldest first, waiting up to
        ``timeout_s`` for the first ([] on timeout). They leave the queue together and cost
        at most one cumulative ack (per producer epoch); each still names one element."""
        if max_count < 1:
            raise FramegateError(f"max_count must be >= 1, got {max_count}")
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        protocol = self._protocol
        while True:
            with self._lock:
                self._drain()
                entries = protocol.take_many(max_count)
                acks = protocol.acks(time.monotonic_ns(), idle=not entries)
                if entries:
                    flush_at = protocol.next_deadline_ns()
                elif not acks:
                    if self._closed:
                        return []
                    wait_s = _REACK_S
                    if deadline is not None:
                        wait_s = min(deadline - time.monotonic(), _REACK_S)
                        if wait_s <= 0:
                            return []
                    self._wait_input(wait_s)
                    continue
                if entries and self._waiting and len(protocol):
                    self._cond.notify_all()  # more queued: another caller may take them
            self._send_acks(acks)
            if entries:
                if flush_at is not None:
                    self._loop.poke(flush_at)
                notes = [self._notification(entry) for entry in entries]
                if self._fetching:
                    self._fetch_ahead(notes)
                return notes

    def _send_acks(self, acks: list[bytes]) -> None:
        for ack in acks:
            with contextlib.suppress(zenoh.ZError):
                self._ack_publisher.put(ack)

    def _notification(self, entry: Entry[Item]) -> Notification:
        timestamp, metadata, pushed = entry.item
        element = None
        if pushed is not None and metadata is not None:
            payload = pushed if isinstance(pushed, bytes) else pushed.to_bytes()
            element = DataObject(timestamp, payload, metadata)
        return Notification(
            self.service, self.buffer, timestamp, entry.seq, metadata, element, entry.missed
        )

    def __iter__(self) -> Iterator[Notification]:
        """Notifications until the subscription is closed."""
        while not self._closed:
            note = self.take(timeout_s=0.5)
            if note is not None:
                yield note

    def fetch(self, notification: Notification, *, timeout_s: float = 5.0) -> DataObject:
        """The element a notification names (inline if it came along, else one query).

        A subscription that fetches keeps fetching ahead: once ``fetch`` has queried, every
        notification taken or queued without its element has its query started at once (up
        to the queue size in flight), so elements arrive pipelined, not one round trip each.
        """
        if notification.element is not None:
            return notification.element
        with self._lock:
            pending = self._inflight.pop(notification.timestamp_ns, None)
        if pending is not None:
            self.fetched_ahead += 1
        if pending is None or self._prefetch is None:
            self._fetching = self._prefetch is not None
            return self._fetch(self.name, notification.timestamp_ns, timeout_s)
        return self._prefetch[1](self.name, notification.timestamp_ns, pending)

    def _fetch_ahead(self, taken: list[Notification]) -> None:
        """Start the queries of taken and queued notifications that lack their element."""
        assert self._prefetch is not None
        with self._lock:
            queued = [e.item[0] for e in self._protocol.ledger.queued() if e.item[2] is None]
            wanted = [n.timestamp_ns for n in taken if n.element is None] + queued
            start = [t for t in wanted if t not in self._inflight][: self.queue_size]
        for stamp in start:
            try:
                pending = self._prefetch[0](self.name, stamp, 5.0)
            except FramegateError:
                return  # fetch() will query, and say what failed
            with self._lock:
                self._inflight[stamp] = pending
                while len(self._inflight) > self.queue_size + len(taken):
                    self._inflight.popitem(last=False)

    def close(self) -> None:
        """Withdraw: the producer stops counting this subscription at once."""
        if self._closed:
            return
        self._closed = True
        self._loop.remove(self)
        with self._lock:
            self._cond.notify_all()
        self._inbox.close()  # ends a receiver's recv
        for entity in (self._token, self._ack_publisher):
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()
        if self._on_close is not None:
            self._on_close(self)

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *_exc: Any) -> None:
        self.close()


def _sender(sample: zenoh.Sample) -> str | None:
    """The Zenoh session a sample names as its source (None: it names none)."""
    info = sample.source_info
    return str(info.source_id.zid) if info is not None else None
