"""``framegate run vision`` in real processes behind a real mediator (``framegate launch``)."""

from __future__ import annotations

import contextlib
import json
import logging
import signal
import threading
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import zenoh

from middleware import (
    DataObject,
    FramegateError,
    NetworkConfig,
    Node,
    Notification,
    SubscriptionMode,
    field_text,
    now_ns,
    validate_metadata,
)
from middleware._wire import Keys
from services.lib.messages import frame_metadata
from services.lib.quality import Exposure
from services.lib.vision import ResultKind
from services.nodes.vision import Runner, RunnerSpec, VisionStep
from tests.conftest import free_port, start_framegate, wait_until
from tests.helpers.raw_zenoh import open_session
from tests.helpers.timing import answered, scaled
from tests.services.nodes import vision_handlers
from tests.services.nodes.pipeline import Pipeline

pytestmark = pytest.mark.integration

HANDLERS = "tests.services.nodes.vision_handlers"
SENSORS = """\
version: 1
services:
  camera: {args: {source: sim, seed: 3, loop: true}}
  gyro: {args: {source: sim, seed: 3, loop: true}}
  mediator: {args: {policy: paper, b0: 5.0}}
"""


@pytest.fixture
def pipeline(tmp_path: Path) -> Iterator[list[Pipeline]]:
    started: list[Pipeline] = []
    yield started
    for pipe in started:
        pipe.close()


def _skipped(pipe: Pipeline, target: str, reason: str) -> int:
    try:
        return int(pipe.info(target).skipped.get(reason, 0))
    except FramegateError:
        return 0


def test_a_handler_named_on_the_command_line_runs_behind_the_mediator_and_its_errors_are_counted(
    tmp_path: Path, pipeline: list[Pipeline]
) -> None:
    # Odd frame ids raise ValueError: half the frames fail, the pipeline must keep going.
    deploy = SENSORS + f"  vision: {{args: {{handler: '{HANDLERS}:odd_frames_raise'}}}}\n"
    pipe = Pipeline(tmp_path, deploy)
    pipeline.append(pipe)
    reason = "handler-error:ValueError"
    wait_until(
        lambda: (
            pipe.counter("vision/detections") >= 3
            and _skipped(pipe, "vision/detections", reason) >= 3
        ),
        90,
        lambda: "results and counted handler errors\n" + pipe.log(),
    )
    # The runner is the mediator's flow-controlled consumer: its queue is the load.
    subs = pipe.info("mediator/images").subscriptions
    assert [(s.node, s.mode) for s in subs] == [("vision", SubscriptionMode.FLOW)], subs
    puts, errors = pipe.count("vision/detections"), _skipped(pipe, "vision/detections", reason)
    wait_until(
        lambda: (
            pipe.counter("vision/detections") > puts + 2
            and _skipped(pipe, "vision/detections", reason) > errors + 2
        ),
        60,
        lambda: "the runner to keep going after errors\n" + pipe.log(),
    )
    assert pipe.pid("vision") is not None
    warned = [line for line in pipe.lines if "handler raised ValueError" in line]
    assert len(warned) == 1, pipe.log()


@pytest.mark.slow
def test_a_slower_handler_is_sent_fewer_frames_from_the_same_camera_and_gyro(
    tmp_path: Path, pipeline: list[Pipeline]
) -> None:
    # One camera and gyro; two mediators, each with its own consumer: a cheap handler and
    # one that needs 2.5 s per frame.
    deploy = SENSORS + (
        "  mediator-slow: {type: mediator, args: {policy: paper, b0: 5.0}}\n"
        f"  vision: {{args: {{handler: '{HANDLERS}:brightest'}}}}\n"
        f"  vision-slow: {{type: vision, args: {{handler: '{HANDLERS}:slow', "
        "input: mediator-slow/images}}\n"
    )
    pipe = Pipeline(tmp_path, deploy)
    pipeline.append(pipe)
    wait_until(
        lambda: (
            pipe.counter("vision-slow/detections") >= 3 and pipe.counter("vision/detections") >= 3
        ),
        90,
        lambda: "both handlers to have results\n" + pipe.log(),
    )
    fast0, slow0 = pipe.count("mediator/images"), pipe.count("mediator-slow/images")
    done0 = pipe.count("vision-slow/detections")
    wait_until(
        lambda: pipe.counter("vision-slow/detections") >= done0 + 3,
        120,
        lambda: "the slow handler to process 3 more frames\n" + pipe.log(),
    )
    fast = pipe.count("mediator/images") - fast0
    slow = pipe.count("mediator-slow/images") - slow0
    # Over the same stretch of the same camera stream, the mediator in front of the slow
    # handler forwarded fewer frames: its acceptance follows the handler's speed.
    assert slow < fast, (slow, fast)
    decisions = pipe.info("mediator-slow/decisions").puts
    assert decisions > slow, (decisions, slow)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_stop_ends_the_runner_with_exit_0_while_its_handler_is_busy(signum: int) -> None:
    port = free_port()
    camera = start_framegate(["run", "camera", "--seed", "3", "--loop"], local_port=port)
    vision = start_framegate(
        ["run", "vision", "--handler", f"{HANDLERS}:stuck", "--input", "camera/images"],
        local_port=port,
    )
    try:
        with Node(network=NetworkConfig(local_port=port)) as node:
            # The camera is refused once the runner's queue is full: the handler is busy.
            wait_until(
                lambda: _refused(node, "camera/images") > 0, 90, "the runner's queue to fill"
            )
        sent = time.monotonic()
        vision.send_signal(signum)
        out, _ = vision.communicate(timeout=scaled(60))
        took_s = time.monotonic() - sent
        assert vision.returncode == 0, out
        # Far less than the handler's 600 s: the stop did not wait for it.
        assert took_s < scaled(60), took_s
    finally:
        for proc in (vision, camera):
            if proc.poll() is None:
                proc.kill()
                proc.communicate()


def _refused(node: Node, target: str) -> int:
    try:
        return node.buffer_info(target, timeout_s=2.0).refused
    except FramegateError:
        return 0


class _Rig:
    """A vision runner (``vision/detections``) behind this test's own ``src/images``, fed
    by hand: frame ``i`` is stamped ``base_ns + i * step_ns`` and stored by ``src`` when it
    is newer than what ``src`` holds."""

    def __init__(self, src: Node, node: Node, base_ns: int, step_ns: int) -> None:
        self.images = src.offer("images", kind="frame")
        self.output = node.offer("detections", kind="detections")
        spec = RunnerSpec("vision", "src/images", 2, "detections", ResultKind.DETECTIONS)
        log = logging.getLogger("test.vision.rewind")
        step = VisionStep(vision_handlers.brightest, ResultKind.DETECTIONS, "src/images", log)
        self.runner = Runner(spec, step, node, self.output, threading.Event())
        self.node, self.base_ns, self.step_ns = node, base_ns, step_ns

    def note(self, frame_id: int, *, store: bool = True) -> Notification:
        image = np.full((8, 8), frame_id, np.uint8)
        stamp = self.base_ns + frame_id * self.step_ns
        meta = frame_metadata(frame_id, Exposure(stamp, 1_000_000), image, None)
        element = DataObject(stamp, image.tobytes(), meta)
        newest = self.images.series.newest_ns
        if store and (newest is None or stamp > newest):
            self.images.put(stamp, element.payload, meta)
        return Notification("src", "images", stamp, frame_id, meta, element)

    def handle(self, frame_id: int, *, store: bool = True, missed: int = 0) -> None:
        note = replace(self.note(frame_id, store=store), missed=missed)
        self.runner.handle([note], lambda n: n.element)  # type: ignore[arg-type,return-value]

    def results(self) -> list[int]:
        """The frame numbers of the results stored."""
        found = self.node.query("vision/detections")
        return [(e.timestamp_ns - self.base_ns) // self.step_ns for e in found]


def test_results_are_removed_only_by_a_rewind_the_input_producer_recorded() -> None:
    net = NetworkConfig(local_port=free_port())
    with Node("src", net) as src_node, Node("vision", net) as node:
        # 0.1 s apart: a producer rewinds at most its horizon (10 s) back.
        rig = _Rig(src_node, node, now_ns() - 3_600 * 10**9, 10**8)
        for frame_id in (10, 20, 30):
            rig.handle(frame_id)
        assert rig.results() == [10, 20, 30]
        # One stale element while its producer still holds newer ones: skipped, nothing gone.
        rig.handle(15)
        assert rig.results() == [10, 20, 30]
        assert rig.output.info().skipped == {"out-of-order": 1}
        # The producer went back (it removed its frames after 12, as a mediator does after a
        # camera restarted with its clock behind): our results after the new frame follow.
        rig.images.discard_after(rig.base_ns + 12 * rig.step_ns, "rewound")
        rig.handle(16)
        assert rig.results() == [10, 16]
        assert rig.output.info().skipped == {"out-of-order": 1, "rewound": 2}
        # A peer's forged notification (the producer never stored it) stamped ahead of the
        # producer, then a stale one: the producer's newest is older than our newest result,
        # but it recorded no rewind of it, so nothing is removed.
        rig.handle(90, store=False)
        rig.handle(17)
        assert rig.results() == [10, 16, 90]
        assert rig.output.info().skipped == {"out-of-order": 2, "rewound": 2}


def test_frames_an_observing_runner_never_saw_are_counted() -> None:
    """An observer's full queue drops its oldest frames (keep-last): the next notification
    carries how many, and the runner counts them ``not-observed``."""
    net = NetworkConfig(local_port=free_port())
    with Node("src", net) as src_node, Node("vision", net) as node:
        rig = _Rig(src_node, node, now_ns() - 10**9, 10**6)
        rig.handle(1)
        rig.handle(5, missed=3)
        assert rig.results() == [1, 5]
        assert rig.output.info().skipped == {"not-observed": 3}


def test_a_rewind_a_second_session_reports_in_the_inputs_name_removes_nothing() -> None:
    """A peer answers the input's ``@info`` too, with the real description plus a rewind
    that would cover every result: the description two sessions give decides nothing, so a
    stale element is skipped and every result stays."""
    port = free_port()
    net = NetworkConfig(local_port=port)
    with (
        Node("src", net) as src_node,
        Node("vision", net) as node,
        open_session(f"tcp/127.0.0.1:{port}") as rogue,
    ):
        rig = _Rig(src_node, node, now_ns() - 10**9, 10**6)
        for frame_id in (10, 20, 30):
            rig.handle(frame_id)
        keys = Keys("framegate")
        real = json.loads(
            next(r.ok.payload.to_bytes() for r in rogue.get(keys.info("src")) if r.ok)
        )
        for buffer in real["buffers"]:
            buffer["rewinds"] = [
                {"after_ns": 0, "count": 1, "first_ns": 1, "last_ns": 2**63 - 1, "cause": "x"}
            ]
        forged = json.dumps(real).encode()

        def answer(query: zenoh.Query) -> None:
            with query:  # stamped: Zenoh prefers the newest of two answers
                query.reply(query.key_expr, forged, timestamp=rogue.new_timestamp())

        queryable = rogue.declare_queryable(keys.info("src"), zenoh.handlers.Callback(answer))
        try:

            def both_answer() -> bool:
                try:
                    node.service_info("src", unambiguous=True, timeout_s=scaled(2))
                except FramegateError:
                    return True
                return False

            wait_until(both_answer, scaled(30), "the forger's answers to reach the runner")
            rig.handle(15)
        finally:
            queryable.undeclare()
        assert rig.results() == [10, 20, 30]
        assert rig.output.info().skipped == {"out-of-order": 1}
        assert rig.output.info().rewinds == ()


@contextlib.contextmanager
def _camera_and_vision(handler: str) -> Iterator[Node]:
    """A simulated camera and ``run vision --handler HANDLERS:handler`` on it, in processes
    of their own; a node on their rendezvous port. Both are stopped by SIGTERM after."""
    port = free_port()
    camera = start_framegate(["run", "camera", "--seed", "3", "--loop"], local_port=port)
    vision = start_framegate(
        ["run", "vision", "--handler", f"{HANDLERS}:{handler}", "--input", "camera/images"],
        local_port=port,
    )
    try:
        with Node(network=NetworkConfig(local_port=port)) as node:
            yield node
    finally:
        for proc in (vision, camera):
            proc.send_signal(signal.SIGTERM)
            proc.communicate(timeout=scaled(30))


def test_a_handler_returning_output_fills_a_generic_results_buffer() -> None:
    with _camera_and_vision("histogram") as node:
        elements = wait_until(
            lambda: _elements(node, "vision/results"), 90, "the handler's results"
        )
        results = answered(lambda: node.buffer_info("vision/results"), "vision/results")
        assert results.kind == "generic"
        element = elements[-1]
        assert len(element.payload) == 16 * 4  # the histogram
        assert b"<mean>" in element.metadata and b"<frame_id>" in element.metadata
        frame = answered(lambda: node.get("camera/images", element.timestamp_ns), "the frame")
        assert frame.timestamp_ns == element.timestamp_ns


def test_a_handler_class_is_created_and_called_on_one_thread() -> None:
    """Every call on the thread the class was created on: per-thread state (a model or
    connection bound to its thread, a thread-local cache) carries from frame to frame. Each
    call used to run on a new thread, the class made on the main thread."""
    with _camera_and_vision("ThreadBound") as node:
        elements = wait_until(
            lambda: _elements(node, "vision/results")[2:],
            90,
            "three of the handler's results",
        )
        fields = [
            (field_text(root, "created_here"), int(field_text(root, "calls_here") or 0))
            for root in (validate_metadata(e.metadata, "generic") for e in elements)
        ]
        assert all(created == "true" for created, _calls in fields), fields
        assert fields[-1][1] >= 3, fields


def _elements(node: Node, target: str) -> list[DataObject]:
    try:
        return node.query(target)
    except FramegateError:
        return []


def test_a_misspelt_input_is_said_once_with_what_the_service_offers() -> None:
    """``--input src/image`` while ``src`` offers ``images``: the runner waits (the buffer
    may still come), but says so once, with a did-you-mean, instead of waiting in silence."""
    port = free_port()
    with Node("src", NetworkConfig(local_port=port)) as src:
        src.offer("images", kind="frame")
        vision = start_framegate(
            ["run", "vision", "--handler", f"{HANDLERS}:brightest", "--input", "src/image"],
            local_port=port,
        )
        try:
            assert vision.stdout is not None
            said = ""
            deadline = time.monotonic() + scaled(60)
            while "still waiting" not in said and time.monotonic() < deadline:
                said = vision.stdout.readline()
                assert said, "the runner ended"
            assert "still waiting for src/image: service 'src' has no buffer 'image'" in said
            assert "(did you mean 'images'?)" in said
        finally:
            vision.send_signal(signal.SIGTERM)
            vision.communicate(timeout=scaled(30))
    assert vision.returncode == 0


def _not_observed(node: Node, target: str) -> int:
    try:
        return int(node.buffer_info(target, timeout_s=2.0).skipped.get("not-observed", 0))
    except FramegateError:
        return 0


def test_frames_an_observer_loses_while_its_handler_is_stuck_are_counted_meanwhile() -> None:
    """The frames its full queue drops are counted while the handler runs, not only when it
    takes its next frame (a handler that never returned showed no count at all)."""
    port = free_port()
    camera = start_framegate(["run", "camera", "--seed", "3", "--loop"], local_port=port)
    vision = start_framegate(
        ["run", "vision", "--handler", f"{HANDLERS}:stuck", "--input", "camera/images",
         "--observe"],
        local_port=port,
    )  # fmt: skip
    try:
        with Node(network=NetworkConfig(local_port=port)) as node:
            wait_until(
                lambda: _not_observed(node, "vision/detections") > 0,
                90,
                "frames the stuck runner never saw to be counted",
            )
            counted = _not_observed(node, "vision/detections")
            wait_until(
                lambda: _not_observed(node, "vision/detections") > counted,
                90,
                "the count to go on rising while the handler is still stuck",
            )
            assert node.buffer_info("vision/detections", timeout_s=5.0).puts == 0
    finally:
        for proc in (vision, camera):
            if proc.poll() is None:
                proc.kill()
                proc.communicate()


def test_garbage_on_the_runner_s_notification_key_is_counted_and_results_go_on() -> None:
    """A peer publishing garbage on the key the runner's notifications come on: each is
    counted ``bad-notification`` in the output's info (it was counted nowhere visible), and
    the runner keeps storing results."""
    with _camera_and_vision("brightest") as node:
        wait_until(lambda: _elements(node, "vision/detections"), 90, "the first results")
        images = answered(lambda: node.buffer_info("camera/images"), "camera/images")
        (sub,) = [s for s in images.subscriptions if s.node == "vision"]
        key = Keys("framegate").notify("camera", "images", sub.subscription_id)
        port = node.network.local_port
        with open_session(f"tcp/127.0.0.1:{port}") as rogue:

            def counted() -> bool:
                # Sent until counted: a new session's first puts may go before it has
                # learnt of the runner's subscriber, and reach no one.
                for _ in range(20):
                    rogue.put(key, b"\xff" * 32, attachment=b"not a notification")
                info = node.buffer_info("vision/detections", timeout_s=scaled(5))
                return info.skipped.get("bad-notification", 0) >= 20

            wait_until(counted, scaled(30), "the garbage counted in vision/detections")
        before = len(_elements(node, "vision/detections"))
        wait_until(
            lambda: len(_elements(node, "vision/detections")) > before, 60, "results after it"
        )
