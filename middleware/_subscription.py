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
from typing import Any, TypeVar

import zenoh

from ._decode import printable
from ._errors import FramegateError, RegistrationRefused
from ._executor import BUDGET, Executor, Wake, remaining_s
from ._inbox import Inbox
from ._ledger_subscriber import REACK_NS, AckPolicy, Entry, SubscriberCounters
from ._news import News
from ._protocol_subscriber import RETRY_NS, Item, SubscriberProtocol
from ._records import DataObject, Notification, SubscriptionMode, data_object, notification
from ._wire import Keys, holder_chunk

T = TypeVar("T")

log = logging.getLogger("framegate.middleware")

# A push limit larger than any payload: everything travels with its notification.
PUSH_ALL = 2**31 - 1
_REACK_S = REACK_NS / 1e9
_INBOX_SLACK = 64  # greetings, refusals


def inbox_capacity(queue_size: int) -> int:
    """Notifications honest traffic can leave in the inbox between two executor turns: the
    credit (N), and N again per resend round (every 0.5 s), with room to spare."""
    return 4 * queue_size + _INBOX_SLACK


Handler = Callable[[list[Notification]], object]


class Subscription:
    """Availability notifications of one buffer. Create with ``Node.subscribe``.

    Survives restarts of the producing service: the producer re-registers this subscription
    from its liveliness token under a new epoch, and the protocol tracks every epoch it meets.

    Threads (see docs/threads.md): Zenoh's thread only appends each notification to the
    bounded ``Inbox`` and wakes whoever needs it (``Wake``): with a handler (``Node.on``)
    the node's executor, which feeds a bounded batch to the protocol per turn and runs the
    handler on a bounded batch of taken notifications (``run_ready``); else a caller of
    ``take`` blocked in ``_cond``, which feeds the input itself. The executor also sends
    delayed acks when they fall due (``on_deadline``) and works off a backlog nobody takes.
    ``_lock`` guards the protocol, the fetches in flight and the ``Wake`` counts; acks are
    computed under it and sent after releasing it.
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
        fetch: Callable[[str, int, float, str | None], DataObject],
        executor: Executor,
        prefetch: tuple[Callable[[str, int, float, str | None], Any], Callable[..., DataObject]]
        | None = None,
        push_max_bytes: int = -1,
        holder: str | None = None,
        on_close: Callable[[Subscription], None] | None = None,
        producer_ids: Callable[[str], frozenset[str]] | None = None,
        ack_each_take: bool = False,
    ) -> None:
        policy = AckPolicy() if ack_each_take else None  # None: coalesced (docs/protocol.md)
        self._protocol = SubscriberProtocol(mode, queue_size, push_max_bytes, policy=policy)
        self.service = service
        self.buffer = buffer
        self.queue_size = queue_size
        self.mode = mode
        self.subscription_id = secrets.token_hex(6)
        self._session = session
        self._keys = keys
        self._fetch = fetch
        self._prefetch = prefetch
        # Fetches started ahead (timestamp -> pending query), at most ``queue_size`` in flight.
        self._inflight: OrderedDict[int, Any] = OrderedDict()
        self.fetched_ahead = 0  # fetches answered by a query started ahead
        self._executor = executor
        self.scheduled = False  # the executor's flag (see ``Source``)
        self._handler: Handler | None = None
        self._max_batch = 1
        self._idle_ack_at_ns = 0  # with a handler: when to repeat acks while nothing comes
        self._on_close = on_close
        # The Zenoh sessions answering as a service: asked when a refusal must be judged.
        self._producer_ids = producer_ids
        self._lock = threading.Lock()
        self._news = News(f"{service}/{buffer}", log)  # under _lock
        self._cond = threading.Condition(self._lock)
        self._ack_lock = threading.Lock()  # ack puts against the publisher's undeclare
        self._closed = False
        # A caller waits in ``subscribe(wait_s=)``: a refusal is raised to it, not logged.
        self.caller_waits = False
        self._ack_publisher = session.declare_publisher(
            keys.ack(service, buffer, self.subscription_id),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        self._wake = Wake(self, self._cond, executor, lambda: len(self._inbox))
        # Until the producer greets it, the producer's answer is the executor's to read: a
        # refusal must be logged and retried even when nobody takes (see ``_refused``).
        self._wake.executor_owned = True
        self._inbox = Inbox(
            capacity=inbox_capacity(queue_size),
            max_bytes=self._protocol.max_message_bytes(),
            signal=self._wake.signal,
        )
        self._holder = holder_chunk(holder, socket.gethostname())
        self._token_key = keys.subscription_token(
            service, buffer, self.subscription_id, mode, queue_size, push_max_bytes, self._holder
        )
        # Its deadlines are read on the executor thread from now on: every field they use
        # is set (the token is declared only once input can come, below).
        executor.add(self)
        self._inbox.declare(session, keys.notify(service, buffer, self.subscription_id))
        # Declared last: once the producer sees it, notifications may flow.
        self._token = session.liveliness().declare_token(self._token_key)

    @property
    def name(self) -> str:
        return f"{self.service}/{self.buffer}"

    @property
    def missed_total(self) -> int:
        """Elements lost so far: out of an observer's full queue, or while the token lapsed."""
        return self._fed(lambda protocol: protocol.missed_total)

    @property
    def counters(self) -> SubscriberCounters:
        """Notifications ignored so far, by reason (foreign, duplicate, out of order, ...)."""
        return self._fed(lambda protocol: protocol.counters())

    @property
    def dropped(self) -> int:
        """Messages dropped unread: larger than this subscription's notifications can be,
        or pushed out of its full inbox by newer ones (a flood; what was lost of honest
        traffic is resent, or counted in ``missed_total`` for an observer)."""
        return self._inbox.dropped

    @property
    def garbage(self) -> int:
        """Messages on this subscription's key that were not notifications."""
        return self._fed(lambda protocol: protocol.garbage)

    # -- input (on the executor, or inline on a caller that looks) ------------------
    def _fed(self, read: Callable[[SubscriberProtocol], T]) -> T:
        """``read(protocol)`` after feeding it a bounded batch of waiting input."""
        with self._lock:
            self._feed(BUDGET)
            return read(self._protocol)

    def _feed(self, budget: int) -> None:
        """(under _lock) Feed the protocol at most ``budget`` waiting notifications."""
        protocol = self._protocol
        needs_sender = protocol.needs_sender
        for sample in self._inbox.take(budget):
            attachment = sample.attachment
            raw = attachment.to_bytes() if attachment is not None else None
            payload = sample.payload
            protocol.receive(raw, payload, _sender(sample) if needs_sender(payload) else None)
        again, lapsed = protocol.registration_news(), protocol.lapse_news()
        if again or lapsed:  # said at a bounded rate: a peer can forge greetings
            self._news.report(again, lapsed, time.monotonic_ns())

    def run_ready(self, budget: int) -> bool:
        """(the executor) Feed a bounded batch; then run the handler on a bounded batch of
        taken notifications, or wake the callers of ``take``. True if more is waiting."""
        with self._lock:
            if self._closed:
                return False
            self._feed(budget)
            handler = self._handler
            answered = self._protocol.registered_epoch is not None
            self._wake.executor_owned = handler is not None or not answered
            if self._protocol.refusal_to_judge:
                self._executor.poke(0)  # judged on the executor's next turn
            if handler is None:
                if self._wake.threads:
                    self._cond.notify_all()
                return len(self._inbox) >= budget
        notes = self._take(self._max_batch, idle=False)
        if notes:
            handler(notes)
        with self._lock:
            return len(self._inbox) > 0 or len(self._protocol) > 0

    def handle(self, handler: Handler, max_batch: int) -> None:
        """Have the executor call ``handler`` with up to ``max_batch`` notifications each
        time some are queued (see ``Node.on``)."""
        if max_batch < 1:
            raise FramegateError(f"max_batch must be >= 1, got {max_batch}")
        with self._lock:
            if self._handler is not None:
                raise FramegateError(f"{self.name} already has a handler")
            self._handler = handler
            self._max_batch = max_batch
            self._idle_ack_at_ns = time.monotonic_ns() + REACK_NS
            self._wake.executor_owned = True
        self._executor.signal(self)  # what is queued already

    def judge_refusal(self) -> None:
        """Judge a refusal that arrived: it counts only from a session that answers as this
        subscription's service (asked here, on the calling thread, when the protocol
        needs it; not under ``_lock``)."""
        now = time.monotonic_ns()
        if self._fed(lambda protocol: protocol.judge(now)):
            ids = self._producer_ids(self.service) if self._producer_ids else frozenset()
            with self._lock:
                self._protocol.trust_producer(ids, now)

    def _refused(self, now_ns: int) -> None:
        """(the executor, not under _lock) Judge a refusal; log a trusted one once, as an
        error naming its reason (the producer's message names the holder); declare the
        token again when the retry falls due, so a subscription refused for a limit
        registers once the holder it lost to leaves."""
        self.judge_refusal()
        with self._lock:
            news = self._protocol.refusal_news()
            retry = self._protocol.retry_due(now_ns)
        if news is not None and not (self.caller_waits or self._closed):
            log.error(
                "%s refused the subscription of %s: %s; retrying every %.0f s",
                self.name,
                self._holder,
                printable(news),
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

        def answered() -> bool:
            self._feed(BUDGET)
            if self._protocol.refusal is not None and self._protocol.registered_epoch is None:
                raise RegistrationRefused(
                    f"{self.name} refused this subscription: {printable(self._protocol.refusal)}"
                )
            return self._protocol.registered_epoch is not None

        try:
            with self._cond:
                while not self._wake.wait(answered, remaining_s(deadline)):
                    if time.monotonic() >= deadline or self._closed:
                        return False
                return True
        finally:
            self._wake.left_over(len(self._inbox))

    # -- deadlines (the executor) ------------------------------------------------------
    def next_deadline_ns(self) -> int | None:
        with self._lock:
            due = self._protocol.next_deadline_ns()
            if self._handler is not None and (due is None or self._idle_ack_at_ns < due):
                due = self._idle_ack_at_ns
            return due

    def on_deadline(self, now_ns: int) -> None:
        """Send a delayed ack that fell due with nobody taking since (see ``AckPolicy``);
        with a handler, repeat acks while nothing comes (a lost ack heals)."""
        with self._lock:
            idle = False
            if self._handler is not None and self._idle_ack_at_ns <= now_ns:
                self._idle_ack_at_ns = now_ns + REACK_NS
                idle = len(self._protocol) == 0
            due = self._protocol.next_deadline_ns()
            ready = idle or (due is not None and due <= now_ns)
            acks = self._protocol.acks(now_ns, idle=idle) if ready else []
            refused = self._protocol.registered_epoch is None
        self._send_acks(acks)
        if refused:
            self._refused(now_ns)

    @property
    def registered_epoch(self) -> str | None:
        """The epoch the producer greeted this subscription with (None: not registered);
        only a greeting changes it."""
        return self._fed(lambda protocol: protocol.registered_epoch)  # a waiting greeting too

    @property
    def producer_session(self) -> str | None:
        """The Zenoh session that greeted the registration whose notifications came last
        (None: not registered): the one whose answers in its service's name count (a clock
        sample, a fetched element). See ``SubscriberProtocol.data_session``."""
        return self._fed(lambda protocol: protocol.data_session)

    @property
    def producer_epoch(self) -> str | None:
        """The instance part of ``registered_epoch``: it changes when the producer
        restarted or another process took its name."""
        epoch = self.registered_epoch
        return None if epoch is None else epoch.partition(".")[0]

    # -- taking ----------------------------------------------------------------------------
    @property
    def pending(self) -> int:
        """Notifications waiting in this process's queue."""
        return self._fed(len)

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
        at most one cumulative ack (per producer epoch); each still names one element.

        Not for a subscription with a handler (``Node.on``): the executor takes for it."""
        if max_count < 1:
            raise FramegateError(f"max_count must be >= 1, got {max_count}")
        if self._handler is not None:
            raise FramegateError(
                f"{self.name} has a handler (Node.on): its notifications go to the handler"
            )
        deadline = None if timeout_s is None else time.monotonic() + timeout_s

        def queued() -> bool:
            self._feed(BUDGET)
            return len(self._protocol) > 0 or self._closed

        try:
            while True:
                notes = self._take(max_count, idle=True)
                if notes:
                    return notes
                with self._cond:
                    if self._closed:
                        return []
                    left = _REACK_S if deadline is None else deadline - time.monotonic()
                    wait_s = min(left, _REACK_S)
                    if wait_s <= 0:
                        return []
                    # A delayed ack that falls due while this caller waits is sent by it
                    # (the next ``_take``), not by waking the executor (see ``_take``).
                    due_ns = self._protocol.next_deadline_ns()
                    if due_ns is not None and due_ns > time.monotonic_ns():
                        wait_s = min(wait_s, (due_ns - time.monotonic_ns()) / 1e9)
                    self._wake.wait(queued, wait_s)
        finally:
            self._wake.left_over(len(self._inbox))

    def _take(self, max_count: int, *, idle: bool) -> list[Notification]:
        """Take what is queued now (after feeding a bounded batch) and send the acks due;
        ``idle``: nothing taken means the caller waits (acks are repeated then)."""
        protocol = self._protocol
        with self._lock:
            self._feed(BUDGET)
            entries = protocol.take_many(max_count)
            acks = protocol.acks(time.monotonic_ns(), idle=idle and not entries)
            fetching = protocol.fetching
            if entries and self._wake.threads and len(protocol):
                self._cond.notify_all()  # more queued: another caller may take them
        self._send_acks(acks)
        if not entries:
            return []
        # An ack this take delayed (``AckPolicy``) is not announced to the executor: waking
        # it cost more per element than the ack itself. The caller sends it when it comes
        # back to wait (``take_many``), a handler's executor reads the deadline after the
        # handler; a caller that stays away leaves it to the executor's next turn (at most
        # its longest sleep). Meanwhile the producer sees at most ``N // 2 - 1`` taken
        # elements as queued, as between two acks of a busy subscriber.
        notes = self._notifications(entries)
        if fetching:
            self._fetch_ahead(notes)
        return notes

    def _send_acks(self, acks: list[bytes]) -> None:
        # A lost ack costs nothing: acks are cumulative and repeated.
        if not acks:
            return
        with self._ack_lock:
            if self._closed:
                return
            for ack in acks:
                with contextlib.suppress(zenoh.ZError):
                    self._ack_publisher.put(ack)

    def _notifications(self, entries: list[Entry[Item]]) -> list[Notification]:
        """The taken entries as notifications (one loop: it runs once per element)."""
        service, buffer = self.service, self.buffer
        notes: list[Notification] = []
        append = notes.append
        for epoch, seq, (timestamp, metadata, pushed), missed in entries:
            element = None
            if pushed is not None and metadata is not None:
                payload = pushed if type(pushed) is bytes else pushed.to_bytes()
                element = data_object(timestamp, payload, metadata)
            append(notification(service, buffer, timestamp, seq, metadata, element, missed, epoch))
        return notes

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
            elif self._prefetch is not None:
                self._protocol.fetching = True  # from now on, fetch ahead
        # Only the producer's answer counts: any session may answer a query, and a peer's
        # reply stamped alike was taken for the element, its garbage voided the answer.
        session = self.producer_session
        if pending is None or self._prefetch is None:
            return self._fetch(self.name, notification.timestamp_ns, timeout_s, session)
        return self._prefetch[1](self.name, notification.timestamp_ns, pending, session)

    def _fetch_ahead(self, taken: list[Notification]) -> None:
        """Start the queries the protocol says to start ahead (see ``fetch``)."""
        assert self._prefetch is not None
        missing = [n.timestamp_ns for n in taken if n.element is None]
        with self._lock:
            start = self._protocol.fetch_ahead(missing, self._inflight)
        for stamp in start:
            try:
                pending = self._prefetch[0](self.name, stamp, 5.0, self.producer_session)
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
        self._executor.remove(self)
        with self._lock:
            self._cond.notify_all()
        self._inbox.close()
        # Not while another thread puts an ack on it (zenoh-python refuses an undeclare
        # during a put on the same publisher: "Already borrowed").
        with self._ack_lock:
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
