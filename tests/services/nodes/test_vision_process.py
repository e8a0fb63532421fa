"""``framegate run vision`` in real processes behind a real mediator (``framegate launch``)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from middleware import SubscriptionMode
from tests.conftest import wait_until
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
    except Exception:
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
        "results and counted handler errors\n" + pipe.log(),
    )
    # The runner is the mediator's flow-controlled consumer: its queue is the load.
    subs = pipe.info("mediator/images").subscriptions
    assert [(s.node, s.mode) for s in subs] == [("vision", SubscriptionMode.FLOW)], subs
    puts, errors = pipe.counter("vision/detections"), _skipped(pipe, "vision/detections", reason)
    wait_until(
        lambda: (
            pipe.counter("vision/detections") > puts + 2
            and _skipped(pipe, "vision/detections", reason) > errors + 2
        ),
        60,
        "the runner to keep going after errors\n" + pipe.log(),
    )
    assert pipe.pid("vision") is not None
    warned = [line for line in pipe.lines if "handler raised ValueError" in line]
    assert len(warned) == 1, pipe.log()


def test_a_slower_handler_is_sent_fewer_frames_from_the_same_camera_and_gyro(
    tmp_path: Path, pipeline: list[Pipeline]
) -> None:
    # One camera and gyro; two mediators, each with its own consumer: a cheap handler and
    # one that needs 1 s per frame.
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
        "both handlers to have results\n" + pipe.log(),
    )
    fast0, slow0 = pipe.counter("mediator/images"), pipe.counter("mediator-slow/images")
    done0 = pipe.counter("vision-slow/detections")
    wait_until(
        lambda: pipe.counter("vision-slow/detections") >= done0 + 5,
        120,
        "the slow handler to process 5 more frames\n" + pipe.log(),
    )
    fast = pipe.counter("mediator/images") - fast0
    slow = pipe.counter("mediator-slow/images") - slow0
    # Over the same stretch of the same camera stream, the mediator in front of the slow
    # handler forwarded fewer frames: its acceptance follows the handler's speed.
    assert slow < fast, (slow, fast)
    decisions = pipe.info("mediator-slow/decisions").puts
    assert decisions > slow, (decisions, slow)
