"""Fault injection: how fast a killed service produces again under the supervisor.

The pipeline (services/launch/_pipeline.py) runs on a private loopback port. Round after
round, each service in turn is SIGKILLed once it has produced for a while; the restart time
is from the kill to the first element the new process stores in its output buffer
(``camera/images``, ``gyro/rates``, ``mediator/decisions``, ``detector/detections``).
Goal: p95 <= 3 s per service. A benchmark, not a CI check: it takes minutes.

    python -m services.cli faults --kills 10
"""

from __future__ import annotations

import os
import signal
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from middleware import FramegateError, NetworkConfig, Node
from services.evidence.bench import BenchError
from services.launch import Supervisor, free_port, pipeline, private_specs
from services.launch._supervisor import HEALTHY_AFTER_S

# What each service stores once it works again.
OUTPUT = {
    "camera": "images",
    "gyro": "rates",
    "mediator": "decisions",
    "detector": "detections",
}
GOAL_P95_S = 3.0
_POLL_S = 0.02
_GIVE_UP_S = 60.0


@dataclass(frozen=True, slots=True)
class FaultConfig:
    """How many kills, and on which rendezvous port."""

    kills: int = 10
    port: int | None = None
    show_logs: bool = False


def _producing(node: Node, service: str, not_pid: int | None) -> int | None:
    """The service's pid once a process other than ``not_pid`` has stored an element."""
    try:
        info = node.service_info(service, timeout_s=0.5)
    except FramegateError:
        return None
    if info.pid == not_pid:
        return None
    for buffer in info.buffers:
        if buffer.buffer == OUTPUT[service] and buffer.puts > 0:
            return info.pid
    return None


def _wait(
    node: Node, service: str, not_pid: int | None, stop: threading.Event, supervisor: Supervisor
) -> int:
    deadline = time.monotonic() + _GIVE_UP_S
    while not stop.is_set():
        supervisor.poll()  # restarts the killed process
        pid = _producing(node, service, not_pid)
        if pid is not None:
            return pid
        if time.monotonic() > deadline:
            raise BenchError(
                f"{service} did not produce within {_GIVE_UP_S:.0f} s of its restart; "
                "run with --show-logs to see why"
            )
        time.sleep(_POLL_S)
    raise KeyboardInterrupt


def _rest(seconds: float, stop: threading.Event, supervisor: Supervisor) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        supervisor.poll()
        if stop.wait(0.1):
            raise KeyboardInterrupt


def run_faults(config: FaultConfig, stop: threading.Event | None = None) -> dict[str, Any]:
    """Kill each service ``config.kills`` times; restart seconds per service and summary."""
    stop = stop or threading.Event()
    port = config.port or free_port()
    network = NetworkConfig(local_port=port)
    specs = private_specs(pipeline(name="faults"), port)
    supervisor = Supervisor(specs, colour=False, quiet=not config.show_logs)
    restarts_s: dict[str, list[float]] = {name: [] for name in OUTPUT}
    with Node(network=network) as node:
        supervisor.start()
        try:
            pids = {name: _wait(node, name, None, stop, supervisor) for name in OUTPUT}
            up_since = dict.fromkeys(OUTPUT, time.monotonic())
            for _round in range(config.kills):
                for name in OUTPUT:
                    # Past the supervisor's healthy uptime, a crash restarts at once; a
                    # crash loop (shorter uptimes) backs off, which is not what we measure.
                    rest = HEALTHY_AFTER_S + 0.5 - (time.monotonic() - up_since[name])
                    _rest(rest, stop, supervisor)
                    killed_at = time.monotonic()
                    os.kill(pids[name], signal.SIGKILL)
                    pids[name] = _wait(node, name, pids[name], stop, supervisor)
                    up_since[name] = time.monotonic()
                    restarts_s[name].append(up_since[name] - killed_at)
        except KeyboardInterrupt:
            pass
        finally:
            supervisor.stop()
    return {
        "port": port,
        "kills": {name: len(v) for name, v in restarts_s.items()},
        "restart_s": {name: [round(x, 3) for x in v] for name, v in restarts_s.items()},
        "p95_s": {
            name: round(float(np.percentile(v, 95)), 3) if v else None
            for name, v in restarts_s.items()
        },
        "goal_p95_s": GOAL_P95_S,
    }


def format_faults(report: dict[str, Any]) -> str:
    """The report as a table: kills, median, p95, max and the goal per service."""
    lines = [f"{'service':<10} {'kills':>5} {'median':>8} {'p95':>8} {'max':>8}  goal p95 <= 3 s"]
    for name, times in report["restart_s"].items():
        if not times:
            lines.append(f"{name:<10} {0:>5}  not measured")
            continue
        p95 = report["p95_s"][name]
        lines.append(
            f"{name:<10} {len(times):>5} {float(np.median(times)):>7.2f}s {p95:>7.2f}s "
            f"{max(times):>7.2f}s  {'ok' if p95 <= report['goal_p95_s'] else 'MISSED'}"
        )
    return "\n".join(lines)
