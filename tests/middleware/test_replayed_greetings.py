"""Replays of a producer's old greetings to a live subscription, driven through the sans-IO
protocol objects: a peer that captured the ``hello`` of earlier registrations (on the
subscription's notify key, readable in the default profile) sends them again from its own
session."""

from __future__ import annotations

from middleware._protocol_events import Publish
from middleware._protocol_producer import ProducerProtocol
from middleware._protocol_subscriber import SubscriberProtocol
from middleware._records import DataObject, SubscriptionMode
from middleware._wire import Control, Keys, decode_notification_header, encode_notification_header

KEYS = Keys("framegate")
FLOW = SubscriptionMode.FLOW
PRODUCER, ROGUE = "producer-session", "rogue-session"


def test_replayed_old_greetings_cannot_make_a_subscription_forget_its_live_epoch() -> None:
    """Two old greetings of the live producer replayed in turn, each followed by 32 made-up
    epochs at seq 1: each replay moved the subscription's pin (the live epoch, never
    evicted) to an old epoch and opened room for 32 more made-up ones, and after 12 rounds
    the live epoch was gone from the subscription's memory: every resend of it was ignored
    (out of order) and the producer was held for good once its queue filled. A greeting of
    an earlier registration of the instance that greeted it last is garbage now."""
    producer = ProducerProtocol(KEYS, "svc", "buf", "P0", inline_max_bytes=4)
    sub = SubscriberProtocol(FLOW, 4, -1)
    token = KEYS.subscription_token("svc", "buf", "s1", FLOW, 4, -1, "n~h")
    hellos: list[bytes] = []
    stamp = iter(range(1, 1000))

    def deliver() -> None:
        for ev in producer.events():
            if isinstance(ev, Publish):
                head = decode_notification_header(ev.attachment)
                if isinstance(head, Control) and head.kind == "hello":
                    hellos.append(ev.attachment)
                sub.receive(ev.attachment, ev.payload, PRODUCER)

    def put_and_take() -> int:
        producer.put_many((DataObject(next(stamp), b"", b"m"),), 0)
        deliver()
        taken = sub.take_many(10)
        for ack in sub.acks(0, idle=True):
            producer.ack(KEYS.ack("svc", "buf", "s1"), ack, 0)
        return len(taken)

    for lapse in (True, True, False):  # three registrations: the token lapsed twice
        producer.token(token, True, 0)
        deliver()
        assert put_and_take() == 1
        live = producer.registrations()[0].epoch
        if lapse:
            producer.token(token, False, 0)
    garbage = sub.garbage
    made_up = 0
    for round_ in range(12):
        sub.receive(hellos[round_ % 2], b"", ROGUE)
        for _ in range(32):
            made_up += 1
            forged = encode_notification_header(
                f"X{made_up}.1", 1, 10**6 + made_up, b"m", pushed=False, descriptor=sub.descriptor
            )
            sub.receive(forged, b"")
        sub.take_many(100)
        sub.acks(0, idle=True)
    for _ in range(6):  # more than the queue: the producer would be held if they were lost
        assert put_and_take() == 1
    assert producer.admit(1, may_wait=False) is None
    assert sub.garbage == garbage + 12
    assert sub.registered_epoch == live
