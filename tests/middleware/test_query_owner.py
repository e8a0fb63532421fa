"""A query naming no session asks the session that answers as the service (its owner) for
its answer alone; the owner is remembered, so that each query costs no ``@info`` round trip,
and asked again when it stops answering (the service restarted: a new session)."""

from __future__ import annotations

import threading

import pytest
import zenoh

from middleware import NetworkConfig, Node, make_metadata
from middleware._wire import Keys
from tests.helpers.raw_zenoh import open_session
from tests.helpers.timing import scaled, wait_until

pytestmark = pytest.mark.integration


def _offer(node: Node, t: int) -> None:
    node.offer("images", kind="generic").put(t, b"x", make_metadata("generic", t))


def test_queries_ask_the_owner_once_not_each_time(
    listen_net: NetworkConfig, connect_net: NetworkConfig, endpoint: str
) -> None:
    # Each query and latest asked @info/cam first: twice the round trips (0.3 -> 0.7 ms).
    asked: list[str] = []
    lock = threading.Lock()

    def count(query: zenoh.Query) -> None:
        with lock:
            asked.append(str(query.key_expr))
        query.drop()  # answers nothing: cam's own answer is the one that counts

    with (
        Node("cam", listen_net) as cam,
        open_session(endpoint) as watcher,
        Node(network=connect_net) as client,
    ):
        _offer(cam, 1)
        counter = watcher.declare_queryable(
            Keys("framegate").info("cam"), zenoh.handlers.Callback(count)
        )
        try:
            # The watcher's queryable must be known to the client before its first query.
            wait_until(
                lambda: client.service_info("cam", timeout_s=scaled(5)) and asked,
                scaled(20),
                "the watcher to see the client's @info queries",
            )
            asked.clear()
            for _ in range(10):
                assert [
                    e.timestamp_ns for e in client.query("cam/images", timeout_s=scaled(10))
                ] == [1]
                assert [
                    e.timestamp_ns for e in client.latest("cam/images", timeout_s=scaled(10))
                ] == [1]
        finally:
            counter.undeclare()
    assert 1 <= len(asked) <= 2, asked  # the first query finds the owner (and what follows)


def test_a_restarted_service_is_found_again(
    listen_net: NetworkConfig, connect_net: NetworkConfig
) -> None:
    with Node(network=connect_net) as client:
        with Node("cam", listen_net) as first:
            _offer(first, 1)
            assert [e.timestamp_ns for e in client.query("cam/images", timeout_s=scaled(10))] == [1]
        with Node("cam", listen_net) as second:  # the same service, another session
            _offer(second, 2)
            found = client.query("cam/images", timeout_s=scaled(20))
        assert [e.timestamp_ns for e in found] == [2]
