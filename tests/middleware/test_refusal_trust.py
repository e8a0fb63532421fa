"""Whose ``refused`` a subscription believes (``SubscriberProtocol.judge``): only the one
session that answers as the service. Pure: no Zenoh, no threads, no clock."""

from __future__ import annotations

import pytest

from middleware._protocol_subscriber import SubscriberProtocol
from middleware._records import SubscriptionMode
from middleware._wire import encode_control, encode_notification_header

PRODUCER, ROGUE = "a1", "b2"


def _refused_by(sender: str) -> SubscriberProtocol:
    sub = SubscriberProtocol(SubscriptionMode.FLOW, 4, -1)
    refusal = encode_control("refused", sub.descriptor, "queue budget used up")
    sub.receive(refusal, b"", sender=sender)
    assert sub.judge(0) is True  # the producer's sessions must be asked first
    return sub


@pytest.mark.parametrize(
    ("sender", "answering", "believed"),
    [
        (PRODUCER, {PRODUCER}, True),  # the producer itself
        (ROGUE, {PRODUCER}, False),  # a forgery
        (ROGUE, {PRODUCER, ROGUE}, False),  # a rogue that also answers as the service
        (PRODUCER, {PRODUCER, ROGUE}, False),  # two answer: nobody can tell, nobody is trusted
        (ROGUE, set(), False),  # nobody answers as the service
    ],
)
def test_a_refusal_counts_only_from_the_one_session_answering_as_the_service(
    sender: str, answering: set[str], believed: bool
) -> None:
    sub = _refused_by(sender)
    sub.trust_producer(frozenset(answering), 0)
    assert (sub.refusal == "queue budget used up") is believed


@pytest.mark.parametrize(
    ("greeter", "refuser", "answering", "refused"),
    [
        (ROGUE, PRODUCER, {PRODUCER}, True),  # a forged greeting, then the real refusal
        (PRODUCER, ROGUE, {PRODUCER}, False),  # the real greeting, then a forged refusal
        (ROGUE, PRODUCER, {PRODUCER, ROGUE}, False),  # two answer: nothing is trusted
    ],
)
def test_a_refusal_from_another_session_than_the_greeting_is_judged(
    greeter: str, refuser: str, answering: set[str], refused: bool
) -> None:
    """A peer greets a new subscription in the producer's name before the producer's
    refusal arrives: the refusal is judged, and if it is the producer's, the forged greeting
    is void (the subscription is refused, says so and retries), not left waiting unheard."""
    sub = SubscriberProtocol(SubscriptionMode.FLOW, 4, -1)
    hello = encode_control("hello", sub.descriptor, "forged.1", base=0)
    sub.receive(hello, b"", sender=greeter)
    assert sub.registered_epoch == "forged.1"
    refusal = encode_control("refused", sub.descriptor, "observe share used up")
    sub.receive(refusal, b"", sender=refuser)
    assert sub.next_deadline_ns() == 0, "to be judged at once"
    assert sub.judge(0) is True
    sub.trust_producer(frozenset(answering), 0)
    assert (sub.refusal == "observe share used up") is refused
    assert (sub.registered_epoch is None) is refused
    if refused:
        assert sub.refusal_news() == "observe share used up"
        assert sub.retry_due(10**10), "a refused subscription declares its token again"


def test_a_greeting_under_a_new_epoch_is_news_once_and_a_refusal_waits_to_be_judged() -> None:
    """What the wrapper logs and when it wakes the executor is the protocol's to say."""
    sub = SubscriberProtocol(SubscriptionMode.FLOW, 4, -1)
    assert sub.needs_sender(b"") and not sub.needs_sender(b"payload")
    sub.receive(encode_control("hello", sub.descriptor, "p1.1", base=0), b"", sender=PRODUCER)
    assert not sub.registration_news()  # the first greeting is no "again"
    sub.receive(encode_control("hello", sub.descriptor, "p2.1", base=0), b"", sender=PRODUCER)
    assert sub.registration_news() and not sub.registration_news()
    assert not sub.refusal_to_judge
    sub.receive(encode_control("refused", sub.descriptor, "full"), b"", sender=ROGUE)
    assert sub.refusal_to_judge and sub.next_deadline_ns() == 0


def test_a_greeting_of_the_same_epoch_from_another_session_is_forged() -> None:
    """The greeting's session is the one whose answers speak for the service (a mediator's
    clock samples). A peer that sends the same epoch's greeting in its own name made itself
    that session, and fed the mediator a clock 3 s off; an epoch is one instance's, in one
    session. A new epoch from another session is a restarted producer, as before."""
    sub = SubscriberProtocol(SubscriptionMode.FLOW, 4, -1)
    sub.receive(encode_control("hello", sub.descriptor, "p1.1", base=0), b"", sender=PRODUCER)
    assert sub.greeted_by == PRODUCER
    sub.receive(encode_control("hello", sub.descriptor, "p1.1", base=0), b"", sender=ROGUE)
    assert (sub.greeted_by, sub.registered_epoch, sub.garbage) == (PRODUCER, "p1.1", 1)
    sub.receive(encode_control("hello", sub.descriptor, "p1.1", base=0), b"", sender=PRODUCER)
    assert (sub.greeted_by, sub.garbage) == (PRODUCER, 1), "the producer's own re-greeting"
    sub.receive(encode_control("hello", sub.descriptor, "p2.1", base=0), b"", sender=ROGUE)
    assert (sub.greeted_by, sub.registered_epoch) == (ROGUE, "p2.1")


def _notification(sub: SubscriberProtocol, epoch: str, seq: int) -> bytes:
    return encode_notification_header(
        epoch, seq, seq, b"<m/>", pushed=False, descriptor=sub.descriptor, base=0
    )


def test_the_session_that_speaks_for_the_service_is_the_one_whose_notifications_come() -> None:
    """A peer's greeting under a made-up epoch and one notification of it made the peer's
    session the one a mediator asked for the camera's clock, for good: it never answered
    and every frame went unpaired (``clock-unmeasured``). The producer's next notification
    names its own greeter again; a restarted producer's greeting speaks until its first."""
    sub = SubscriberProtocol(SubscriptionMode.FLOW, 4, -1)
    sub.receive(encode_control("hello", sub.descriptor, "p1.1", base=0), b"", sender=PRODUCER)
    assert sub.data_session == PRODUCER
    sub.receive(_notification(sub, "p1.1", 1), b"")
    sub.receive(encode_control("hello", sub.descriptor, "rogue.1", base=0), b"", sender=ROGUE)
    assert sub.data_session == ROGUE  # nothing came after it yet: a restart looks the same
    sub.receive(_notification(sub, "rogue.1", 1), b"")
    assert sub.data_session == ROGUE
    sub.receive(_notification(sub, "p1.1", 2), b"")
    assert sub.data_session == PRODUCER, "the producer's notifications came again"
    assert (sub.greeted_by, sub.registered_epoch) == (ROGUE, "rogue.1")  # as before
    # A real restart: the new session's greeting, then its notifications.
    sub.receive(encode_control("hello", sub.descriptor, "p2.1", base=0), b"", sender="new")
    assert sub.data_session == "new"
    sub.receive(_notification(sub, "p2.1", 1), b"")
    assert sub.data_session == "new"
