"""Floods on a producer's ack key from other processes: oversize messages are dropped and
counted before they are buffered, and ``put(wait_s=)`` returns or raises within ``wait_s``
plus a small slack however fast the flood comes (real processes, real Zenoh)."""

from __future__ import annotations

import contextlib
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
import zenoh

from middleware import PUSH_ALL, FlowControlRefused, Node, Subscription, make_metadata
from middleware._inbox import NOTIFY_INBOX_BYTES
from middleware._producer import ACK_MAX_BYTES
from middleware._wire import encode_ack
from tests.conftest import REPO, child_env, wait_until
from tests.helpers.raw_zenoh import open_session
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration

_FLOODER = """
import sys, time
from tests.helpers.raw_zenoh import open_session
endpoint, key, size, seconds = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
with open_session(endpoint) as session:
    pub = session.declare_publisher(key)
    payload = bytes(size)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for _ in range(64):
            pub.put(payload)
"""


# A flow-controlled subscriber that never reads what it is sent: its Zenoh receive thread
# blocks in a full channel while its session stays alive (the lease holds).
_STUCK = """
import sys, time, zenoh
from tests.helpers.raw_zenoh import open_session
endpoint, sub_id = sys.argv[1], sys.argv[2]
with open_session(endpoint) as session:
    notify = session.declare_subscriber(
        f"framegate/@notify/cam/images/{sub_id}", zenoh.handlers.FifoChannel(1)
    )
    token = session.liveliness().declare_token(
        f"framegate/@sub/cam/images/{sub_id}/flow/16384/-1/stuck~rogue"
    )
    time.sleep(float(sys.argv[3]))
"""


@contextmanager
def flooding(endpoint: str, key: str, size: int, processes: int) -> Iterator[None]:
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", _FLOODER, endpoint, key, str(size), str(scaled(60))],
            cwd=REPO,
            env=child_env(),
        )
        for _ in range(processes)
    ]
    try:
        yield
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()


def _meta(t: int) -> bytes:
    return make_metadata("generic", t)


@pytest.mark.parametrize("size", [16, 1 << 20], ids=["16 B garbage", "1 MiB garbage"])
def test_put_with_wait_s_returns_in_time_under_an_ack_flood(
    listen_net, connect_net, endpoint, size
) -> None:
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        images = service.offer("images")
        sub = client.subscribe("cam/images", queue_size=2)
        key = f"framegate/@ack/cam/images/{sub.subscription_id}"
        with flooding(endpoint, key, size, processes=2):
            wait_until(
                lambda: images.info().dropped_messages > 0 or size <= ACK_MAX_BYTES, 30, "the flood"
            )
            time.sleep(0.5)  # the flood under way
            for t in (1, 2):
                images.put(t, b"x", _meta(t), wait_s=scaled(10))  # the queue of 2 fills
            waits, refused = [], 0
            for t in (3, 4, 5):
                start = time.monotonic()
                try:
                    images.put(t, b"x", _meta(t), wait_s=0.5)  # nobody takes: refused
                except FlowControlRefused:
                    refused += 1
                waits.append(time.monotonic() - start)
            info = images.info()
            # 1 MiB floods from two processes can saturate loopback for the consumer's session
            # too (its registration may lapse and re-register meanwhile): refusals and the
            # flow going on are checked under the small flood, the time bound under both.
            if size <= ACK_MAX_BYTES:
                assert refused == 3
                # Flow goes on: a taken notification frees its credit despite the flood.
                assert sub.take(timeout_s=scaled(10)) is not None
                images.put(6, b"x", _meta(6), wait_s=scaled(10))
        # Bounded by its wait plus slack a 10x slower machine meets (a starved test process
        # runs again past the deadline): a put that ignored wait_s would block for good.
        assert max(waits) < 0.5 + scaled(10.0), f"put(wait_s=0.5) took {waits}"
        if size > ACK_MAX_BYTES:
            assert info.dropped_messages > 0, "oversize acks are dropped and counted"


def test_oversize_acks_are_never_buffered(listen_net, connect_net, endpoint) -> None:
    """1 MiB acks from two processes: each is counted and dropped before it is buffered,
    so the ack inbox holds none of them."""
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        images = service.offer("images")
        sub = client.subscribe("cam/images", queue_size=2)
        key = f"framegate/@ack/cam/images/{sub.subscription_id}"
        with flooding(endpoint, key, 1 << 20, processes=2):
            wait_until(lambda: images.info().dropped_messages > 50, 60, "oversize acks counted")
            assert len(images._acks) == 0


def test_a_flooded_subscription_does_not_starve_the_others(
    listen_net, connect_net, endpoint
) -> None:
    """Garbage floods one subscription's notification key from two processes; the node's
    executor still serves the other subscription's handler (round robin, bounded batches)."""
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        flooded, calm = service.offer("flooded"), service.offer("calm")
        victim = client.subscribe("cam/flooded", queue_size=2)
        sub = client.subscribe("cam/calm", queue_size=4)
        seen: list[int] = []
        client.on(victim, lambda notes: None)
        client.on(sub, lambda notes: seen.extend(n.timestamp_ns for n in notes))
        key = f"framegate/@notify/cam/flooded/{victim.subscription_id}"
        with flooding(endpoint, key, 16, processes=2):
            wait_until(lambda: victim.garbage > 1000, 60, "the flood under way")
            for t in range(1, 41):
                calm.put(t, b"x", _meta(t), wait_s=scaled(20))
            wait_until(lambda: len(seen) == 40, 60, "every calm notification handled")
        assert seen == list(range(1, 41))
        del flooded


def test_garbage_and_repeated_acks_are_dropped_before_they_are_buffered(
    listen_net, connect_net, endpoint
) -> None:
    """Garbage (not an ack's first byte) and one valid-looking ack repeated, on a live
    subscription's own ack key: each is counted as dropped on Zenoh's thread and none is
    buffered, and the subscription's own acks still free its credit among them."""
    garbage, repeats = 500, 500
    with (
        Node("cam", listen_net) as service,
        Node(network=connect_net) as client,
        open_session(endpoint) as rogue,
    ):
        images = service.offer("images")
        sub = client.subscribe("cam/images", queue_size=1)
        key = f"framegate/@ack/cam/images/{sub.subscription_id}"
        # A copy of the subscription's own ack of its first element (an ack that could
        # count: one of a seq never sent, or below 1, is dropped as foreign instead).
        images.put(1, b"x", _meta(1), wait_s=scaled(10))
        first = sub.take(timeout_s=scaled(10))
        assert first is not None and first.timestamp_ns == 1
        forged = encode_ack(images.epoch + ".1", 1)
        block = zenoh.CongestionControl.BLOCK  # every message arrives: the counts are exact
        for _ in range(garbage):
            rogue.put(key, bytes(16), congestion_control=block)
        for _ in range(repeats):
            rogue.put(key, forged, congestion_control=block)
        acks = images._acks
        wait_until(lambda: acks.malformed == garbage, 30, "every garbage ack counted")
        # The forged ack is kept once per repeat window (100 ms): most of them are repeats
        # (all of them when the subscription's own ack is still the one kept).
        wait_until(lambda: acks.repeats >= repeats // 2, 30, "the repeats counted")
        assert len(acks) <= repeats - acks.repeats + 1
        assert images.info().dropped_messages >= garbage + acks.repeats
        # The subscription's own acks pass among them: its queue of 1 frees each time.
        for t in range(2, 7):
            images.put(t, b"x", _meta(t), wait_s=scaled(10))
            for _ in range(50):
                rogue.put(key, bytes(16), congestion_control=block)
                rogue.put(key, forged, congestion_control=block)
            note = sub.take(timeout_s=scaled(10))
            assert note is not None and note.timestamp_ns == t


def test_distinct_forged_acks_are_dropped_before_they_are_buffered(
    listen_net, connect_net, endpoint
) -> None:
    """Valid-looking acks, each different (made-up epochs, another id's epoch, numbers beyond
    what was sent), on a live subscription's ack key: none can count, so each is dropped on
    Zenoh's thread (``foreign``) and none is buffered. They used to fill the inbox ahead of
    the subscription's own acks (a camera stalled ~10 s under such a flood)."""
    with (
        Node("cam", listen_net) as service,
        Node(network=connect_net) as client,
        open_session(endpoint) as rogue,
    ):
        images = service.offer("images")
        sub = client.subscribe("cam/images", queue_size=1)
        other = client.subscribe("cam/images", queue_size=1)
        key = f"framegate/@ack/cam/images/{sub.subscription_id}"
        wait_until(lambda: len(images.subscriptions()) == 2, 30, "both registered")
        epochs = [f"{images.epoch}.{n}" for n in (1, 2)]  # sub's, and other's
        block = zenoh.CongestionControl.BLOCK
        forged = [encode_ack(f"made-up.{n}", 1) for n in range(300)]
        forged += [encode_ack(epoch, 10**6 + n) for n in range(300) for epoch in epochs[:1]]
        forged += [encode_ack(epochs[1], n) for n in range(300)]  # not this key's epoch
        for payload in forged:
            rogue.put(key, payload, congestion_control=block)
        acks = images._acks
        # sub's own epoch on sub's key, beyond sent: the first 300 + 300 + 300 are foreign.
        wait_until(lambda: acks.foreign == len(forged), 30, "every forged ack counted")
        assert len(acks) == 0 and acks.overflow == 0
        for t in range(1, 6):  # the subscription's own acks free its credit among them
            images.put(t, b"x", _meta(t), wait_s=scaled(10))
            for payload in forged[:20]:
                rogue.put(key, payload, congestion_control=block)
            note = sub.take(timeout_s=scaled(10))
            assert note is not None and note.timestamp_ns == t
            assert other.take(timeout_s=scaled(10)) is not None


def _held_bytes(sub: Subscription) -> int:
    items = list(sub._inbox._items)  # a copy: Zenoh's thread appends meanwhile
    return sum(len(s.payload) + len(s.attachment or b"") for s in items)


def test_a_flood_of_large_garbage_on_a_notify_key_holds_bounded_bytes(
    listen_net, connect_net, endpoint
) -> None:
    """2 MiB garbage on the notify key of a subscription that takes every payload pushed
    (``PUSH_ALL``, as the mediator's), while it takes nothing: its inbox holds at most
    ``NOTIFY_INBOX_BYTES``, not its count of samples of any size (4 MiB garbage from one
    process grew a mediator-like consumer from 42 to 362 MB), and an element put after the
    flood is still taken."""
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        images = service.offer("images")
        sub = client.subscribe("cam/images", queue_size=8, push_max_bytes=PUSH_ALL)
        key = f"framegate/@notify/cam/images/{sub.subscription_id}"
        most = 0
        with flooding(endpoint, key, 2 << 20, processes=1):

            def filled() -> bool:
                nonlocal most
                most = max(most, _held_bytes(sub))
                return sub._inbox.squeezed > 100 or most > NOTIFY_INBOX_BYTES

            wait_until(filled, 60, "the inbox filled and pushing out")
        most = max(most, _held_bytes(sub))
        assert most <= NOTIFY_INBOX_BYTES, f"held {most / 2**20:.0f} MiB"
        images.put(1, b"y" * 100, _meta(1), wait_s=scaled(10))
        note = sub.take(timeout_s=scaled(10))
        while note is not None and note.timestamp_ns != 1:  # garbage is no notification
            note = sub.take(timeout_s=scaled(10))
        assert note is not None and sub.fetch(note).payload == b"y" * 100


def test_a_subscriber_that_stops_reading_has_its_link_closed_and_puts_go_on(
    listen_net, endpoint
) -> None:
    """A flow-controlled subscriber (queue 16,384) whose process stops reading its link while
    its session lives: the notifications fill the link, the put that sends the next one
    waits in Zenoh until the link is closed, and then the subscription is dropped and puts
    go on. How long that wait is (the lease, 1 s, not Zenoh's 5 s: a ``put(wait_s=0)``
    took 5.0 s, again each time the peer came back) is the session's configuration,
    checked in test_config_network.py; a time measured here would be the machine's."""
    with Node("cam", listen_net) as service:
        images = service.offer("images")
        stuck = subprocess.Popen(
            [sys.executable, "-c", _STUCK, endpoint, "stuck1", str(scaled(60))],
            cwd=REPO,
            env=child_env(),
        )
        try:
            wait_until(lambda: images.info().subscriptions, 30, "the stuck subscriber")
            t, blob = 0, bytes(2048)
            while images.info().subscriptions:  # until its link is closed
                t += 1
                with contextlib.suppress(FlowControlRefused):
                    images.put(t, blob, _meta(t), wait_s=0)
                assert t < 10_000_000, "the stuck subscriber's link never closed"
            images.put(t + 1, blob, _meta(t + 1), wait_s=0)  # nobody left to refuse it
        finally:
            stuck.kill()
            stuck.wait()
