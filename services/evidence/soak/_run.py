"""Soak's run: the pipeline on a private port, memory samples, audits and stalls (see
``services.evidence.soak``)."""

from __future__ import annotations

import os
import shutil
import socket
import statistics
import subprocess
import threading
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import psutil

from middleware import BufferInfo, FramegateError, NetworkConfig, Node
from services.launch import Deployment, Supervisor, free_port, pipeline, private_specs

from ._audit import Audit

MIB = 2**20
# A stage whose input grows while its output stands still this long is stalled.
_STALL_S = 30.0
# (stage, its input buffers (stored + refused), its output buffer)
_STAGES = (
    ("mediator", "camera/images", "mediator/decisions"),
    ("detector", "mediator/images", "detector/detections"),
)
# gyro/rates keeps 30 s of batches (services/nodes/gyro.py).
_GYRO_RETENTION_S = 30.0
_PIPELINE = frozenset(
    ["camera/images", "gyro/rates", "mediator/images", "mediator/decisions", "detector/detections"]
)


@dataclass(frozen=True, slots=True)
class SoakConfig:
    """What the soak runs and how it measures."""

    duration_s: float = 600.0
    warmup_s: float | None = None  # None: a quarter of the run, at most 60 s
    sample_s: float = 5.0
    check_s: float = 10.0
    rate: float = 1.0
    seed: int = 1
    service_factor: float | None = None  # detector's emulated load; None: none at all
    growth_goal: float = 0.05
    port: int | None = None  # private rendezvous port; None: a free one
    show_logs: bool = False

    @property
    def warmup(self) -> float:
        if self.warmup_s is not None:
            return self.warmup_s
        return min(60.0, self.duration_s / 4)


def soak_deployment(config: SoakConfig) -> Deployment:
    """The pipeline (deploy/local.yaml) at the soak's rate, the detector without emulated
    load unless asked."""
    source = {"seed": config.seed, "rate": config.rate}
    return pipeline(
        {
            "camera": source,
            "gyro": source,
            "detector": {"service_factor": config.service_factor},
        },
        name="soak",
    )


# -- memory ------------------------------------------------------------------------------


@dataclass
class MemorySeries:
    """RSS samples of one service: (seconds since start, pid, bytes)."""

    samples: list[tuple[float, int, int]] = field(default_factory=list)

    def summary(self, warmup_s: float, goal: float) -> dict[str, Any]:
        pids = [pid for _t, pid, _rss in self.samples]
        last_pid = pids[-1] if pids else None
        after = [(t, rss) for t, pid, rss in self.samples if t >= warmup_s and pid == last_pid]
        out: dict[str, Any] = {"pid": last_pid, "samples": len(self.samples)}
        if len(after) < 2:
            return out | {"growth": None, "ok": None}
        k = min(3, len(after) // 2)
        start = statistics.fmean(rss for _t, rss in after[:k])
        end = statistics.fmean(rss for _t, rss in after[-k:])
        span_min = (after[-1][0] - after[0][0]) / 60
        slope = statistics.linear_regression([t for t, _ in after], [r for _, r in after]).slope
        growth = (end - start) / start
        return out | {
            "rss_after_warmup_mib": round(start / MIB, 1),
            "rss_end_mib": round(end / MIB, 1),
            "rss_peak_mib": round(max(rss for _t, _pid, rss in self.samples) / MIB, 1),
            "growth": round(growth, 4),
            "slope_mib_per_min": round(slope * 60 / MIB, 3),
            "measured_min": round(span_min, 1),
            "ok": growth <= goal,
        }


def rss_bytes(pid: int | None) -> int | None:
    """Resident memory of a process, None if it is gone."""
    if pid is None:
        return None
    try:
        return int(psutil.Process(pid).memory_info().rss)
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        return None


# -- the run -------------------------------------------------------------------------------


def _full(buffers: dict[str, BufferInfo]) -> bool:
    """True once the count-limited image buffers hold as many elements as they keep."""
    for name in ("camera/images", "mediator/images"):
        info = buffers[name]
        if info.retention.max_count is not None and info.count < info.retention.max_count:
            return False
    return True


def _progress(elapsed_s: float, buffers: dict[str, BufferInfo]) -> dict[str, Any]:
    """One timeline point: stored/refused per buffer, queued/size per subscription."""
    return {
        "t": round(elapsed_s, 1),
        "buffers": {n: [b.puts, b.refused] for n, b in buffers.items()},
        "queued": {
            n: [f"{s.mode.value} {s.queued}/{s.queue_size}" for s in b.subscriptions]
            for n, b in buffers.items()
            if b.subscriptions
        },
    }


def find_stalls(timeline: list[dict[str, Any]], stall_s: float = _STALL_S) -> list[dict[str, Any]]:
    """Intervals in which a stage's input kept arriving but its output did not grow."""
    stalls: list[dict[str, Any]] = []
    for stage, source, output in _STAGES:
        since: tuple[float, int, int] | None = None  # (t, input, output) at last output change
        current: dict[str, Any] | None = None
        for point in timeline:
            counts = point["buffers"]
            if source not in counts or output not in counts:
                continue
            seen, done = sum(counts[source]), counts[output][0]
            if since is None or done != since[2]:
                since, current = (point["t"], seen, done), None
                continue
            if seen > since[1] and point["t"] - since[0] >= stall_s:
                if current is None:
                    current = {"stage": stage, "from_s": since[0], "to_s": point["t"]}
                    stalls.append(current)
                current["to_s"] = point["t"]
                current["input_meanwhile"] = seen - since[1]
    return stalls


def dump_stacks(pids: dict[str, int | None]) -> dict[str, str]:
    """Every thread's Python stack of each process (py-spy), to see where a stall sits."""
    spy = shutil.which("py-spy")
    if spy is None:
        return {"note": "install py-spy to get the stacks of stalled processes"}
    out = {}
    for name, pid in pids.items():
        if pid is None:
            continue
        try:
            done = subprocess.run(
                [spy, "dump", "--pid", str(pid)], capture_output=True, text=True, timeout=60
            )
            out[name] = done.stdout + done.stderr
        except (OSError, subprocess.TimeoutExpired) as exc:
            out[name] = f"py-spy failed: {exc}"
    return out


def _buffers(node: Node) -> dict[str, BufferInfo]:
    try:
        return {b.name: b for s in node.services(timeout_s=2.0) for b in s.buffers}
    except FramegateError:
        return {}


def _elements(buffers: dict[str, BufferInfo], elapsed_s: float) -> dict[str, Any]:
    """The producers' own counters per buffer (``info``): stored, refused, rejected, kept,
    skipped by reason (the camera's ``late``), subscriptions refused."""

    def counters(info: BufferInfo) -> dict[str, Any]:
        return {
            "puts": info.puts,
            "refused": info.refused,
            "rejected": info.rejected,
            "count": info.count,
            "skipped": dict(info.skipped),
            "refused_subscriptions": info.refused_subscriptions,
            "per_s": round(info.puts / elapsed_s, 2) if elapsed_s > 0 else 0.0,
        }

    return {name: counters(buffers[name]) for name in sorted(buffers)}


def run_soak(config: SoakConfig, stop: threading.Event | None = None) -> dict[str, Any]:
    """Run the pipeline for ``duration_s``; return the report (JSON-ready; the CLI prints it)."""
    port = config.port or free_port()
    network = NetworkConfig(local_port=port)
    specs = private_specs(soak_deployment(config), port)
    logs: list[str] = []

    def keep(line: str) -> None:
        logs.append(line)
        if config.show_logs:
            print(line, flush=True)

    supervisor = Supervisor(specs, colour=False, out=keep)
    memory = {spec.name: MemorySeries() for spec in specs}
    audit = Audit()
    started = time.monotonic()
    due = {"sample": 0.0, "check": config.warmup / 2}
    buffers: dict[str, BufferInfo] = {}
    # Memory grows until the count-limited image buffers hold their retention: the warm-up
    # lasts at least until then (at a slow frame rate that is longer than warmup_s).
    filled_at: float | None = None
    load_before = os.getloadavg()
    check_errors: list[str] = []
    timeline: list[dict[str, Any]] = []
    stall_stacks: dict[str, str] = {}  # at the first stall, where every process is
    with Node(network=network) as node:
        supervisor.start()

        def tick() -> None:
            nonlocal buffers, filled_at
            elapsed = time.monotonic() - started
            if elapsed >= due["sample"]:
                due["sample"] += config.sample_s
                for name, pid in supervisor.pids().items():
                    rss = rss_bytes(pid)
                    if pid is not None and rss is not None:
                        memory[name].samples.append((round(elapsed, 2), pid, rss))
            if elapsed >= due["check"]:
                due["check"] = elapsed + config.check_s
                buffers = _buffers(node) or buffers
                timeline.append(_progress(elapsed, buffers))
                if not set(buffers) >= _PIPELINE:
                    return  # not everything is up yet
                if filled_at is None and elapsed >= _GYRO_RETENTION_S and _full(buffers):
                    filled_at = elapsed
                try:
                    audit.check(node)
                except FramegateError as exc:
                    # A service that is restarting: the next check catches up.
                    check_errors.append(f"{elapsed:.0f}s: {exc}")
                if not stall_stacks and find_stalls(timeline):
                    stall_stacks.update(dump_stacks(supervisor.pids()))

        try:
            # stop() also waits for the services' last log lines (camera/gyro totals).
            supervisor.run(config.duration_s, on_tick=tick, stop=stop)
        except KeyboardInterrupt:
            supervisor.stop()
        elapsed = time.monotonic() - started
    audit_summary = audit.summary()
    unqueryable = {
        name: max(0, (info.puts - info.count))
        for name, info in buffers.items()
        if name in ("mediator/decisions", "detector/detections")
        and info.retention.max_count is not None
        and info.puts <= info.retention.max_count
    }
    warmup = max(config.warmup, filled_at) if filled_at is not None else config.warmup
    processes = {
        name: series.summary(warmup, config.growth_goal) for name, series in memory.items()
    }
    lost_total = sum(audit_summary["lost"].values()) + sum(unqueryable.values())
    restarts = supervisor.restarts()
    memory_ok = all(p.get("ok") is not False for p in processes.values())
    stalls = find_stalls(timeline)
    return {
        "config": asdict(config) | {"port": port, "warmup_s": config.warmup},
        "warmup_s": round(warmup, 1),
        "retention_filled_at_s": None if filled_at is None else round(filled_at, 1),
        "host": {
            "cpus": os.cpu_count(),
            "hostname": socket.gethostname(),
            "loadavg_before": [round(x, 2) for x in load_before],
            "loadavg_after": [round(x, 2) for x in os.getloadavg()],
        },
        "duration_s": round(elapsed, 1),
        "processes": processes,
        "memory_samples": {name: s.samples for name, s in memory.items()},
        "elements": _elements(buffers, elapsed),
        "audit": audit_summary,
        "unqueryable": unqueryable,
        "lost_total": lost_total,
        "restarts": restarts,
        "stalls": stalls,
        "stall_stacks": stall_stacks,
        "check_errors": check_errors,
        "goals": {
            "memory_growth_at_most": config.growth_goal,
            "memory_ok": memory_ok,
            "lost_ok": lost_total == 0,
            "no_restarts": not any(restarts.values()),
            "no_stalls": not stalls,
        },
        "timeline": timeline,
        "logs": logs[-5000:],
    }
