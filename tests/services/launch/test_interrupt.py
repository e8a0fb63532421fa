"""One Ctrl-C or SIGTERM ends any long-running framegate process within 2 s, and nothing a
supervisor started outlives it, however it ends (issue 15: one interrupt, no orphans)."""

from __future__ import annotations

import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import psutil
import pytest

from middleware import FramegateError, NetworkConfig, Node
from services.launch import pipeline_yaml
from services.nodes import SERVICES
from tests.conftest import free_port, start_framegate, wait_until
from tests.helpers.timing import LEASE_LAPSE_S, answered, scaled
from tests.services.nodes.pipeline import Pipeline

pytestmark = pytest.mark.integration

# What the default pipeline (and the demo) runs; SERVICES also lists the ROS 2 bridge.
PIPELINE = ("camera", "gyro", "mediator", "detector")

# The goal is 2 s (0.4-0.9 s measured on an idle machine; by design no wait outlasts it);
# the bound only fails a process that keeps running after the signal, on a machine ten
# times slower too (scaled by FRAMEGATE_TEST_TIMEOUT_SCALE).
STOP_WITHIN_S = scaled(20.0)
STARTUP_S = 60.0


def _gone(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


@pytest.fixture
def port() -> int:
    return free_port()


@pytest.fixture
def client(port: int) -> Iterator[Node]:
    with Node(network=NetworkConfig(local_port=port)) as node:
        yield node


def _pid_of(node: Node, service: str) -> int | None:
    try:
        return node.service_info(service, timeout_s=scaled(1.0)).pid
    except FramegateError:
        return None


def _pids(pipe: Pipeline) -> dict[str, int]:
    """Every service's pid once all four are live."""

    def live() -> dict[str, int | None] | None:
        pids = {s: pipe.pid(s) for s in PIPELINE}
        return pids if all(pids.values()) else None

    try:
        return wait_until(live, STARTUP_S, "all four services")  # type: ignore[no-any-return]
    except AssertionError as exc:
        raise AssertionError(f"{exc}\n{pipe.log()}") from None


def _stopped_in_time(proc: subprocess.Popen[str], sig: signal.Signals) -> float:
    sent = time.monotonic()
    proc.send_signal(sig)
    try:
        proc.wait(timeout=scaled(10))
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        pytest.fail(f"still running 10 s after {sig.name}")
    return time.monotonic() - sent


@pytest.mark.parametrize("service", SERVICES)
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_one_signal_stops_a_service(
    service: str, sig: signal.Signals, port: int, client: Node
) -> None:
    # camera and gyro: the simulator; the ROS 2 bridge needs a topic and a router address
    # (nobody answers there: it must stop all the same).
    # vision needs a handler to run.
    extras = {
        "ros2": [
            "--image-in",
            "/camera/image_raw",
            "--ros-connect",
            f"tcp/127.0.0.1:{free_port()}",
        ],
        "vision": ["--handler", "tests.services.nodes.vision_handlers:brightest"],
    }
    extra = extras.get(service, [])
    proc = start_framegate(["run", service, *extra], local_port=port)
    try:
        wait_until(lambda: _pid_of(client, service) == proc.pid, STARTUP_S, f"{service} up")
        took_s = _stopped_in_time(proc, sig)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    output = proc.stdout.read() if proc.stdout else ""
    assert took_s < STOP_WITHIN_S, output
    assert proc.returncode == 0, output
    assert "Traceback" not in output, output
    # A put between the stop and the service's end meets a closed buffer: that is the stop,
    # not a failure worth a warning.
    assert "is closed" not in output, output


def test_one_signal_stops_launch_and_its_services(tmp_path: Path) -> None:
    pipe = Pipeline(tmp_path, pipeline_yaml())
    try:
        pids = list(_pids(pipe).values())
        took_s = _stopped_in_time(pipe.proc, signal.SIGINT)
        assert took_s < STOP_WITHIN_S, pipe.log()
        assert all(_gone(pid) for pid in pids), pipe.log()
        assert "is closed" not in pipe.log(), pipe.log()
    finally:
        pipe.close()


def test_one_signal_stops_the_demo(port: int, client: Node) -> None:
    # A live-rendering camera: no approach to render first (the prerendered source's
    # render, interruptible too, is minutes of CPU on a cold cache).
    proc = start_framegate(["demo", "--duration", "120", "--source", "sim"], local_port=port)
    try:
        pids = [wait_until(lambda s=s: _pid_of(client, s), STARTUP_S, s) for s in PIPELINE]  # type: ignore[misc]
        took_s = _stopped_in_time(proc, signal.SIGINT)
        assert took_s < STOP_WITHIN_S
        assert all(_gone(pid) for pid in pids)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_services_end_with_a_killed_launcher_and_a_fresh_launch_starts_cleanly(
    tmp_path: Path,
) -> None:
    first = Pipeline(tmp_path, pipeline_yaml())
    try:
        old = _pids(first)
        first.proc.send_signal(signal.SIGKILL)
        first.proc.wait()
        wait_until(lambda: all(_gone(pid) for pid in old.values()), STOP_WITHIN_S, "orphans to end")
    finally:
        first.close()
    second = Pipeline(tmp_path, pipeline_yaml())
    try:
        new = _pids(second)
        assert not set(new.values()) & set(old.values())
        # One gyro answers: the last five batches are five, not ten from two gyros.
        wait_until(lambda: second.counter("gyro/rates") >= 5, 30, "gyro batches")
        last = answered(
            lambda: second.node.query("gyro/rates", last=5, timeout_s=scaled(3.0)), "gyro/rates"
        )
        assert len(last) == 5
        # Exactly one (asked again while a lapsed one is silent; two never become one).
        wait_until(
            lambda: [s.service for s in second.node.services()].count("gyro") == 1,
            LEASE_LAPSE_S,
            lambda: f"one gyro among {[s.service for s in second.node.services()]}",
        )
        assert {p.pid for p in psutil.Process(second.proc.pid).children()} == set(new.values())
    finally:
        second.close()
