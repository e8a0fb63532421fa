"""``idle``: what a node costs when nothing happens.

Two framegate processes at rest: a *producer* node offering ``IDLE_BUFFERS`` buffers, and a
*client* node that offers ``CLIENT_BUFFERS`` buffers of its own and holds subscriptions to
the producer's (flow-controlled and observing), so both sides of every registration are
alive. Their raw-Zenoh counterparts hold as many publishers (plus a liveliness token) and
subscribers. All four processes sit idle together; each pair measures the CPU (user +
system, % of one core) of every process over the same ``IDLE_WINDOW_S`` window, once every
subscription is registered and a settling second has passed. Goal: each framegate node
<= ``IDLE_GOAL_PCT`` % of a core.
"""

from __future__ import annotations

import os
import time
from typing import Any

from ._options import BenchOptions
from ._procs import BenchError, Worker, WorkerGroup, free_endpoint
from ._records import SIDES, Goal, Row, ScenarioResult

IDLE_BUFFERS = 3
CLIENT_BUFFERS = 2
# 10 s: the CPU-time counter's tick (10 ms) is then 0.1 % of a core, below the goal; over
# 5 s one tick more or less (0.2 %) decided it.
IDLE_WINDOW_S = 10.0
IDLE_SETTLE_S = 1.0
IDLE_GOAL_PCT = 0.3
# The client's subscriptions to the producer's buffers: (buffer index, mode).
SUBSCRIPTIONS = ((0, "flow"), (1, "flow"), (1, "observe"), (2, "observe"))

ROLES = ("producer", "client")


def worker_params() -> dict[str, dict[str, dict[str, Any]]]:
    """The four idle processes' parameters, endpoints left out: side -> role -> params."""
    buffers = [f"idle{i}" for i in range(IDLE_BUFFERS)]
    return {
        "raw": {
            "producer": {"publishers": IDLE_BUFFERS},
            "client": {"subscribers": len(SUBSCRIPTIONS), "publishers": CLIENT_BUFFERS},
        },
        "framegate": {
            "producer": {"service": "bench", "offers": buffers},
            "client": {
                "service": "benchclient",
                "offers": [f"own{i}" for i in range(CLIENT_BUFFERS)],
                "subscribe": [
                    {"target": f"bench/{buffers[i]}", "mode": mode} for i, mode in SUBSCRIPTIONS
                ],
            },
        },
    }


def start_idle(group: WorkerGroup) -> dict[str, dict[str, Worker]]:
    """Start the four idle processes (raw and framegate, producer and client) and wait until
    every one is ready (the framegate client's subscriptions are registered)."""
    params = worker_params()
    workers: dict[str, dict[str, Worker]] = {}
    for side, role_name in (("raw", "raw-idle"), ("framegate", "fg-idle")):
        at = free_endpoint()
        workers[side] = {
            "producer": group.start(role_name, {**params[side]["producer"], "listen": at}),
            "client": group.start(role_name, {**params[side]["client"], "connect": at}),
        }
    group.wait_ready()
    return workers


def measure_idle(workers: dict[str, dict[str, Worker]], window_s: float) -> dict[str, Any]:
    """CPU % of one core of every process over one ``window_s`` window: side -> role -> %."""
    if window_s <= 0:
        raise BenchError(f"idle window {window_s} s must be > 0")
    flat = [(side, role, w) for side, roles in workers.items() for role, w in roles.items()]
    for _side, _role, worker in flat:
        if worker.proc.poll() is not None:
            raise BenchError(f"{worker.role} worker exited with code {worker.proc.returncode}")
    t0 = time.monotonic()
    before = [w.cpu_s() for _s, _r, w in flat]
    time.sleep(window_s)
    after = [w.cpu_s() for _s, _r, w in flat]
    wall_s = time.monotonic() - t0
    out: dict[str, Any] = {side: {} for side in workers}
    for (side, role, _w), cpu0, cpu1 in zip(flat, before, after, strict=True):
        out[side][role] = 100.0 * (cpu1 - cpu0) / wall_s
    out["window_s"] = wall_s
    return out


def tick_resolution_pct(window_s: float) -> float | None:
    """The smallest CPU share the OS's CPU-time counter can show over ``window_s``."""
    try:
        ticks = os.sysconf("SC_CLK_TCK")
    except (AttributeError, ValueError, OSError):
        return None
    return 100.0 / ticks / window_s


def idle_rows() -> dict[str, Row]:
    note = (
        f"idle: producer node offers {IDLE_BUFFERS} buffers; client node offers "
        f"{CLIENT_BUFFERS} and holds {len(SUBSCRIPTIONS)} subscriptions to the producer's "
        "(flow and observe); raw: as many publishers/subscribers; no traffic"
    )
    return {
        "producer": Row(
            f"idle node, {IDLE_BUFFERS} buffers offered",
            "idle CPU",
            "% core",
            higher_is_better=False,
            note=note,
        ),
        "client": Row(
            f"idle node, {len(SUBSCRIPTIONS)} subs + {CLIENT_BUFFERS} buffers",
            "idle CPU",
            "% core",
            higher_is_better=False,
            note=note,
        ),
    }


def idle_goal(row: Row) -> Goal:
    return Goal(
        f"idle CPU <= {IDLE_GOAL_PCT:g} % of a core",
        IDLE_GOAL_PCT,
        False,
        row.median("framegate"),
    )


def run_idle(options: BenchOptions) -> ScenarioResult:
    window_s = max(IDLE_WINDOW_S, options.duration_s)
    rows = idle_rows()
    result = ScenarioResult(
        "idle",
        params={
            "window_s": window_s,
            "settle_s": IDLE_SETTLE_S,
            "processes": worker_params(),
            "cpu": "user+system CPU of each process over the window, % of one core",
            "resolution_pct": tick_resolution_pct(window_s),
        },
    )
    with WorkerGroup() as group:
        workers = start_idle(group)
        time.sleep(IDLE_SETTLE_S)
        for pair in range(options.pairs):
            sample = measure_idle(workers, window_s)
            for role, row in rows.items():
                for side in SIDES:
                    row.samples(side).append(
                        {"pair": pair, "value": sample[side][role], "window_s": sample["window_s"]}
                    )
            options.progress(
                f"idle pair {pair + 1}/{options.pairs}: "
                + ", ".join(
                    f"{side} {role} {sample[side][role]:.2f}%"
                    for side in ("raw", "framegate")
                    for role in ROLES
                )
            )
    for row in rows.values():
        row.goal = idle_goal(row)
        result.rows.append(row)
    return result
