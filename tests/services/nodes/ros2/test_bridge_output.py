"""The bridge's outputs count what they were never notified of: an observer whose queue was
full, or whose subscription lapsed, misses elements, and the bridge never publishes them; each
is a counted ``not-observed`` skip, never a silent gap on the ROS 2 topic."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest

from middleware import NetworkConfig, Node, make_metadata
from middleware._wire import Keys
from services.nodes._not_observed import BAD_NOTIFICATION
from services.nodes.ros2._bridge import Output, _Skips
from services.nodes.ros2._config import Mapping, Ros2Config
from tests.conftest import wait_until
from tests.helpers.raw_zenoh import open_session

pytestmark = pytest.mark.integration

COUNT = 12


class _Publisher:
    """Stands in for the ROS 2 publisher: keeps what the output published."""

    def __init__(self) -> None:
        self.published: list[bytes] = []

    def publish(self, cdr: bytes) -> None:
        self.published.append(bytes(cdr))


def _output(bridge: Node, config: Ros2Config) -> tuple[_Publisher, _Skips, Output]:
    """An output of mediator/decisions on ``bridge``, publishing to a stand-in."""
    publisher = _Publisher()
    skips = _Skips(logging.getLogger("test.bridge.output"))
    output = Output(
        bridge,
        publisher,  # type: ignore[arg-type]
        Mapping("mediator/decisions", "/framegate/verdicts"),
        lambda element: element.payload,
        config,
        skips,
    )
    return publisher, skips, output


@pytest.fixture
def nodes(listen_net: NetworkConfig, connect_net: NetworkConfig) -> Iterator[tuple[Node, Node]]:
    with Node("mediator", listen_net) as producer, Node("ros2", connect_net) as bridge:
        yield producer, bridge


def test_elements_an_output_was_never_notified_of_are_counted_not_observed(
    nodes: tuple[Node, Node],
) -> None:
    producer, bridge = nodes
    decisions = producer.offer("decisions")
    publisher, skips, output = _output(bridge, Ros2Config(out_queue=1))
    wait_until(lambda: decisions.subscriptions(), 30, "the output's subscription")
    # Nobody takes yet: a queue of one holds the first, the observer misses the rest.
    for t in range(1, COUNT):
        decisions.put(t, b"%d" % t, make_metadata("generic", t))
    output.attach()  # the node's executor takes from now on
    wait_until(lambda: publisher.published, 30, "the first element published")
    decisions.put(COUNT, b"%d" % COUNT, make_metadata("generic", COUNT))
    wait_until(lambda: publisher.published[-1] == b"%d" % COUNT, 30, "the last element published")
    missed = skips.counts["not-observed"]
    assert missed > 0, publisher.published
    # Every element either reached the ROS 2 topic or was counted as never observed.
    assert len(publisher.published) + missed == COUNT, (publisher.published, missed)


def test_garbage_on_an_output_s_notify_key_is_counted_and_publishing_goes_on(
    nodes: tuple[Node, Node], endpoint: str
) -> None:
    """A peer's garbage on the key an output's notifications come on is a counted
    ``bad-notification`` (it was counted inside the subscription only, shown nowhere), and the
    output keeps publishing."""
    producer, bridge = nodes
    decisions = producer.offer("decisions")
    publisher, skips, output = _output(bridge, Ros2Config())
    output.attach()
    (sub,) = wait_until(lambda: decisions.subscriptions(), 30, "the output's subscription")
    key = Keys("framegate").notify("mediator", "decisions", sub.subscription_id)
    with open_session(endpoint) as rogue:

        def counted() -> bool:
            for _ in range(10):  # sent until counted: the first may reach no one yet
                rogue.put(key, b"\xff" * 32, attachment=b"not a notification")
            return skips.counts[BAD_NOTIFICATION] >= 10

        wait_until(counted, 30, "the garbage counted bad-notification")
    decisions.put(1, b"1", make_metadata("generic", 1))
    wait_until(lambda: publisher.published == [b"1"], 30, "the element published after it")
