"""A query naming no session asks the session that answers as the service (its owner) for
its answer alone: a restarted service (another session) is its owner from then on."""

from __future__ import annotations

import pytest

from middleware import NetworkConfig, Node, make_metadata
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration


def _offer(node: Node, t: int) -> None:
    node.offer("images", kind="generic").put(t, b"x", make_metadata("generic", t))


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
