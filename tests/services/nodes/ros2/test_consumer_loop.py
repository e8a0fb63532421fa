"""A ROS 2 vision node in framegate's loop, in real processes: a framegate producer (this
test, standing in for the mediator), the ``ros2`` bridge with ``--consumer-done``, a Zenoh
router standing in for ``rmw_zenohd`` (this test) and a plain-Zenoh ROS 2 vision node
(``services.evidence.bench._ros2_node``) that answers with the image's header after a service
time, or never. The producer's view of the bridge's flow-controlled subscription is the
load a mediator would use."""

from __future__ import annotations

import json
import queue
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import zenoh

from middleware import (
    FlowControlRefused,
    FramegateError,
    NetworkConfig,
    Node,
    Producer,
    SubscriptionMode,
)
from services.lib.messages import DecisionRecord, frame_metadata_of
from services.lib.quality import Exposure
from tests.conftest import REPO, child_env, free_port, wait_until
from tests.helpers.timing import answered, scaled

pytestmark = [pytest.mark.integration]

W, H = 16, 8
RESULT_TYPE = "my_msgs/msg/Done"
RESULT_HASH = "RIHS01_" + "cd" * 32


class Proc:
    """A child process whose JSON lines are collected and whose other lines are kept."""

    def __init__(self, argv: list[str]) -> None:
        self.proc = subprocess.Popen(
            argv,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            cwd=REPO,
            env=child_env(),
        )
        self.events: queue.Queue[dict[str, Any]] = queue.Queue()
        self.text: list[str] = []
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.text.append(line)
            if line.startswith("{"):
                self.events.put(json.loads(line))

    def log(self) -> str:
        return "".join(self.text[-40:])

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=scaled(10))
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


class VisionNode(Proc):
    """The ROS 2 vision node stand-in; counts what it received and answered."""

    def __init__(self, ros_at: str, **params: Any) -> None:
        params = {
            "connect": ros_at,
            "image_topic": "/vision/in",
            "result_topic": "/vision/out",
            "result_type": RESULT_TYPE,
            "result_hash": RESULT_HASH,
            **params,
        }
        super().__init__(
            [sys.executable, "-m", "services.evidence.bench._ros2_node", json.dumps(params)]
        )
        self.received: list[int] = []
        self.answered: list[int] = []

    def poll(self) -> None:
        while True:
            try:
                event = self.events.get_nowait()
            except queue.Empty:
                return
            if "received" in event:
                self.received.append(int(event["received"]))
            elif "answered" in event:
                self.answered.append(int(event["answered"]))

    @property
    def images(self) -> int:
        """Images received so far (answered or not)."""
        self.poll()
        return len(self.received)

    @property
    def outstanding(self) -> int:
        self.poll()
        return len(self.received) - len(self.answered)


@pytest.fixture
def ros_router() -> Iterator[tuple[str, zenoh.Session]]:
    at = f"tcp/127.0.0.1:{free_port()}"
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([at]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as router:
        yield at, router


def _bridge(endpoint: str, ros_at: str, timeout_ms: int, queue: int = 2) -> Proc:
    return Proc(
        [
            *(sys.executable, "-m", "services.cli", "run", "ros2", "--connect", endpoint),
            *("--ros-connect", ros_at, "--image-out", "cam/images=/vision/in"),
            *("--consumer-done", "/vision/out", "--consumer-queue", str(queue)),
            *("--consumer-timeout-ms", str(timeout_ms)),
        ]
    )


def _gate(images: Producer) -> Any:
    flow = [s for s in images.subscriptions() if s.mode is SubscriptionMode.FLOW]
    return flow[0] if len(flow) == 1 else None


def _put(images: Producer, stamp_ns: int) -> None:
    pixels = (np.arange(W * H) % 251).astype(np.uint8).tobytes()
    images.put(
        stamp_ns, pixels, frame_metadata_of(1, Exposure(stamp_ns, 1_000_000), "mono8", W, H, None)
    )


def _ready(images: Producer, bridge: Proc, vision: VisionNode) -> None:
    assert vision.events.get(timeout=scaled(60)).get("ready"), vision.log()
    wait_until(
        lambda: len(images.subscriptions()) == 2 and _gate(images) is not None,
        60,
        lambda: "the bridge's feed and gate subscriptions\n" + bridge.log(),
    )
    wait_until(
        lambda: any("consumer results on /vision/out" in line for line in bridge.text),
        60,
        lambda: "the bridge to learn the result type\n" + bridge.log(),
    )


@pytest.mark.slow
def test_the_load_follows_the_nodes_outstanding_images_and_its_type_is_learnt(
    listen_net: NetworkConfig, endpoint: str, ros_router: tuple[str, zenoh.Session]
) -> None:
    ros_at, router = ros_router
    with Node("cam", listen_net) as node:
        images = node.offer("images", kind="frame")
        bridge = _bridge(endpoint, ros_at, 60_000)
        # Each state below lasts one service time: long enough that a test process starved
        # for seconds on a loaded machine still looks while it holds.
        vision = VisionNode(ros_at, service_time_s=scaled(5.0))
        try:
            _ready(images, bridge, vision)
            line = next(t for t in bridge.text if "consumer results on /vision/out" in t)
            assert f"first announced: {RESULT_TYPE}, {RESULT_HASH}" in line
            # The bridge's subscription to the results carries the type it learnt. Its token
            # reaches the router some time after the bridge declared it (and logged the line
            # above): looked at until it shows.
            learnt = "/MS/%/%/framegate_bridge/%vision%out/my_msgs::msg::dds_::Done_/" + RESULT_HASH
            tokens: list[str] = []

            def subscribed() -> bool:
                replies = router.liveliness().get("@ros2_lv/0/**")
                tokens[:] = [str(r.ok.key_expr) for r in replies if r.ok]
                return any(learnt in t for t in tokens)

            wait_until(subscribed, 30, lambda: f"the bridge's typed results token in {tokens}")
            gate = _gate(images)
            assert (gate.queue_size, gate.queued, gate.node) == (2, 0, "ros2")

            now = time.time_ns()
            _put(images, now)
            _put(images, now + 1_000_000)
            # Two images the node has not answered fill its queue: the third is refused.
            with pytest.raises(FlowControlRefused):
                _put(images, now + 2_000_000)

            def matches(outstanding: int) -> bool:
                gate = _gate(images)  # None while a lapsed bridge registers again
                pair = (vision.outstanding, gate.queued if gate is not None else None)
                return pair == (outstanding, outstanding) and len(vision.received) == 2

            # As the node answers one image after the other (5 s each), its queue empties
            # with it.
            wait_until(lambda: matches(2), 60, "both images at the node, unanswered")
            wait_until(lambda: matches(1), 60, "one image answered, one outstanding")
            wait_until(lambda: matches(0), 60, "both answered")
            assert vision.answered == [now, now + 1_000_000]
            _put(images, now + 3_000_000)  # room again

            results = wait_until(
                lambda: answered(lambda: node.query("ros2/results"), "ros2/results") or None,
                30,
                "results",
            )
            assert [r.timestamp_ns for r in results][:2] == [now, now + 1_000_000]
            assert b"<answer_ns>" in results[0].metadata
            info = answered(
                lambda: node.buffer_info("ros2/results", timeout_s=scaled(10.0)), "ros2/results"
            )
            assert not info.skipped, info.skipped
        finally:
            vision.close()
            bridge.close()
        assert bridge.proc.returncode == 0, bridge.log()


@pytest.mark.slow
def test_each_answer_frees_its_slot_at_once_in_a_queue_of_four(
    listen_net: NetworkConfig, endpoint: str, ros_router: tuple[str, zenoh.Session]
) -> None:
    # A queue of 4 coalesced its acks (one per 2 takes): after an answer the mediator saw
    # the node holding 4 images, not 3, until the next answer a whole service time later.
    ros_at, _router = ros_router
    with Node("cam", listen_net) as node:
        images = node.offer("images", kind="frame")
        bridge = _bridge(endpoint, ros_at, 60_000, queue=4)
        vision = VisionNode(ros_at, service_time_s=scaled(5.0))
        try:
            _ready(images, bridge, vision)
            now = time.time_ns()
            for i in range(4):
                _put(images, now + i * 1_000_000)

            def matches(outstanding: int) -> bool:
                gate = _gate(images)
                pair = (vision.outstanding, gate.queued if gate is not None else None)
                return pair == (outstanding, outstanding) and len(vision.received) == 4

            wait_until(lambda: matches(4), 60, "four images at the node, unanswered")
            wait_until(lambda: matches(3), 60, "one answered, its slot free at the producer")
            wait_until(lambda: matches(2), 60, "two answered")
        finally:
            vision.close()
            bridge.close()
        assert bridge.proc.returncode == 0, bridge.log()


@pytest.mark.slow
def test_a_node_that_never_answers_frees_its_slots_after_the_timeout_counted(
    listen_net: NetworkConfig, endpoint: str, ros_router: tuple[str, zenoh.Session]
) -> None:
    ros_at, _router = ros_router
    with Node("cam", listen_net) as node:
        images = node.offer("images", kind="frame")
        bridge = _bridge(endpoint, ros_at, 1500)
        vision = VisionNode(ros_at, answer=False)
        try:
            _ready(images, bridge, vision)
            now = time.time_ns()
            _put(images, now)
            _put(images, now + 1_000_000)
            with pytest.raises(FlowControlRefused):
                _put(images, now + 2_000_000)
            wait_until(lambda: vision.outstanding == 2, 90, "both images at the node")
            wait_until(
                lambda: (gate := _gate(images)) is not None and gate.queued == 0,
                60,
                lambda: "the slots freed\n" + bridge.log(),
            )
            info = answered(
                lambda: node.buffer_info("ros2/results", timeout_s=scaled(10.0)), "ros2/results"
            )
            assert info.skipped == {"consumer-timeout": 2}
            assert info.puts == 0
            assert vision.answered == []
            _put(images, now + 3_000_000)  # the freed slots take images again
        finally:
            vision.close()
            bridge.close()
        assert bridge.proc.returncode == 0, bridge.log()


@pytest.mark.slow
def test_the_mediator_decides_with_the_ros2_nodes_load(
    listen_net: NetworkConfig, endpoint: str, ros_router: tuple[str, zenoh.Session]
) -> None:
    # No gyro: every frame falls under the gyro-missing rule, forwarded only while the
    # consumer is idle, so each decision shows the load the mediator read.
    ros_at, _router = ros_router
    with Node("cam", listen_net) as node:
        camera = node.offer("images", kind="frame")
        mediator = Proc(
            [
                *(sys.executable, "-m", "services.cli", "run", "mediator", "--connect", endpoint),
                *("--camera", "cam/images", "--gyro", "gyro/rates", "--gyro-wait-ms", "10"),
            ]
        )
        bridge = Proc(
            [
                *(sys.executable, "-m", "services.cli", "run", "ros2", "--connect", endpoint),
                *("--ros-connect", ros_at, "--image-out", "mediator/images=/vision/in"),
                *("--consumer-done", "/vision/out", "--consumer-queue", "2"),
                *("--consumer-timeout-ms", "60000"),
            ]
        )
        vision = VisionNode(ros_at, service_time_s=5.0)
        try:
            assert vision.events.get(timeout=scaled(60)).get("ready"), vision.log()
            wait_until(
                lambda: _flow_queued(node) == 0 and camera.subscriptions(),
                60,
                "the mediator and the bridge's gate\n" + mediator.log() + bridge.log(),
            )
            wait_until(
                lambda: any("consumer results on /vision/out" in t for t in bridge.text),
                60,
                "the result type\n" + bridge.log(),
            )
            now = time.time_ns()
            _put(camera, now)  # idle node: forwarded
            wait_until(lambda: vision.images == 1, 60, "the image at the node")
            wait_until(lambda: _flow_queued(node) == 1, 30, "the mediator to see it")
            _put(camera, now + 1_000_000)  # the node works on one: not idle, left out
            first = wait_until(lambda: _decisions(node, 2), 30, "two decisions")
            wait_until(lambda: vision.outstanding == 0, 60, "the node's answer")
            wait_until(lambda: _flow_queued(node) == 0, 30, "the slot freed")
            _put(camera, now + 2_000_000)  # idle again: forwarded
            decisions = wait_until(lambda: _decisions(node, 3), 30, "three decisions")
            assert first == decisions[:2]
            assert [(d.accepted, d.load) for d in decisions] == [
                (True, 0.0),
                (False, 0.5),
                (True, 0.0),
            ], decisions
            # Received, whether or not its 5 s of work are over when this test looks.
            wait_until(lambda: vision.images == 2, 60, "the third image")
            assert vision.received == [now, now + 2_000_000]
        finally:
            vision.close()
            bridge.close()
            mediator.close()


def _flow_queued(node: Node) -> int | None:
    """The queue of the one flow-controlled subscriber of mediator/images, as its producer
    counts it (what ``framegate info`` shows and the mediator reads), else None."""
    try:
        info = node.buffer_info("mediator/images", timeout_s=2.0)
    except FramegateError:
        return None
    flow = [s for s in info.subscriptions if s.mode is SubscriptionMode.FLOW]
    return flow[0].queued if len(flow) == 1 and flow[0].node == "ros2" else None


def _decisions(node: Node, count: int) -> list[DecisionRecord] | None:
    try:
        elements = node.query("mediator/decisions")
    except FramegateError:
        return None
    records = [DecisionRecord.from_metadata(e.metadata) for e in elements]
    return records if len(records) >= count else None
