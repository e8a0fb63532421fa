"""The client side of a subscription: a bounded notification queue with flow-control acks.

The queue lives here, in the subscriber's process; the producer mirrors its fill from the
acknowledgements (queued = sent - taken). A notification leaves the queue when ``take``
returns it; processing the element afterwards does not count against the queue.
"""

from __future__ import annotations

import contextlib
import secrets
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from typing import Any

import zenoh

from ._errors import FramegateError
from ._records import DataObject, Notification, SubscriptionMode
from ._wire import Keys, decode_notification_header, encode_ack

# A push limit larger than any payload: everything travels with its notification.
PUSH_ALL = 2**31 - 1
# An idle subscriber repeats its last ack this often, so a lost final ack heals.
_REACK_S = 0.5


class Subscription:
    """Availability notifications of one buffer. Create with ``Node.subscribe``.

    Survives restarts of the producing service: a new producer epoch resets the counters,
    and the producer re-registers this subscription from its liveliness token.
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
        self._cond = threading.Condition()
        self._queue: deque[tuple[str, Notification]] = deque()
        self._epoch: str | None = None
        self._last_seq = 0
        self._missed_unreported = 0
        self._last_ack: tuple[str, int] | None = None
        self._reacked_at = 0.0
        self.missed_total = 0
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
        # Declared last: once the producer sees it, notifications may flow.
        self._token = session.liveliness().declare_token(
            keys.subscription_token(
                service, buffer, self.subscription_id, mode, queue_size, push_max_bytes
            )
        )

    @property
    def name(self) -> str:
        return f"{self.service}/{self.buffer}"

    def _on_notification(self, sample: zenoh.Sample) -> None:
        try:
            attachment = sample.attachment
            if attachment is None:
                raise ValueError("notification without a header")
            body = decode_notification_header(attachment.to_bytes())
        except Exception:  # garbage on our key is counted, never raised into Zenoh
            self.garbage += 1
            return
        epoch, seq, timestamp = body["e"], body["s"], body["t"]
        metadata = body.get("m")
        element = (
            DataObject(timestamp, sample.payload.to_bytes(), metadata)
            if body["p"] and metadata is not None
            else None
        )
        with self._cond:
            if epoch != self._epoch:
                # The producer restarted: its old notifications name elements that are gone.
                self._queue.clear()
                self._epoch = epoch
                self._last_seq = 0
            if seq <= self._last_seq:
                return  # duplicate or stale
            gap = seq - self._last_seq - 1
            self._last_seq = seq
            self._missed_unreported += gap
            self.missed_total += gap
            if self.mode is SubscriptionMode.OBSERVE and len(self._queue) >= self.queue_size:
                self._missed_unreported += 1
                self.missed_total += 1
                return
            # Misses are reported on the first notification that made it after them.
            note = Notification(
                self.service,
                self.buffer,
                timestamp,
                seq,
                metadata=metadata,
                element=element,
                missed=self._missed_unreported,
            )
            self._missed_unreported = 0
            self._queue.append((epoch, note))
            self._cond.notify_all()

    @property
    def pending(self) -> int:
        """Notifications waiting in this process's queue."""
        with self._cond:
            return len(self._queue)

    def take(self, timeout_s: float | None = None) -> Notification | None:
        """Take the oldest notification (it leaves the queue now); None on timeout."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._cond:
            while not self._queue:
                if self._closed:
                    return None
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    self._reack()
                    return None
                if not self._cond.wait(min(remaining, _REACK_S) if remaining else _REACK_S):
                    self._reack()
            epoch, note = self._queue.popleft()
            self._last_ack = (epoch, note.seq)
        # A lost ack heals itself: the next one is cumulative, and an idle subscriber
        # repeats its last one (``_reack``) so the producer's count cannot stay high.
        with contextlib.suppress(zenoh.ZError):
            self._ack_publisher.put(encode_ack(epoch, note.seq))
        return note

    def _reack(self) -> None:
        """Repeat the last ack while waiting idle (at most every ``_REACK_S``)."""
        now = time.monotonic()
        if self._last_ack is None or now - self._reacked_at < _REACK_S:
            return
        self._reacked_at = now
        with contextlib.suppress(zenoh.ZError):
            self._ack_publisher.put(encode_ack(*self._last_ack))

    def __iter__(self) -> Iterator[Notification]:
        """Notifications until the subscription is closed."""
        while not self._closed:
            note = self.take(timeout_s=0.5)
            if note is not None:
                yield note

    def fetch(self, notification: Notification, timeout_s: float = 5.0) -> DataObject:
        """The element a notification names (inline if it came along, else one query)."""
        if notification.element is not None:
            return notification.element
        return self._fetch(self.name, notification.timestamp_ns, timeout_s)

    def close(self) -> None:
        """Withdraw: the producer stops counting this subscription at once."""
        if self._closed:
            return
        self._closed = True
        with self._cond:
            self._cond.notify_all()
        for entity in (self._token, self._subscriber, self._ack_publisher):
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *_exc: Any) -> None:
        self.close()
