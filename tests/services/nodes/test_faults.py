"""Fault injection on the running pipeline: SIGKILL each service in turn, SIGSTOP a consumer."""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from middleware import DataObject, FramegateError
from services.launch import pipeline_yaml
from tests.conftest import wait_until
from tests.services.nodes.pipeline import Pipeline

pytestmark = pytest.mark.integration

DEPLOY = pipeline_yaml({"camera": {"seed": 5}, "gyro": {"seed": 5}})

# What each service offers: a survivor's buffers must keep every accepted element intact.
BUFFERS = {
    "camera": ["camera/images"],
    "gyro": ["gyro/rates"],
    "mediator": ["mediator/images", "mediator/decisions"],
    "detector": ["detector/detections"],
}
# Whose subscriptions each producer holds, by the subscriber that may die.
SUBSCRIBED = {"mediator": ["camera/images", "gyro/rates"], "detector": ["mediator/images"]}


@pytest.fixture
def pipe(tmp_path: Path) -> Iterator[Pipeline]:
    pipeline = Pipeline(tmp_path, DEPLOY)
    yield pipeline
    pipeline.close()


def _snapshot(pipe: Pipeline, target: str) -> dict[int, DataObject]:
    try:
        return {e.timestamp_ns: e for e in pipe.node.query(target, timeout_s=5)}
    except FramegateError:
        return {}


def test_each_service_killed_in_turn_recovers_and_survivors_lose_nothing(pipe: Pipeline) -> None:
    wait_until(
        lambda: pipe.counter("detector/detections") >= 10, 60, "the pipeline to run\n" + pipe.log()
    )
    timings: dict[str, dict[str, float]] = {}
    for victim in ["detector", "mediator", "gyro", "camera"]:
        survivors = [s for s in BUFFERS if s != victim]
        pids = {s: pipe.pid(s) for s in survivors}
        before = {t: _snapshot(pipe, t) for s in survivors for t in BUFFERS[s]}
        detections_before = pipe.counter("detector/detections")
        old_pid = pipe.kill(victim)
        killed_at = time.monotonic()
        # A producer the victim subscribed to is free within about a second.
        for target in SUBSCRIBED.get(victim, []):
            wait_until(
                lambda t=target: pipe.subscriber_count(t) == 0,
                1.5,
                f"{target} to drop the dead {victim}'s subscription",
            )
        freed_s = time.monotonic() - killed_at
        wait_until(
            lambda v=victim, old=old_pid: (p := pipe.pid(v)) is not None and p != old,
            20,
            f"the supervisor to restart {victim}\n" + pipe.log(),
        )
        restarted_s = time.monotonic() - killed_at
        wait_until(
            lambda d=detections_before: pipe.counter("detector/detections") > d + 2,
            30,
            f"detections after restarting {victim}\n" + pipe.log(),
        )
        timings[victim] = {
            "freed_s": freed_s,
            "restarted_s": restarted_s,
            "detecting_again_s": time.monotonic() - killed_at,
        }
        # Survivors never crashed, and kept every accepted element byte for byte.
        for survivor in survivors:
            assert pipe.pid(survivor) == pids[survivor], f"{survivor} crashed"
            for target in BUFFERS[survivor]:
                after = _snapshot(pipe, target)
                oldest_after = min(after) if after else 0
                for timestamp, element in before[target].items():
                    if timestamp < oldest_after:
                        continue  # evicted by retention, not lost
                    assert after.get(timestamp) == element, f"{target} lost or changed {timestamp}"
    print("fault injection timings (s):", timings)


def test_stopped_subscriber_fills_its_queue_and_resumes_on_sigcont(pipe: Pipeline) -> None:
    wait_until(
        lambda: pipe.counter("detector/detections") >= 5, 60, "the pipeline to run\n" + pipe.log()
    )
    detector = pipe.pid("detector")
    assert detector is not None
    refused_before = pipe.info("mediator/images").refused
    os.kill(detector, signal.SIGSTOP)
    try:
        # Alive but stuck: its queue fills (load 1), so the mediator stops forwarding.
        wait_until(
            lambda: any(s.fill == 1.0 for s in pipe.info("mediator/images").subscriptions),
            5,
            "the stopped detector's queue to fill",
        )
        decisions = pipe.node.query("mediator/decisions", last=3)
        assert decisions
    finally:
        os.kill(detector, signal.SIGCONT)
    count = pipe.counter("detector/detections")
    wait_until(
        lambda: pipe.counter("detector/detections") > count + 2,
        30,
        "the detector to resume\n" + pipe.log(),
    )
    # The mediator refuses nothing by design: a full queue means load 1, so q > load fails first.
    assert pipe.info("mediator/images").refused == refused_before
