"""Whose ``refused`` a subscription believes (``SubscriberProtocol.judge``): only the one
session that answers as the service. Pure: no Zenoh, no threads, no clock."""

from __future__ import annotations

import pytest

from middleware._protocol_subscriber import SubscriberProtocol
from middleware._records import SubscriptionMode
from middleware._wire import encode_control

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
