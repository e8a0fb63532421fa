"""Tiny real runs of the new measurements: each handler design, the idle nodes and the
hostile peer's tokens. They check that numbers come out and the wire is right, never a
speed (the machine is shared)."""

from __future__ import annotations

import math

import pytest

from services.evidence.bench._idle import SUBSCRIPTIONS, measure_idle, start_idle
from services.evidence.bench._procs import WorkerGroup, free_endpoint
from services.evidence.bench._raw import HANDLER_DESIGNS
from services.evidence.bench._throughput import measure
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration


def test_every_handler_design_receives_and_reports_cpu_per_message() -> None:
    with WorkerGroup() as group:
        pairs = {}
        for design in HANDLER_DESIGNS:
            at = free_endpoint()
            pairs[design] = (
                group.start("raw-pub", {"listen": at, "size": 64, "shm": False}),
                group.start(
                    "raw-handler-sub", {"connect": at, "size": 64, "shm": False, "design": design}
                ),
            )
        group.wait_ready()
        for design, (producer, consumer) in pairs.items():
            # A process's CPU time is counted in clock ticks (10 ms): a consumer starved on a
            # loaded machine received its elements in 0.3 s within less than one tick and
            # read 0. A longer window then, up to 3 s; a design that never counts its CPU
            # still fails.
            for window_s in (0.3, 1.0, 3.0):
                sample = measure(producer, consumer, 0.2, window_s)
                if sample["cpu_consumer_us"] > 0:
                    break
            assert sample["count"] > 0, design
            assert sample["value"] > 0 and math.isfinite(sample["cpu_consumer_us"]), design
            assert sample["cpu_consumer_us"] > 0, design


def test_an_unknown_handler_design_fails_the_worker_with_its_name() -> None:
    from services.evidence.bench import BenchError

    with WorkerGroup() as group:
        group.start("raw-handler-sub", {"connect": free_endpoint(), "design": "carrier-pigeon"})
        with pytest.raises(BenchError, match="carrier-pigeon"):
            group.wait_ready(timeout_s=scaled(60.0))


def test_idle_nodes_register_their_subscriptions_and_report_cpu() -> None:
    with WorkerGroup() as group:
        workers = start_idle(group)
        assert workers["framegate"]["client"].ready["subscriptions"] == len(SUBSCRIPTIONS)
        sample = measure_idle(workers, 0.5)
    for side in ("raw", "framegate"):
        for role in ("producer", "client"):
            value = sample[side][role]
            assert math.isfinite(value) and value >= 0, (side, role)
    assert sample["window_s"] >= 0.5


def test_hostile_tokens_reach_the_camera_as_registrations_or_refusals() -> None:
    from middleware import NetworkConfig

    with WorkerGroup() as group:
        at = free_endpoint()
        camera = group.start(
            "fg-camera",
            {"listen": at, "size": 4096, "rate_hz": 20.0, "retain": 4, "buffer": "images"},
        )
        group.wait_ready()
        group.start(
            "raw-hostile",
            {
                "connect": at,
                "namespace": NetworkConfig().namespace,
                "service": "bench",
                "buffer": "images",
                "tokens": 3,
                "queue_size": 1 << 20,
                "listen_notify": True,
            },
        )
        group.wait_ready()
        deadline_runs = 20
        for _ in range(deadline_runs):  # until the camera has seen all three tokens
            answer = camera.call("run", 30.0, seconds=0.5)
            if answer["subscriptions"] + answer["refused_subscriptions"] >= 3:
                break
        assert answer["subscriptions"] + answer["refused_subscriptions"] == 3, answer
        assert answer["stored"] > 0 and answer["rss_max"] >= answer["rss_start"] > 0
