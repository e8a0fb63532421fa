"""A flood of forged greetings on a subscription's notify key costs a bounded log.

Any peer can send the producer's ``hello`` control message on a subscription's notify key
(the default profile): each reads as the subscription registered again. Real processes'
sessions over loopback: the producer, the subscriber and a rogue Zenoh session.
"""

from __future__ import annotations

import logging

import msgpack
import pytest

from middleware import NetworkConfig, Node
from tests.conftest import wait_until
from tests.helpers.raw_zenoh import open_session
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration

GREETINGS = 100


def test_a_flood_of_forged_greetings_is_logged_in_a_line_or_two(
    listen_net: NetworkConfig,
    connect_net: NetworkConfig,
    endpoint: str,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """500 forged greetings in a second made the mediator log 422 lines "registered
    again": a peer could fill a disk with one line per message it sends."""
    caplog.set_level(logging.INFO, logger="framegate.middleware")
    with (
        Node("cam", listen_net) as service,
        Node(network=connect_net) as client,
        open_session(endpoint) as rogue,
    ):
        images = service.offer("images")
        sub = client.subscribe("cam/images", queue_size=4, wait_s=scaled(30))
        assert images.subscriptions(), "not registered"
        key = f"framegate/@notify/cam/images/{sub.subscription_id}"
        descriptor = "flow/4/-1"
        for k in range(GREETINGS):
            # One at a time, each read before the next: as a subscription fed by its
            # executor between them (the mediator's) reads a flood.
            epoch = f"forged{k}.1"
            rogue.put(key, b"", attachment=msgpack.packb(("hello", descriptor, epoch, 0)))
            wait_until(
                lambda e=epoch: sub.registered_epoch == e,  # type: ignore[misc]
                scaled(30),
                "the forged greeting",
            )
    lines = [r for r in caplog.records if "registered again" in r.getMessage()]
    assert 1 <= len(lines) <= 2, [r.getMessage() for r in lines]
    assert "times since the last such line" in lines[-1].getMessage() or len(lines) == 1
