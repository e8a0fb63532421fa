"""A peer that declares more liveliness tokens than Zenoh's default reply channel holds (256):
every liveliness query of framegate still ends (real Zenoh on loopback; the peer is a raw
session in this process)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TypeVar

import pytest
import zenoh

from middleware import NetworkConfig, Node, NotFoundError, make_metadata
from tests.conftest import wait_until
from tests.helpers.raw_zenoh import open_session
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration

CROWD = 300
T = TypeVar("T")


@contextmanager
def _crowd(endpoint: str, prefix: str) -> Iterator[None]:
    """``CROWD`` liveliness tokens ``<prefix>0000`` ... declared by a raw peer."""
    with open_session(endpoint) as rogue:
        tokens = [rogue.liveliness().declare_token(f"{prefix}{i:04d}") for i in range(CROWD)]
        try:
            yield
        finally:
            for token in tokens:
                token.undeclare()


def _ends(call: Callable[[], T], what: str) -> T:
    """``call()`` run on a daemon thread, which must end (it hung for good, past Ctrl-C,
    parked in Zenoh's full reply channel): its result."""
    out: list[T] = []
    thread = threading.Thread(target=lambda: out.append(call()), daemon=True)
    thread.start()
    thread.join(scaled(30))
    assert out, f"{what} never ended"
    return out[0]


def _seen(node: Node, name: str) -> bool:
    return name in _ends(lambda: node.live_services(timeout_s=scaled(2)), "live_services")


def test_a_crowd_of_service_tokens_does_not_hang_live_services(
    listen_net: NetworkConfig, endpoint: str
) -> None:
    """300 bare service tokens: a CLI's look at the live services (``echo``, ``watch``,
    ``record``, ``play`` start with one) hung for good."""
    with Node("real", listen_net) as service, Node(network=NetworkConfig(connect=(endpoint,))):
        service.offer("b")
        with _crowd(endpoint, "framegate/@svc/crowd"):
            client = service  # the service's own session knows the peer's tokens too
            wait_until(lambda: _seen(client, f"crowd{CROWD - 1:04d}"), 30, "the crowd")
            assert _seen(client, "real")


def test_a_crowd_of_subscription_tokens_does_not_hang_the_producer_at_resync(
    listen_net: NetworkConfig, endpoint: str
) -> None:
    """300 tokens under a buffer's subscription key (none a valid registration, so no
    limit holds them back) and a resync (as after a token churn that overflowed the
    producer's inbox): its executor hung in the liveliness query for good, so no later
    subscriber was registered and the node could not stop."""
    with (
        Node("cam", listen_net) as service,
        Node(network=NetworkConfig(connect=(endpoint,))) as client,
    ):
        images = service.offer("images")
        with _crowd(endpoint, "framegate/@sub/cam/images/junk"):
            wait_until(lambda: images.info().bad_messages >= CROWD, 30, "the junk tokens")
            with images._lock:  # what a churn that overflows the token inbox does
                images._protocol.tokens_lost(time.monotonic_ns())
            wait_until(  # asked and answered (the executor never waits on the query)
                lambda: (
                    images._resync is None
                    and not images._protocol.resync_due(time.monotonic_ns() + 10**12)
                ),
                30,
                "the resync",
            )
            sub = client.subscribe("cam/images", queue_size=2, wait_s=scaled(10))
            wait_until(lambda: images.info().subscriptions, 30, "the registration")
            t = time.time_ns()
            images.put(t, b"x", make_metadata("generic", t), wait_s=scaled(10))
            note = sub.take(timeout_s=scaled(10))
            assert note is not None and note.timestamp_ns == t


def test_live_keys_keeps_at_most_its_limit(endpoint: str) -> None:
    from middleware._liveliness import live_keys

    with open_session(endpoint, listen=True) as session, _crowd(endpoint, "x/crowd"):
        wait_until(
            lambda: len(live_keys(session, "x/*", timeout_s=scaled(2))) == CROWD, 30, "the crowd"
        )
        assert len(live_keys(session, "x/*", timeout_s=scaled(2), limit=7)) == 7
        assert isinstance(session, zenoh.Session)


def test_a_crowd_of_service_tokens_makes_no_endless_error_line(
    listen_net: NetworkConfig, endpoint: str
) -> None:
    """A misspelt name beside 300 services a peer made up: the error names 20 of them and
    how many more (it listed all 300; 65,536 of 1,024 characters would be 64 MiB)."""
    with Node("real", listen_net) as service, _crowd(endpoint, "framegate/@svc/crowd"):
        wait_until(lambda: _seen(service, f"crowd{CROWD - 1:04d}"), 30, "the crowd")
        with pytest.raises(NotFoundError, match=r"crowd0019 and \d+ more") as caught:
            service.subscribe("nosuch/b", wait_s=0.1)
        assert len(str(caught.value)) < 1_000


def test_a_live_query_tells_its_end_and_never_blocks_on_a_closed_session(endpoint: str) -> None:
    """What a producer's executor relies on to resync without waiting: the query's end is
    told (``on_end``, which wakes the executor), and a ``get`` that raises (the session
    closing) gives a query that is done at once, with an answer that is not whole."""
    from middleware._liveliness import LiveQuery

    ended = threading.Event()
    with open_session(endpoint, listen=True) as session:
        token = session.liveliness().declare_token("x/mine")
        query = LiveQuery(session, "x/*", timeout_s=scaled(2), on_end=ended.set)
        assert ended.wait(scaled(10)), "the query's end was never told"
        assert query.done(time.monotonic_ns())
        assert query.answer() == (["x/mine"], True)
        token.undeclare()
    closed = LiveQuery(session, "x/*", timeout_s=scaled(2))
    assert closed.error is not None and closed.done(time.monotonic_ns())
    assert closed.answer() == ([], False)
