"""The two flow-control ledgers driven directly, for the behaviours the model test checks
only in aggregate: how many acks a run of takes costs, and batches of elements."""

from __future__ import annotations

from middleware._ledger_producer import ProducerLedger, RegistrationKey
from middleware._ledger_subscriber import AckPolicy, SubscriberLedger
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
        for send in producer.put(t, 0):
            assert subscriber.receive(send.epoch, send.seq, send.header, descriptor=None)


def _take_counting_acks(subscriber: SubscriberLedger[int], count: int) -> list[tuple[str, int]]:
    acks: list[tuple[str, int]] = []
    for _ in range(count):
        assert subscriber.take() is not None
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


def test_coalesced_acks_leave_as_soon_as_the_queue_runs_empty() -> None:
    producer, subscriber, _ = _pair(8)
    _fill(producer, subscriber, 3)
    acks = _take_counting_acks(subscriber, 3)
    assert [seq for _, seq in acks] == [3], "a consumer that keeps up must not hold credit"


def test_a_waiting_subscriber_sends_the_coalesced_ack() -> None:
    producer, subscriber, _ = _pair(8)
    _fill(producer, subscriber, 6)
    assert _take_counting_acks(subscriber, 5) == [(producer.registrations()[0].epoch, 4)]
    assert [seq for _, seq in subscriber.acks_due(0, idle=True)] == [5]
