"""The subscriber's side of the protocol as one sans-IO object: notification bytes and the
time go in, queued notifications and wire-ready acks come out.

``SubscriberProtocol`` owns every decision a subscription makes: its descriptor (the one
place it is built), the limits on what it may ask for (checked before any token is
declared, so ``subscribe`` refuses at once), decoding and judging each notification
(the pure ``SubscriberLedger`` keeps the rules), the producer's greeting or refusal, and
when acks leave (coalesced, delayed, repeated while idle). ``next_deadline_ns`` tells the
node's executor when a delayed ack falls due for a caller that does not come back to take.
"""

from __future__ import annotations

from collections.abc import Container
from typing import Any

from ._errors import ConfigError
from ._ledger_subscriber import AckPolicy, Entry, SubscriberCounters, SubscriberLedger
from ._protocol_producer import INLINE_METADATA_MAX, QUEUE_BUDGET
from ._records import SubscriptionMode
from ._wire import (
    MAX_QUEUE_SIZE,
    BatchHeader,
    Control,
    Header,
    decode_notification_header,
    descriptor_of,
    encode_ack,
)

# What the queue holds per notification: timestamp_ns, metadata, the pushed payload (Zenoh's
# ZBytes for a single element, turned into bytes by ``take`` on the caller's thread; bytes
# cut out of a batch).
Item = tuple[int, bytes | None, Any]
# Room for a notification header's fields besides its metadata (epoch, seq, descriptor, ...).
_HEADER_SLACK = 1024


def check_request(mode: SubscriptionMode, queue_size: int, push_max_bytes: int) -> None:
    """Refuse what no producer would register, with the limit named."""
    if type(queue_size) is not int or queue_size < 1:
        raise ConfigError(f"queue_size must be an integer >= 1, got {queue_size!r}")
    limit = QUEUE_BUDGET if mode is SubscriptionMode.FLOW else MAX_QUEUE_SIZE
    if queue_size > limit:
        raise ConfigError(
            f"queue_size {queue_size} exceeds the {mode.value} limit of {limit} (a producer "
            "keeps every un-acked notification of a flow-controlled subscriber); "
            "choose a smaller queue"
        )
    if push_max_bytes < -1:
        raise ConfigError(f"push_max_bytes must be >= 0, got {push_max_bytes}")


class SubscriberProtocol:
    """One subscription's protocol. Not thread-safe: the caller serialises every call."""

    def __init__(
        self,
        mode: SubscriptionMode,
        queue_size: int,
        push_max_bytes: int,
        *,
        policy: AckPolicy | None = None,
    ) -> None:
        check_request(mode, queue_size, push_max_bytes)
        self.mode = mode
        self.queue_size = queue_size
        self.push_max_bytes = push_max_bytes
        self.descriptor = descriptor_of(mode, queue_size, push_max_bytes)
        self.ledger: SubscriberLedger[Item] = SubscriberLedger(
            mode, queue_size, self.descriptor, policy=policy or AckPolicy.for_queue(queue_size)
        )
        self.garbage = 0
        # The producer's answer to our token: its registration's epoch, or why it refused.
        self.registered: str | None = None
        self.refusal: str | None = None
        self.registrations = 0  # greetings under distinct epochs
        # Fetch ahead: set once the consumer had to query for an element (see ``fetch_ahead``).
        self.fetching = False

    # -- input -----------------------------------------------------------------------------
    def receive(self, attachment: bytes | None, payload: Any) -> bool:
        """One notification (or control message) as it arrived; True if something was
        queued. ``payload`` is the Zenoh payload (anything with ``to_bytes()``, or bytes)."""
        try:
            if attachment is None:
                raise ValueError("notification without a header")
            head = decode_notification_header(attachment)
            if type(head) is Header:
                metadata = head.metadata
                pushed = payload if head.pushed and metadata is not None else None
                return self.ledger.receive(
                    head.epoch,
                    head.seq,
                    (head.timestamp_ns, metadata, pushed),
                    descriptor=head.descriptor,
                )
            if type(head) is BatchHeader:
                items = _batch_items(head, payload)
                return (
                    self.ledger.receive_many(
                        head.epoch, head.seq, items, descriptor=head.descriptor
                    )
                    > 0
                )
            assert type(head) is Control
            self._control(head)
            return False
        except Exception:  # garbage on our key is counted, never raised
            self.garbage += 1
            return False

    def _control(self, control: Control) -> None:
        if control.descriptor != self.descriptor:
            return  # meant for another registration of this key: not ours to judge
        if control.kind == "hello":
            if self.registered is not None and self.registered != control.text:
                self.registrations += 1  # a producer restart, or our token had lapsed
            elif self.registered is None:
                self.registrations = 1
            self.registered = control.text
            self.refusal = None
        elif self.registered is None:
            self.refusal = control.text
        # else: a refusal after a greeting, a forgery or an old message: the greeting stands

    # -- taking and acking -----------------------------------------------------------------
    def take_many(self, max_count: int) -> list[Entry[Item]]:
        """Up to ``max_count`` queued notifications, oldest first (they leave the queue)."""
        entries: list[Entry[Item]] = []
        ledger = self.ledger
        while len(entries) < max_count and (entry := ledger.take()) is not None:
            entries.append(entry)
        return entries

    def acks(self, now_ns: int, *, idle: bool) -> list[bytes]:
        """The acks to send now, wire-ready (see ``SubscriberLedger.acks_due``)."""
        return [encode_ack(epoch, seq) for epoch, seq in self.ledger.acks_due(now_ns, idle=idle)]

    def next_deadline_ns(self) -> int | None:
        """When a delayed ack falls due with nobody taking (None: none waits)."""
        return self.ledger.flush_at_ns()

    def fetch_ahead(self, taken_missing: list[int], inflight: Container[int]) -> list[int]:
        """The stamps whose queries to start now, once ``fetching``: the taken notifications
        that came without their element (``taken_missing``) and every queued one, oldest
        first, less those in flight, at most a queue's worth."""
        queued = [e.item[0] for e in self.ledger.queued() if e.item[2] is None]
        wanted = [t for t in taken_missing + queued if t not in inflight]
        return wanted[: self.queue_size]

    def max_message_bytes(self) -> int:
        """The largest message (payload and header) an honest producer sends this
        subscription; a larger one is garbage, dropped before it is buffered. Unbounded
        while the push limit is the producer's (``push_max_bytes`` -1), and for observers
        (a batch of any length may reach them)."""
        if self.push_max_bytes < 0 or self.mode is not SubscriptionMode.FLOW:
            return 1 << 62
        per_element = self.push_max_bytes + INLINE_METADATA_MAX + _HEADER_SLACK
        return self.queue_size * per_element + _HEADER_SLACK

    # -- reading ---------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.ledger)

    @property
    def missed_total(self) -> int:
        return self.ledger.missed_total

    def counters(self) -> SubscriberCounters:
        c = self.ledger.counters
        return SubscriberCounters(c.foreign, c.invalid, c.out_of_order, c.duplicates, c.refused)


def _batch_items(head: BatchHeader, payload: Any) -> list[Item]:
    """The elements of a decoded batch notification, payloads cut out when pushed."""
    times, metas, sizes = head.timestamps_ns, head.metadata, head.payload_sizes
    if sizes is None:
        return [(t, m, None) for t, m in zip(times, metas, strict=True)]
    raw = payload if type(payload) is bytes else payload.to_bytes()
    if sum(sizes) != len(raw):
        raise ValueError("batch payload sizes do not add up to the payload")
    items: list[Item] = []
    offset = 0
    for t, m, size in zip(times, metas, sizes, strict=True):
        items.append((t, m, raw[offset : offset + size] if m is not None else None))
        offset += size
    return items
