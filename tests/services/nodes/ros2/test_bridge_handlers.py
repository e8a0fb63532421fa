"""The bridge's outputs and its first look at the ROS 2 side as handlers and timers, fed by
the test on its own thread with its own notifications and times: no ROS 2 router, no
producer, and no thread of the bridge's."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest

from middleware import DataObject, NetworkConfig, Node, Notification, TransportError
from services.nodes.ros2._bridge import Output, _InQueue, _Skips
from services.nodes.ros2._config import Mapping, Ros2Config
from services.nodes.ros2._graph import ROUTER_WAIT_S, GraphSettle, RouterWatch
from tests.conftest import free_port

S = 1_000_000_000
WHERE = "tcp/localhost:7447"


class _Publisher:
    """Stands in for the ROS 2 publisher: keeps what it was given, refuses ``b"refuse"``."""

    def __init__(self) -> None:
        self.published: list[bytes] = []

    def publish(self, cdr: bytes) -> None:
        if cdr == b"refuse":
            raise TransportError("cannot publish on the test's topic")
        self.published.append(bytes(cdr))


def _encode(element: DataObject) -> bytes | None:
    if element.payload == b"bad":
        raise ValueError("not an element this output can encode")
    if element.payload == b"bug":
        raise RuntimeError("a bug in an encoder")
    return None if element.payload == b"none" else element.payload


def _note(t: int, payload: bytes, missed: int = 0) -> Notification:
    element = DataObject(t, payload, b"")
    return Notification("mediator", "decisions", t, t, element=element, missed=missed)


@pytest.fixture
def output() -> Iterator[tuple[Output, _Publisher, _Skips]]:
    with Node("ros2", NetworkConfig(local_port=free_port())) as node:
        publisher = _Publisher()
        skips = _Skips(logging.getLogger("test.bridge.handlers"))
        out = Output(
            node,
            publisher,  # type: ignore[arg-type]
            Mapping("mediator/decisions", "/framegate/verdicts"),
            _encode,
            Ros2Config(out_queue=2),
            skips,
        )
        yield out, publisher, skips


def test_an_output_handler_publishes_and_counts_each_skip_by_its_reason(
    output: tuple[Output, _Publisher, _Skips],
) -> None:
    out, publisher, skips = output
    out.on_notes([_note(1, b"one"), _note(5, b"five", missed=3), _note(6, b"bad")])
    out.on_notes([_note(7, b"refuse"), _note(8, b"none"), _note(9, b"bug"), _note(10, b"ten")])
    # An element encoded to nothing is not published, and not a skip either.
    assert publisher.published == [b"one", b"five", b"ten"]
    assert out.published == 3
    assert dict(skips.counts) == {
        "not-observed": 3,  # the elements before 5 the observer was never notified of
        "bad-element": 1,
        "publish-failed": 1,
        "internal-error": 1,  # logged with its traceback; the next element still goes out
    }


def test_a_missing_ros2_router_is_said_once_at_its_wait_and_its_arrival_too(
    caplog: pytest.LogCaptureFixture,
) -> None:
    routers = [0]
    watch = RouterWatch(lambda: routers[0], WHERE, logging.getLogger("test.router"), 0)
    with caplog.at_level(logging.INFO, logger="test.router"):
        assert not watch.on_time(int(ROUTER_WAIT_S * S) - 1)
        assert caplog.text == ""  # not a nanosecond early
        assert not watch.on_time(int(ROUTER_WAIT_S * S))
        assert not watch.on_time(int(ROUTER_WAIT_S * S) + S)
        assert caplog.text.count(f"no ROS 2 router at {WHERE}") == 1
        routers[0] = 1
        assert watch.on_time(int(ROUTER_WAIT_S * S) + 2 * S)
    assert f"connected to the ROS 2 router at {WHERE}" in caplog.text


def test_a_present_ros2_router_is_not_warned_about(caplog: pytest.LogCaptureFixture) -> None:
    watch = RouterWatch(lambda: 1, WHERE, logging.getLogger("test.router"), 0)
    with caplog.at_level(logging.INFO, logger="test.router"):
        assert watch.on_time(10 * S)  # however late the first look
    assert caplog.text == ""


class _Watch:
    """Stands in for a SequenceWatch: keeps what it was told."""

    def __init__(self) -> None:
        self.announced: list[str] = []
        self.settled_after = -1

    def announce(self, token: str) -> None:
        self.announced.append(token)

    def settle(self) -> None:
        self.settled_after = len(self.announced)


def test_the_graph_is_two_looks_joined_then_settled_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    watch = _Watch()
    settle = GraphSettle([watch], "framegate_bridge", logging.getLogger("test.graph"))  # type: ignore[list-item]
    with caplog.at_level(logging.INFO, logger="test.graph"):
        assert settle.looked(["a", "b"])  # look once more
        assert watch.settled_after == -1 and watch.announced == []
        assert not settle.looked(["b", "c"])
        assert not settle.looked(["d"])  # settled: a late answer changes nothing
    assert sorted(watch.announced) == ["a", "b", "c"] and watch.settled_after == 3
    assert caplog.text.count("ROS graph taken by framegate_bridge (3 entities)") == 1


def test_an_in_queue_asks_for_one_drain_per_burst_not_per_sample() -> None:
    # Zenoh's thread puts; the executor drains a few per run and schedules the next run
    # itself while more wait: one deadline per burst on the executor, however many samples.
    asked: list[int] = []
    queue = _InQueue(10, 1 << 20, lambda: None)
    queue.on_ready = lambda: asked.append(1)
    queue.put(b"a", None)
    queue.put(b"b", None)
    assert len(asked) == 1
    assert queue.drain(1) == ([(b"a", None)], True)  # more wait: the drainer goes on
    queue.put(b"c", None)
    assert len(asked) == 1
    assert queue.drain(4) == ([(b"b", None), (b"c", None)], False)
    queue.put(b"d", None)  # a new burst
    assert len(asked) == 2
