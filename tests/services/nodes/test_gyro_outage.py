"""A stopped gyro never throttles the camera: the mediator decides uncovered frames by its
gyro-missing rule without waiting for each, so its queue from the camera keeps draining.

Real processes (``framegate launch`` of the whole pipeline on a private port); the camera's
own counters (``info``) are compared between a window with the gyro alive and one with it
stopped, in the same run: shares, never absolute times.
"""

from __future__ import annotations

import os
import signal
from collections.abc import Iterator
from pathlib import Path

import pytest

from middleware import FramegateError
from services.launch import pipeline_yaml
from services.lib.messages import DecisionRecord
from tests.conftest import wait_until
from tests.helpers.timing import answered, scaled
from tests.services.nodes.pipeline import Pipeline

pytestmark = [pytest.mark.integration, pytest.mark.slow]

# Frames the camera offers (stored + refused) per measured window: a few seconds at 15 fps.
WINDOW_FRAMES = 45


@pytest.fixture
def pipe(tmp_path: Path) -> Iterator[Pipeline]:
    # A long wait for coverage: waited per frame, it would let the mediator take at most
    # 2.5 frames/s of the camera's 15, whatever the machine's speed.
    overrides = {"camera": {"seed": 3}, "gyro": {"seed": 3}, "mediator": {"gyro_wait_ms": 400}}
    pipeline = Pipeline(tmp_path, pipeline_yaml(overrides))
    yield pipeline
    pipeline.close()


def _counts(pipe: Pipeline) -> tuple[int, int] | None:
    """Frames the camera offered and those refused; None while it does not answer (a busy
    machine can leave a live camera without its lease for a while: one look, for polling)."""
    try:
        info = pipe.info("camera/images")
    except FramegateError:
        return None
    return info.puts + info.refused, info.refused


def _silence(pipe: Pipeline) -> str:
    """What is live and what the launcher said, for a wait that timed out."""
    try:
        live = ", ".join(pipe.node.live_services(timeout_s=scaled(5))) or "none"
    except FramegateError as exc:
        live = str(exc)
    return f"(live services: {live})\n" + pipe.log()


def _refused_share(pipe: Pipeline) -> float:
    """The share of the next ``WINDOW_FRAMES`` frames the camera made that flow control
    refused (the mediator's queue from the camera was full)."""
    offered0, refused0 = wait_until(
        lambda: _counts(pipe), 120, lambda: "the camera's counters " + _silence(pipe)
    )
    # One wait, whose every look may find the camera silent: its deadline is the only one.
    offered1, refused1 = wait_until(
        lambda: (c := _counts(pipe)) is not None and c[0] >= offered0 + WINDOW_FRAMES and c,
        120,
        lambda: f"{WINDOW_FRAMES} frames from the camera " + _silence(pipe),
    )
    return (refused1 - refused0) / (offered1 - offered0)


def _uncovered_decisions(pipe: Pipeline) -> list[str]:
    """The reasons of the latest decisions made without a quality: by the gyro-missing rule,
    whether the frame was uncovered (``gyro-missing-*``) or could not be paired because the
    stopped gyro's clock went unmeasured (``clock-*``; on a loaded machine the window outlasts
    the last clock sample)."""
    found = answered(
        lambda: pipe.node.query("mediator/decisions", last=30, timeout_s=scaled(10)),
        "mediator/decisions",
    )
    records = [DecisionRecord.from_metadata(e.metadata) for e in found]
    return [r.reason for r in records if r.quality is None]


def test_a_stopped_gyro_does_not_make_the_camera_drop_frames(pipe: Pipeline) -> None:
    wait_until(
        lambda: pipe.counter("detector/detections") >= 5,
        120,
        lambda: "the pipeline to run\n" + pipe.log(),
    )
    alive = _refused_share(pipe)
    gyro = pipe.pid("gyro")
    assert gyro is not None
    os.kill(gyro, signal.SIGSTOP)
    try:
        # The outage is noticed: frames are decided by the gyro-missing rule.
        wait_until(lambda: len(_uncovered_decisions(pipe)) >= 5, 60, "gyro-missing decisions")
        stopped = _refused_share(pipe)
        uncovered = _uncovered_decisions(pipe)
        assert len(uncovered) >= 5, uncovered  # still out during the window
    finally:
        os.kill(gyro, signal.SIGCONT)
    print(f"camera frames refused: {alive:.0%} with the gyro alive, {stopped:.0%} stopped")
    # Waiting 400 ms for each frame took at most 2.5 of the camera's 15 frames/s: most
    # refused. Without the waits the share is that of the gyro alive.
    assert stopped <= alive + 0.15, (alive, stopped)
