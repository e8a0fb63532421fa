"""The two flow-control ledgers driven directly, for the behaviours the model test checks
only in aggregate: how many acks a run of takes costs, and batches of elements."""

from __future__ import annotations

from middleware._ledger_producer import ProducerLedger, RegistrationKey
from middleware._ledger_subscriber import (
    ACK_DELAY_NS,
    DEEP_ACK_DELAY_NS,
    DEEP_QUEUE,
    AckPolicy,
    SubscriberLedger,
)
from middleware._records import SubscriptionMode

FLOW = SubscriptionMode.FLOW


def _pair(queue_size: int) -> tuple[ProducerLedger[int], SubscriberLedger[int], RegistrationKey]:
    key = RegistrationKey("s", FLOW, queue_size, -1)
    producer: ProducerLedger[int] = ProducerLedger("P")
    producer.token_put(key, 0)
    subscriber: SubscriberLedger[int] = SubscriberLedger(
        FLOW, queue_size, key.descriptor, policy=AckPolicy.for_queue(queue_size)
    )
    return producer, subscriber, key


def _fill(producer: ProducerLedger[int], subscriber: SubscriberLedger[int], count: int) -> None:
    for t in range(count):
        for send in producer.put_many((t,), 0):
            assert subscriber.receive(send.epoch, send.seq, send.headers[0], descriptor=None)


def _take_counting_acks(subscriber: SubscriberLedger[int], count: int) -> list[tuple[str, int]]:
    acks: list[tuple[str, int]] = []
    for _ in range(count):
        assert subscriber.take_many(1)
        acks += subscriber.acks_due(0, idle=False)
    return acks


def test_a_queue_of_eight_sends_one_ack_per_half_queue_taken() -> None:
    producer, subscriber, _ = _pair(8)
    _fill(producer, subscriber, 8)
    acks = _take_counting_acks(subscriber, 8)
    assert [seq for _, seq in acks] == [4, 8]
    for epoch, seq in acks:
        producer.ack("s", epoch, seq, 0)
    assert producer.full() is None and producer.registrations()[0].queued == 0


def test_a_queue_of_one_acks_every_take() -> None:
    producer, subscriber, _ = _pair(1)
    for t in range(3):
        _fill(producer, subscriber, 1)
        assert producer.full() is not None
        [(epoch, seq)] = _take_counting_acks(subscriber, 1)
        assert seq == t + 1
        producer.ack("s", epoch, seq, 0)
        assert producer.full() is None


def test_an_ack_beyond_what_was_sent_frees_nothing() -> None:
    """A peer reads a registration's id and epoch off the wire and acks seq 2^62: taken as
    ``sent``, it acked what the subscriber still held, the producer sent past the
    subscriber's window, and neither side moved again (measured: a queue of 2 held for
    good). It is counted and changes nothing; the subscriber's own acks still work."""
    producer, subscriber, _ = _pair(2)
    _fill(producer, subscriber, 2)
    epoch = producer.registrations()[0].epoch
    for lie in (3, 2**62):
        assert not producer.ack("s", epoch, lie, 0)
    assert producer.full() is not None and producer.counters.foreign_acks == 2
    epoch, seq = _take_counting_acks(subscriber, 2)[-1]
    assert producer.ack("s", epoch, seq, 0) and producer.full() is None


def test_coalesced_acks_leave_within_the_delay_once_the_queue_runs_empty() -> None:
    producer, subscriber, _ = _pair(8)
    _fill(producer, subscriber, 3)
    assert _take_counting_acks(subscriber, 3) == [], "held back for the next few takes"
    due = subscriber.flush_at_ns()
    assert due == ACK_DELAY_NS, "a consumer that keeps up must not hold credit for long"
    assert subscriber.acks_due(due - 1, idle=False) == []
    assert [seq for _, seq in subscriber.acks_due(due, idle=False)] == [3]
    assert subscriber.flush_at_ns() is None


def test_a_slow_stream_acks_each_take_at_once_without_a_timer() -> None:
    """One element every 10 ms at a queue of 8: no later take could join its ack within the
    delay, so the emptied queue acks at once (no flush timer per element)."""
    producer, subscriber, _ = _pair(8)
    for t in range(1, 6):
        now = t * 10 * ACK_DELAY_NS
        _fill(producer, subscriber, 1)
        assert subscriber.take_many(1)
        assert [seq for _, seq in subscriber.acks_due(now, idle=False)] == [t]
        assert subscriber.flush_at_ns() is None


def test_a_deep_queue_shares_one_ack_among_the_takes_of_its_delay() -> None:
    """The mediator's gyro: batches 10 ms apart into a queue of 256. Acking each at once
    would cost a Zenoh wake-up per batch on both sides; the deep queue's delay lets the
    takes of 20 ms share one ack, and the producer's credit is never held longer."""
    producer, subscriber, _ = _pair(256)
    step = 10_000_000
    acks: list[int] = []
    for t in range(10):
        _fill(producer, subscriber, 10)
        for _ in range(10):
            assert subscriber.take_many(1)
        acks += [seq for _, seq in subscriber.acks_due(t * step, idle=False)]
        due = subscriber.flush_at_ns()
        assert due is None or due - t * step <= DEEP_ACK_DELAY_NS
    assert acks[0] == 10, "the first take of a stream is acked at once"
    assert 1 < len(acks) <= 5, acks
    assert acks == sorted(acks)
    _fill(producer, subscriber, 10)  # one more batch, and then nothing
    assert len(subscriber.take_many(10)) == 10
    assert subscriber.acks_due(10 * step, idle=False) == []
    flush = subscriber.flush_at_ns()
    assert flush is not None and flush - 10 * step <= DEEP_ACK_DELAY_NS
    acks += [seq for _, seq in subscriber.acks_due(flush, idle=False)]
    assert acks[-1] == 110, "the last takes leave within the delay"
    producer.ack("s", producer.registrations()[0].epoch, acks[-1], 0)
    assert producer.registrations()[0].queued == 0


def test_only_a_deep_queue_waits_longer_than_the_short_delay() -> None:
    assert AckPolicy.for_queue(DEEP_QUEUE - 1).delay_ns == ACK_DELAY_NS
    assert AckPolicy.for_queue(DEEP_QUEUE).delay_ns == DEEP_ACK_DELAY_NS
    assert AckPolicy.for_queue(2) == AckPolicy(), "a load signal's queue acks every take"


def test_a_fast_stream_still_coalesces_its_acks() -> None:
    producer, subscriber, _ = _pair(8)
    _fill(producer, subscriber, 1)
    assert subscriber.take_many(1)
    subscriber.acks_due(0, idle=False)  # the first take of the stream
    for t in range(1, 3):  # then one every tenth of the delay: coalesced
        _fill(producer, subscriber, 1)
        assert subscriber.take_many(1)
        assert subscriber.acks_due(t * ACK_DELAY_NS // 10, idle=False) == []
    assert subscriber.flush_at_ns() is not None


def test_a_delayed_ack_waits_for_nothing_while_frames_are_queued() -> None:
    producer, subscriber, _ = _pair(8)
    _fill(producer, subscriber, 3)
    assert _take_counting_acks(subscriber, 1) == []
    assert subscriber.flush_at_ns() is None  # the caller comes back for the two queued
    assert subscriber.acks_due(10 * ACK_DELAY_NS, idle=False) == []


def test_a_waiting_subscriber_sends_the_coalesced_ack() -> None:
    producer, subscriber, _ = _pair(8)
    _fill(producer, subscriber, 6)
    assert _take_counting_acks(subscriber, 5) == [(producer.registrations()[0].epoch, 4)]
    assert [seq for _, seq in subscriber.acks_due(ACK_DELAY_NS, idle=True)] == [5]


def test_a_batch_is_refused_whole_when_the_queue_lacks_room_for_all_its_elements() -> None:
    producer, subscriber, _ = _pair(4)
    _fill(producer, subscriber, 3)
    assert producer.full(2) is not None, "3 queued + 2 > 4"
    assert producer.full(1) is None
    [send] = producer.put_many((10,), 0)
    assert (send.seq, len(send.headers)) == (4, 1)


def test_a_batch_is_one_send_that_the_subscriber_queues_as_its_elements() -> None:
    producer, subscriber, _ = _pair(8)
    _fill(producer, subscriber, 2)
    [send] = producer.put_many((10, 11, 12), 0)
    assert (send.seq, send.headers) == (3, (10, 11, 12))
    assert subscriber.receive_many(send.epoch, send.seq, list(send.headers), descriptor=None) == 3
    assert producer.registrations()[0].queued == 5
    taken = subscriber.take_many(5)
    assert [(e.seq, e.item) for e in taken] == [(1, 0), (2, 1), (3, 10), (4, 11), (5, 12)]
    assert subscriber.acks_due(0, idle=False) == [(send.epoch, 5)], "one cumulative ack"


def test_a_lost_batch_is_resent_element_by_element() -> None:
    producer, subscriber, _ = _pair(4)
    producer.put_many((10, 11, 12), 0)  # lost on the way
    resent = producer.tick(10**9)
    assert [(s.seq, s.headers, s.again) for s in resent] == [
        (1, (10,), True),
        (2, (11,), True),
        (3, (12,), True),
    ]
    for send in resent:
        assert subscriber.receive(send.epoch, send.seq, send.headers[0], descriptor=None)
    assert [e.item for e in subscriber.take_many(3)] == [10, 11, 12]


def test_the_producer_dates_the_last_take_by_the_ack_that_freed_credit() -> None:
    producer, subscriber, _key = _pair(2)
    _fill(producer, subscriber, 2)
    [reg] = producer.registrations()
    assert reg.taken_ns is None
    assert subscriber.take_many(1)
    [(epoch, seq)] = subscriber.acks_due(0, idle=False)
    assert producer.ack("s", epoch, seq, 70)
    assert not producer.ack("s", epoch, seq, 90)  # a repeat moves nothing: not a take
    assert not producer.ack("s", "forged", seq + 1, 95)
    assert (reg.queued, reg.taken_ns) == (1, 70)


def _observer(queue_size: int) -> SubscriberLedger[int]:
    descriptor = RegistrationKey("o", SubscriptionMode.OBSERVE, queue_size, -1).descriptor
    return SubscriberLedger(SubscriptionMode.OBSERVE, queue_size, descriptor)


def test_a_full_observer_keeps_the_newest_and_counts_the_oldest_missed() -> None:
    """Keep-last: the last element of a burst is queued (not lost until another comes), and
    every element pushed out is counted on the notification then first."""
    observer = _observer(2)
    for seq in range(1, 11):
        assert observer.receive("E", seq, seq, descriptor=None)
    taken = observer.take_many(10)
    assert [(e.seq, e.missed) for e in taken] == [(9, 8), (10, 0)]
    assert observer.missed_total == 8


def test_an_observer_keeps_missed_counts_with_their_producer_instance() -> None:
    """An element of one epoch pushed out by another epoch's is counted on its own epoch's
    next notification, never on another producer's."""
    observer = _observer(1)
    assert observer.receive("A", 1, 1, descriptor=None)
    assert observer.receive("B", 1, 1, descriptor=None)  # pushes A's out
    assert [(e.epoch, e.missed) for e in observer.take_many(1)] == [("B", 0)]
    assert observer.receive("A", 2, 2, descriptor=None)
    assert [(e.epoch, e.seq, e.missed) for e in observer.take_many(1)] == [("A", 2, 1)]
    assert observer.missed_total == 1


def test_an_ack_below_seq_one_is_counted_and_never_reaches_the_inbox() -> None:
    """No subscriber acks seq 0 or a negative seq (seqs start at 1 and acks are of taken
    ones): a peer that read a registration's epoch sent them, distinct each, and every one
    passed ``plausible`` (so the ack inbox kept them, up to its 8,192, beside the honest
    acks) and was then ignored uncounted. They are foreign acks now, counted, and the
    subscriber's own acks still work."""
    producer, subscriber, _ = _pair(2)
    _fill(producer, subscriber, 2)
    epoch = producer.registrations()[0].epoch
    for lie in (0, -1, -(2**62)):
        assert not producer.plausible("s", epoch, lie)
        assert not producer.ack("s", epoch, lie, 0)
    assert producer.counters.foreign_acks == 3
    assert producer.registrations()[0].resend_now is False  # nor made anything due again
    epoch, seq = _take_counting_acks(subscriber, 2)[-1]
    assert producer.ack("s", epoch, seq, 0) and producer.full() is None
