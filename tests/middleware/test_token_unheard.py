"""A subscriber whose token came back while its producer heard only the withdrawal is
registered again, and what was stored meanwhile reaches it as missed.

Zenoh can lose a token event with no sign of it (under token churn it logged "Unknown token
id", and a flow subscriber whose token had been withdrawn and declared again was never
heard of again). The producer cannot see that loss; what it does see is the subscriber,
idle, repeating its ack of the registration the producer retired. Real sessions over
loopback; the lost declaration is the producer told of the withdrawal alone.
"""

from __future__ import annotations

import time

import pytest

from middleware import NetworkConfig, Node, make_metadata
from tests.conftest import wait_until
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration

MS = 1_000_000


def test_a_subscriber_whose_token_came_back_unheard_is_registered_again(
    listen_net: NetworkConfig, connect_net: NetworkConfig
) -> None:
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        images = service.offer("images")
        sub = client.subscribe("cam/images", queue_size=4, wait_s=scaled(30))
        first = sub.registered_epoch

        def put(t: int) -> None:
            images.put(t * MS, b"x", make_metadata("generic", t * MS))

        for t in (1, 2):
            put(t)
        assert [sub.take(timeout_s=scaled(30)).timestamp_ns for _ in range(2)] == [MS, 2 * MS]
        # (Its ack taken in first: the next one then arrives for a retired registration.)
        wait_until(lambda: images.subscriptions()[0].queued == 0, scaled(30), "the ack")
        # The withdrawal heard, the declaration after it lost: the producer drops the
        # registration the subscriber still holds.
        with images._lock:
            images._protocol.token(sub._token_key, False, time.monotonic_ns())
        assert not images.subscriptions()
        for t in (3, 4, 5):
            put(t)  # nobody registered: stored, notified to nobody

        def registered_again() -> bool:
            # Waiting in ``take`` is idle: the subscriber repeats its ack meanwhile.
            assert sub.take(timeout_s=0.5) is None, "a notification of a retired registration"
            return sub.registered_epoch not in (None, first)

        wait_until(registered_again, scaled(30), "the subscriber registered again")
        put(6)
        back = sub.take(timeout_s=scaled(30))
        assert back.timestamp_ns == 6 * MS
        assert back.missed == 3, "what was stored while it was not registered is not counted"
        assert images.info().foreign_acks >= 1  # its repeated ack of the retired registration


def test_a_subscriber_registered_again_repeats_no_ack_of_its_replaced_registration() -> None:
    """A subscriber registered again (a lapse, heard whole) must not repeat, while idle, its
    ack of the registration the new one replaced: the producer retired it, and each such
    ack would make it check its table against the network (every 2 s, for good). What it
    repeats is the ack of the registration it holds now."""
    from middleware._protocol_subscriber import SubscriberProtocol
    from middleware._records import SubscriptionMode
    from middleware._wire import decode_ack, encode_control, encode_notification_header

    sub = SubscriberProtocol(SubscriptionMode.FLOW, 4, -1)
    descriptor = "flow/4/-1"
    for epoch in ("P0.1", "P0.2"):  # greeted, took one; its token lapsed; greeted again
        sub.receive(encode_control("hello", descriptor, epoch, 0, None), b"")
        sub.receive(
            encode_notification_header(epoch, 1, 1, b"m", pushed=False, descriptor=descriptor), b""
        )
        assert sub.take_many(4)
        sub.acks(0, idle=False)
    repeated = [decode_ack(a) for a in sub.acks(10**10, idle=True)]
    assert repeated == [("P0.2", 1)]
    # A later registration whose greeting was lost (taken from its notifications) is live:
    # its ack is repeated, or a lost one would hold the producer for good.
    sub.receive(
        encode_notification_header("P0.3", 1, 2, b"m", pushed=False, descriptor=descriptor), b""
    )
    assert sub.take_many(4)
    sub.acks(2 * 10**10, idle=False)
    repeated = [decode_ack(a) for a in sub.acks(3 * 10**10, idle=True)]
    assert ("P0.3", 1) in repeated and ("P0.1", 1) not in repeated
