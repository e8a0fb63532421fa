"""The client side of a subscription: a bounded notification queue with flow-control acks.

The queue lives here, in the subscriber's process; the producer mirrors its fill from the
acknowledgements (queued = sent - taken). A notification leaves the queue when ``take``
returns it; processing the element afterwards does not count against the queue. The
protocol itself (which notification is queued, which ignored, which ack is due) is the pure
``SubscriberLedger`` in ``_ledger_subscriber``; this module only feeds it from Zenoh and
sends the acks it returns.
"""

from __future__ import annotations

import contextlib
import secrets
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import zenoh

from ._errors import FramegateError
from ._ledger_subscriber import REACK_NS, AckPolicy, Entry, SubscriberCounters, SubscriberLedger
from ._records import DataObject, Notification, SubscriptionMode
from ._wire import BatchHeader, Header, Keys, decode_notification_header, encode_ack

# A push limit larger than any payload: everything travels with its notification.
PUSH_ALL = 2**31 - 1
_REACK_S = REACK_NS / 1e9

# What the queue holds per notification: timestamp_ns, metadata, the pushed payload. A
# single element's payload stays Zenoh's ZBytes until ``take`` (on the caller's thread) turns
# it into bytes: copying a large frame on Zenoh's receive thread stalls every other message
# behind it. A batch (meant for many small elements) is split into bytes on arrival.
_Item = tuple[int, bytes | None, zenoh.ZBytes | bytes | None]


class Subscription:
    """Availability notifications of one buffer. Create with ``Node.subscribe``.

    Survives restarts of the producing service: the producer re-registers this subscription
    from its liveliness token under a new epoch, and the ledger tracks every epoch it meets.

    Threads: ``_on_notification`` runs on Zenoh's thread; it decodes the header, then takes
    ``_lock`` once to feed the ledger, and never calls Zenoh nor copies a single element's
    payload (``take`` does, on the caller's thread). ``_lock`` guards the ledger, ``garbage``
    and ``_waiting`` (callers blocked in ``_cond``, a condition on ``_lock``: the callback
    notifies only when someone waits). Acks are computed under the lock and sent after
    releasing it (``take`` on the caller's thread), so a blocking ack put never holds a lock
    the callback needs. With a delayed-ack policy (queues of 4 and more) the ``fg-ack``
    thread sends an emptied queue's ack when its delay is up and the caller has not come
    back to take; the caller wakes it (``_flush_wake``) only when such an ack appears while
    it watches none (``_flush_armed``, under ``_lock``).
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
        push_max_bytes: int = -1,
        on_close: Callable[[Subscription], None] | None = None,
    ) -> None:
        if queue_size < 1:
            raise FramegateError(f"queue_size must be >= 1, got {queue_size}")
        self.service = service
        self.buffer = buffer
        self.queue_size = queue_size
        self.mode = mode
        self.subscription_id = secrets.token_hex(6)
        self._session = session
        self._keys = keys
        self._fetch = fetch
        self._on_close = on_close
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._waiting = 0
        self._ledger: SubscriberLedger[_Item] = SubscriberLedger(
            mode,
            queue_size,
            f"{mode.value}/{queue_size}/{push_max_bytes}",
            policy=AckPolicy.for_queue(queue_size),
        )
        self.garbage = 0
        self._closed = False
        self._ack_publisher = session.declare_publisher(
            keys.ack(service, buffer, self.subscription_id),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        self._subscriber = session.declare_subscriber(
            keys.notify(service, buffer, self.subscription_id),
            zenoh.handlers.Callback(self._on_notification, indirect=False),
        )
        # Acks held back by the ledger's delay are sent by this thread if the caller does
        # not come back to take (``_flush_armed``: it has been told there is one to watch).
        self._flush_wake = threading.Event()
        self._flush_armed = False
        self._flusher: threading.Thread | None = None
        if self._ledger.policy.delay_ns:
            self._flusher = threading.Thread(
                target=self._flush_loop, daemon=True, name=f"fg-ack-{service}/{buffer}"
            )
            self._flusher.start()
        # Declared last: once the producer sees it, notifications may flow.
        self._token = session.liveliness().declare_token(
            keys.subscription_token(
                service, buffer, self.subscription_id, mode, queue_size, push_max_bytes
            )
        )

    @property
    def name(self) -> str:
        return f"{self.service}/{self.buffer}"

    @property
    def missed_total(self) -> int:
        """Notifications lost so far (observers only: flow control loses none)."""
        with self._lock:
            return self._ledger.missed_total

    @property
    def counters(self) -> SubscriberCounters:
        """Notifications ignored so far, by reason (foreign, duplicate, out of order, ...)."""
        with self._lock:
            c = self._ledger.counters
            return SubscriberCounters(c.foreign, c.invalid, c.out_of_order, c.duplicates, c.refused)

    def _on_notification(self, sample: zenoh.Sample) -> None:
        try:
            attachment = sample.attachment
            if attachment is None:
                raise ValueError("notification without a header")
            head = decode_notification_header(attachment.to_bytes())
            if isinstance(head, Header):
                metadata = head.metadata
                pushed = sample.payload if head.pushed and metadata is not None else None
                item: _Item = (head.timestamp_ns, metadata, pushed)
                items = None
            else:
                items = _batch_items(head, sample.payload)
        except Exception:  # garbage on our key is counted, never raised into Zenoh
            with self._lock:
                self.garbage += 1
            return
        with self._lock:
            if items is None:
                queued = self._ledger.receive(
                    head.epoch, head.seq, item, descriptor=head.descriptor
                )
            else:
                queued = (
                    self._ledger.receive_many(
                        head.epoch, head.seq, items, descriptor=head.descriptor
                    )
                    > 0
                )
            if queued and self._waiting:
                self._cond.notify_all()

    @property
    def pending(self) -> int:
        """Notifications waiting in this process's queue."""
        with self._lock:
            return len(self._ledger)

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
        ledger = self._ledger
        while True:
            with self._lock:
                entry = ledger.take()
                if entry is not None:
                    entries = [entry]
                    while len(entries) < max_count and (entry := ledger.take()) is not None:
                        entries.append(entry)
                    acks = ledger.acks_due(time.monotonic_ns(), idle=False)
                    # Wake the flusher only when a delayed ack appears while it watches none.
                    wake = (
                        self._flusher is not None
                        and not self._flush_armed
                        and ledger.flush_at_ns() is not None
                    )
                    if wake:
                        self._flush_armed = True
                else:
                    wake = False
                    entries = []
                    acks = ledger.acks_due(time.monotonic_ns(), idle=True)
                    if not acks:
                        if self._closed:
                            return []
                        wait_s = _REACK_S
                        if deadline is not None:
                            wait_s = min(deadline - time.monotonic(), _REACK_S)
                            if wait_s <= 0:
                                return []
                        self._waiting += 1
                        try:
                            self._cond.wait(wait_s)
                        finally:
                            self._waiting -= 1
                        continue
            if wake:
                self._flush_wake.set()
            self._send_acks(acks)
            if entries:
                return [self._notification(entry) for entry in entries]

    def _send_acks(self, acks: list[tuple[str, int]]) -> None:
        for epoch, seq in acks:
            with contextlib.suppress(zenoh.ZError):
                self._ack_publisher.put(encode_ack(epoch, seq))

    def _flush_loop(self) -> None:
        """Send a delayed ack when it falls due and nobody took since (see ``AckPolicy``)."""
        ledger = self._ledger
        while not self._closed:
            self._flush_wake.wait(_REACK_S)
            self._flush_wake.clear()
            while not self._closed:
                with self._lock:
                    due_at = ledger.flush_at_ns()
                    now = time.monotonic_ns()
                    acks = (
                        ledger.acks_due(now, idle=False)
                        if due_at is not None and due_at <= now
                        else []
                    )
                    if due_at is None:
                        self._flush_armed = False
                        break
                self._send_acks(acks)
                if due_at > now:
                    self._flush_wake.wait((due_at - now) / 1e9)
                    self._flush_wake.clear()

    def _notification(self, entry: Entry[_Item]) -> Notification:
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
        """The element a notification names (inline if it came along, else one query)."""
        if notification.element is not None:
            return notification.element
        return self._fetch(self.name, notification.timestamp_ns, timeout_s)

    def close(self) -> None:
        """Withdraw: the producer stops counting this subscription at once."""
        if self._closed:
            return
        self._closed = True
        with self._lock:
            self._cond.notify_all()
        self._flush_wake.set()
        if self._flusher is not None:
            self._flusher.join(timeout=2.0)
        for entity in (self._token, self._subscriber, self._ack_publisher):
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()
        if self._on_close is not None:
            self._on_close(self)

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *_exc: Any) -> None:
        self.close()


def _batch_items(head: BatchHeader, payload: zenoh.ZBytes) -> list[_Item]:
    """The elements of a decoded batch notification, payloads cut out when pushed."""
    times, metas, sizes = head.timestamps_ns, head.metadata, head.payload_sizes
    if sizes is None:
        return [(t, m, None) for t, m in zip(times, metas, strict=True)]
    raw = payload.to_bytes()
    if sum(sizes) != len(raw):
        raise ValueError("batch payload sizes do not add up to the payload")
    items: list[_Item] = []
    offset = 0
    for t, m, size in zip(times, metas, sizes, strict=True):
        items.append((t, m, raw[offset : offset + size] if m is not None else None))
        offset += size
    return items
