"""A lapsed registration's elements are counted when the producer greets the next one, not
only when a later element arrives: a lapse at the end of a stream is counted too."""

from __future__ import annotations

from middleware._protocol_events import Publish
from middleware._protocol_producer import ProducerProtocol
from middleware._protocol_subscriber import SubscriberProtocol
from middleware._records import DataObject, SubscriptionMode
from middleware._wire import (
    Control,
    Keys,
    decode_notification_header,
    encode_notification_header,
)

KEYS = Keys("framegate")
SERVICE, BUFFER, SUB = "svc", "buf", "s1"


class _Pair:
    """A producer and one flow-controlled subscriber, the network a list in between."""

    def __init__(self, mode: SubscriptionMode = SubscriptionMode.FLOW, queue: int = 4) -> None:
        self.producer = ProducerProtocol(KEYS, SERVICE, BUFFER, "P0", inline_max_bytes=4)
        self.sub = SubscriberProtocol(mode, queue, -1)
        self.token = KEYS.subscription_token(SERVICE, BUFFER, SUB, mode, queue, -1, "n~h")
        self.now = 0
        self.next_t = 1
        self.kinds: list[str] = []

    def declare(self, alive: bool) -> None:
        self.producer.token(self.token, alive, self.now)
        self.deliver()

    def put(self, n: int) -> None:
        for _ in range(n):
            self.producer.put_many((DataObject(self.next_t, b"", b"m"),), self.now)
            self.next_t += 1
        self.deliver()

    def deliver(self) -> None:
        for ev in self.producer.events():
            if isinstance(ev, Publish):
                head = decode_notification_header(ev.attachment)
                self.kinds.append(head.kind if isinstance(head, Control) else "data")
                self.sub.receive(ev.attachment, ev.payload)

    def take_all(self) -> list[int]:
        entries = self.sub.take_many(100)
        for ack in self.sub.acks(self.now, idle=True):
            self.producer.ack(KEYS.ack(SERVICE, BUFFER, SUB), ack, self.now)
        self.deliver()
        return [e.missed for e in entries]


def test_a_lapse_at_the_end_of_a_stream_is_counted_at_the_next_greeting() -> None:
    pair = _Pair()
    pair.declare(True)
    pair.put(2)
    assert pair.take_all() == [0, 0]
    pair.declare(False)  # the token lapsed (a link that dropped) ...
    pair.put(3)  # ... while three elements were stored
    pair.kinds.clear()
    pair.declare(True)  # ... and came back: the producer greets the new registration
    assert pair.kinds == ["hello"]
    assert pair.sub.ledger.missed_total == 3  # counted now, with no element after the lapse
    assert pair.sub.lapse_news() == 3
    pair.put(1)
    # The next notification carries the count, and it is not counted twice.
    assert pair.take_all() == [3]
    assert pair.sub.ledger.missed_total == 3
    assert pair.sub.lapse_news() == 0


def test_a_repeated_greeting_and_a_lapse_with_nothing_stored_count_nothing() -> None:
    pair = _Pair()
    pair.declare(True)
    pair.put(2)
    pair.take_all()
    pair.declare(False)
    pair.declare(True)  # nothing stored meanwhile
    pair.put(2)
    assert pair.take_all() == [0, 0]
    assert pair.sub.ledger.missed_total == 0
    assert pair.sub.lapse_news() == 0


def test_a_lapse_is_counted_when_nothing_of_the_registration_came_through() -> None:
    # Found by the protocol model: the greeting lost and every notification refused (a
    # peer's made-up ones filled the queue), then the token lapsed. The subscriber knew no
    # element number of the producer, so the two elements before the lapse went uncounted.
    pair = _Pair()
    pair.producer.token(pair.token, True, pair.now)
    pair.producer.events()  # the greeting is lost
    for i in range(4):  # a peer's notifications fill the queue of 4
        forged = encode_notification_header(
            f"F{i}.1", 1, 0, b"m", pushed=True, acked=None, descriptor=pair.sub.descriptor
        )
        assert pair.sub.receive(forged, b"")
    pair.put(2)  # ignored: the queue is full (the first refused, the next out of order)
    counters = pair.sub.ledger.counters
    assert len(pair.sub) == 4 and counters.refused + counters.out_of_order == 2
    pair.producer.token(pair.token, False, pair.now)  # the lapse
    pair.producer.events()
    pair.kinds.clear()
    pair.declare(True)
    assert pair.kinds == ["hello"]
    assert pair.sub.ledger.missed_total == 2  # from the greeting's ``since``: acked 0 of 2


def test_an_element_of_the_lapsed_registration_that_arrives_late_is_not_taken_too() -> None:
    """A notification sent just before the token lapsed that arrives after the greeting of
    the new registration (held back, or replayed by a peer that captured it): the greeting
    counted it as missed, and it was taken as well (3 missed for 2 lost, and element 3
    taken after the count). Its registration is retired: it is ignored, counted."""
    pair = _Pair()
    pair.declare(True)
    pair.put(2)
    assert pair.take_all() == [0, 0]
    pair.producer.put_many((DataObject(pair.next_t, b"", b"m"),), pair.now)  # element 3 ...
    pair.next_t += 1
    late = [ev for ev in pair.producer.events() if isinstance(ev, Publish)]  # ... held back
    pair.declare(False)  # the token lapsed
    pair.put(2)  # elements 4 and 5, never notified to it
    pair.declare(True)  # the greeting counts 3: nothing past element 2 was queued
    duplicates = pair.sub.counters().duplicates
    for ev in late:
        assert not pair.sub.receive(ev.attachment, ev.payload)  # element 3 comes after all
    assert pair.sub.counters().duplicates == duplicates + 1
    pair.put(1)
    entries = pair.sub.take_many(100)
    assert [(e.item[0], e.missed) for e in entries] == [(6, 3)]
    assert pair.sub.ledger.missed_total == 3


def test_a_full_observer_carries_a_lapse_on_the_element_that_pushed_out_its_oldest() -> None:
    """An observer of queue 1 still holding an element when its token lapsed: the first
    element of the new registration pushes that one out, and the lapse's count was to go on
    the new element at the index the queue had before the push (past its end). The
    notification was queued but counted as garbage, the new element carried neither count,
    and the next lapse, with nothing stored during it, counted one element more."""
    pair = _Pair(SubscriptionMode.OBSERVE, 1)
    pair.declare(True)
    pair.put(1)  # element 1 waits, not taken
    pair.declare(False)
    pair.put(1)  # element 2, stored during the lapse
    pair.declare(True)
    pair.put(1)  # element 3 pushes element 1 out
    assert pair.sub.garbage == 0
    # It carries the lapse (element 2); element 1's push-out stays with its registration's
    # epoch (``SubscriberLedger._drop_oldest``), counted in the total.
    assert pair.take_all() == [1]
    assert pair.sub.ledger.missed_total == 2
    pair.declare(False)
    pair.declare(True)  # a lapse with nothing stored during it
    assert pair.sub.ledger.missed_total == 2
