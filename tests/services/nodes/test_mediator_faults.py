"""The mediator over real Zenoh on loopback: no consumer or peer input can stop it.

In-process nodes (the mediator's ``step`` is driven by the test); the process-level run is
``test_mediator_process.py``.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import pytest

from middleware import NetworkConfig, Node, Producer, Retention, make_metadata
from services.lib.decisions import GyroMissing, Load, tightest_load
from services.lib.messages import frame_metadata
from services.lib.quality import Exposure
from services.nodes.mediator import Mediator, MediatorConfig
from tests.conftest import wait_until
from tests.helpers.timing import answered, scaled
from tests.services.nodes.mediator_driver import step

MS = 1_000_000
IMAGE = np.zeros((2, 4), dtype=np.uint8)


@pytest.fixture
def nodes(listen_net: NetworkConfig, connect_net: NetworkConfig) -> Iterator[tuple[Node, Node]]:
    with Node("camera", listen_net) as camera, Node("mediator", connect_net) as mediator:
        yield camera, mediator


def _mediator(node: Node) -> Mediator:
    # No camera model in the frames: every frame goes through the gyro-missing rule.
    config = MediatorConfig(gyro_missing=GyroMissing.ACCEPT, gyro_wait_ms=0.0)
    return Mediator(node, config, "mediator")


def _put_frame(images: Producer, i: int, payload: bytes | None = None) -> int:
    exposure = Exposure((i + 1) * 40 * MS, 5 * MS)
    images.put(
        exposure.start_ns, payload or IMAGE.tobytes(), frame_metadata(i, exposure, IMAGE, None)
    )
    return exposure.start_ns


def _step_until(mediator: Mediator, done: object) -> None:
    def stepped() -> bool:
        step(mediator, timeout_s=scaled(0.1))
        return bool(done())  # type: ignore[operator]

    wait_until(stepped, 60, "the mediator to get through the frames")


def test_regression_a_flow_controlled_decisions_watcher_never_stops_the_mediator(
    nodes: tuple[Node, Node], connect_net: NetworkConfig
) -> None:
    # Issue 15: `framegate watch mediator/decisions --flow-control --queue 1 --delay 1`
    # killed the mediator: decisions.put raised FlowControlRefused out of step().
    camera, node = nodes
    images = camera.offer("images", kind="frame", retention=Retention(max_count=64))
    mediator = _mediator(node)
    try:
        with Node("watcher", connect_net) as watcher:
            stuck = watcher.subscribe("mediator/decisions", queue_size=1)  # never takes
            assert mediator.decisions.wait_for_subscribers(1, timeout_s=scaled(10))
            wait_until(lambda: images.subscriptions(), 10, "the mediator's camera subscription")
            for i in range(6):
                _put_frame(images, i)
            _step_until(mediator, lambda: mediator.images.info().puts == 6)
            assert mediator.decisions_dropped >= 5  # one record fits the watcher's queue
            assert mediator.decisions.info().puts == 1
            assert stuck.pending <= 1
    finally:
        mediator.close()


def test_frames_with_a_wrong_payload_size_are_skipped_and_good_ones_still_go(
    nodes: tuple[Node, Node],
) -> None:
    camera, node = nodes
    images = camera.offer("images", kind="frame", retention=Retention(max_count=64))
    mediator = _mediator(node)
    try:
        wait_until(lambda: images.subscriptions(), 10, "the mediator's camera subscription")
        good = [_put_frame(images, 0)]
        _put_frame(images, 1, payload=b"\x00" * 7)  # metadata says 4x2 mono8 = 8 bytes
        good.append(_put_frame(images, 2))
        _put_frame(images, 3, payload=b"\x00" * 800)
        good.append(_put_frame(images, 4))
        _step_until(mediator, lambda: mediator.skipped["bad-payload-size"] == 2)
        _step_until(mediator, lambda: mediator.images.info().puts == 3)
        forwarded = [
            e.timestamp_ns for e in answered(lambda: node.query("mediator/images"), "images")
        ]
        assert forwarded == good
        reasons = [
            e.metadata for e in answered(lambda: node.query("mediator/decisions"), "decisions")
        ]
        assert sum(b"bad-payload-size" in m for m in reasons) == 2
    finally:
        mediator.close()


def detector_load(images: Producer) -> Load:
    return tightest_load(images.subscriptions())[0]


def test_the_detector_load_carries_when_the_producer_saw_the_last_take(
    nodes: tuple[Node, Node],
) -> None:
    producer_node, consumer_node = nodes
    images = producer_node.offer("images", retention=Retention(max_count=4))
    with consumer_node.subscribe("camera/images", queue_size=2, wait_s=5.0) as sub:
        assert images.wait_for_subscribers(1, timeout_s=scaled(10.0))
        images.put(1, b"x", make_metadata("generic", 1))
        assert detector_load(images).taken_ns is None
        before = time.monotonic_ns()
        assert sub.take(timeout_s=scaled(10.0)) is not None
        wait_until(lambda: detector_load(images).taken_ns is not None, 10, "the take's ack")
        load = detector_load(images)
        assert load.queued == 0
        assert load.taken_ns is not None and before <= load.taken_ns <= time.monotonic_ns()
