"""Soak: the whole pipeline at full speed for minutes, watching memory and lost elements.

Camera and gyro (simulator), mediator and a detector with no emulated load (it takes the
next frame as soon as it is done) run as separate processes on a private loopback
rendezvous port, started like ``framegate demo``. The simulated camera produces as fast as
it can render (frames it is too late for are skipped, as a real camera would); ``rate``
speeds up the scenario clock of camera and gyro.

Measured:
- resident memory (RSS) of every service process every ``sample_s``; growth after the
  warm-up, from the mean of the first three samples to the mean of the last three
  (goal: <= 5 %);
- accepted elements lost (goal: 0), audited every ``check_s`` while everything runs:
  every camera frame older than the newest decision (or than 30 s) has a decision;
  every frame the
  mediator accepted that is still within mediator/images' retention is there and
  byte-identical (payload and metadata) to the camera's copy; nothing is in
  mediator/images that the mediator did not accept; every accepted frame older than the
  newest detection has a detection; decisions and detections stored are all queryable;
- refusals and drops, from the producers' own counters (``info``, never the logs):
  camera/images and gyro/rates refused by flow control, frames the camera skipped late,
  subscriptions refused, the mediator's decisions by reason;
- stalls (goal: none): a stage whose input keeps coming while its output stands still for
  30 s; the timeline of counters and queue fills and the services' logs go into the report.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import socket
import statistics
import subprocess
import threading
import time
from collections import Counter
from dataclasses import asdict, dataclass, field
from typing import Any

import psutil

from middleware import BufferInfo, FramegateError, NetworkConfig, Node
from services.launch import Deployment, Supervisor, free_port, pipeline, private_specs
from services.lib.messages import DecisionRecord

MIB = 2**20
# A camera frame still undecided this long after it was exposed counts as lost.
_UNDECIDED_AFTER_NS = 30_000_000_000
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


# -- lost elements -------------------------------------------------------------------------


def _digest(payload: bytes, metadata: bytes) -> bytes:
    return hashlib.sha256(len(payload).to_bytes(8, "little") + payload + metadata).digest()


# Decision reasons that explain why an accepted frame gets no detection.
EXCUSED_REASONS = frozenset({"consumer-lapsed"})


@dataclass
class Audit:
    """Accepted elements that went missing, found by querying the services as any client.

    Each check reads only what is new since the last one (cursors), so the soak client
    stays small; camera frames are remembered by digest until the mediator's copy is seen.
    """

    camera_digest: dict[int, bytes] = field(default_factory=dict)
    camera_seen: set[int] = field(default_factory=set)
    decided: dict[int, bool] = field(default_factory=dict)  # frame ts -> accepted
    reasons: Counter[str] = field(default_factory=Counter)
    in_mediator: set[int] = field(default_factory=set)
    detected: set[int] = field(default_factory=set)
    # Frames with a recorded reason why no detection will come (the detector's
    # subscription lapsed while they waited): accepted, not lost.
    excused: set[int] = field(default_factory=set)
    compared: int = 0
    lost: dict[str, set[int]] = field(
        default_factory=lambda: {
            "frames_without_decision": set(),
            "accepted_not_in_mediator": set(),
            "accepted_not_identical": set(),
            "mediator_not_accepted": set(),
            "accepted_without_detection": set(),
        }
    )
    checks: int = 0
    _cursor: dict[str, int] = field(default_factory=dict)

    def _new(self, node: Node, target: str, key: str | None = None) -> list[Any]:
        start = self._cursor.get(key or target, 0)
        found = node.query(target, time_range=f"[{start}..]", timeout_s=20.0)
        if found:
            self._cursor[key or target] = found[-1].timestamp_ns + 1
        return found

    def check(self, node: Node, now_ns: int | None = None) -> None:
        """One pass; the order of the queries is what makes the conclusions safe.

        ``now_ns``: the wall clock (frame timestamps are wall-clock exposure starts).
        """
        for frame in self._new(node, "camera/images"):
            self.camera_seen.add(frame.timestamp_ns)
            self.camera_digest[frame.timestamp_ns] = _digest(frame.payload, frame.metadata)
        accepted_frames = self._new(node, "mediator/images")
        # After the query: whatever is at least as new as this was still held during it.
        oldest = node.buffer_info("mediator/images").oldest_ns or 0
        for element in self._new(node, "mediator/decisions"):
            record = DecisionRecord.from_metadata(element.metadata)
            ts = record.frame_timestamp_ns
            self.decided[ts] = self.decided.get(ts, False) or record.accepted
            self.reasons[record.reason] += 1
            if record.reason in EXCUSED_REASONS:
                self.excused.add(ts)
        for element in self._new(node, "detector/detections"):
            self.detected.add(element.timestamp_ns)
        self.checks += 1
        oldest_decided = min(self.decided, default=0)
        newest_decided = max(self.decided, default=0)
        overdue = (time.time_ns() if now_ns is None else now_ns) - _UNDECIDED_AFTER_NS
        # The mediator decides in camera order, so a frame after its first decision (earlier
        # ones were stored before it subscribed) was lost if a newer frame was decided, or
        # if it is still undecided long after: a stalled mediator loses every frame.
        undecided = self.lost["frames_without_decision"]
        undecided.difference_update(self.decided)
        for ts in self.camera_seen:
            if ts < oldest_decided or ts in self.decided:
                continue
            if ts <= newest_decided or ts < overdue:
                undecided.add(ts)
        for element in accepted_frames:
            ts = element.timestamp_ns
            self.in_mediator.add(ts)
            if ts <= newest_decided and not self.decided.get(ts, False):
                self.lost["mediator_not_accepted"].add(ts)
            copy = self.camera_digest.get(ts)
            if copy is not None:
                self.compared += 1
                if copy != _digest(element.payload, element.metadata):
                    self.lost["accepted_not_identical"].add(ts)
        if accepted_frames:
            newest = accepted_frames[-1].timestamp_ns
            for ts, accepted in self.decided.items():
                if accepted and oldest <= ts <= newest and ts not in self.in_mediator:
                    self.lost["accepted_not_in_mediator"].add(ts)
        newest_detected = max(self.detected, default=0)
        for ts, accepted in self.decided.items():
            done = ts in self.detected or ts in self.excused
            if accepted and ts <= newest_detected and not done:
                self.lost["accepted_without_detection"].add(ts)
        # Frames the mediator has seen need no digest any more.
        horizon = min(newest_decided, self._cursor.get("mediator/images", 0))
        for ts in [t for t in self.camera_digest if t < horizon]:
            del self.camera_digest[ts]

    def summary(self) -> dict[str, Any]:
        accepted = sum(1 for a in self.decided.values() if a)
        return {
            "checks": self.checks,
            "camera_frames_seen": len(self.camera_seen),
            "frames_decided": len(self.decided),
            "accepted": accepted,
            "accepted_seen_in_mediator": len(self.in_mediator),
            "compared_with_camera": self.compared,
            "detected": len(self.detected),
            "accepted_with_reason": sum(1 for t in self.excused if self.decided.get(t)),
            "decision_reasons": dict(self.reasons.most_common()),
            "lost": {name: len(found) for name, found in self.lost.items()},
            "lost_examples": {name: sorted(found)[:5] for name, found in self.lost.items()},
        }


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


def format_report(report: dict[str, Any]) -> str:
    """The report as a plain-text table."""
    cfg = report["config"]
    lines = [
        f"soak: {report['duration_s']} s, scenario rate {cfg['rate']}x, "
        f"{report['host']['cpus']} CPUs (load {report['host']['loadavg_before'][0]} before, "
        f"{report['host']['loadavg_after'][0]} after), port {cfg['port']}",
        f"memory counts after a warm-up of {report['warmup_s']:.0f} s "
        + (
            f"(image buffers full of retained frames at {report['retention_filled_at_s']:.0f} s)"
            if report["retention_filled_at_s"] is not None
            else "(image buffers still filling: growth includes filling them)"
        ),
        "",
        f"{'process':<10} {'pid':>7} {'RSS after warm-up':>18} {'RSS at end':>11} "
        f"{'peak':>9} {'growth':>8} {'MiB/min':>8}  goal <= {cfg['growth_goal']:.0%}",
    ]
    for name, p in report["processes"].items():
        if p.get("growth") is None:
            lines.append(f"{name:<10} {p.get('pid') or '-':>7}  too few samples after warm-up")
            continue
        lines.append(
            f"{name:<10} {p['pid']:>7} {p['rss_after_warmup_mib']:>14.1f} MiB "
            f"{p['rss_end_mib']:>7.1f} MiB {p['rss_peak_mib']:>5.1f} MiB "
            f"{p['growth']:>+7.1%} {p['slope_mib_per_min']:>+8.2f}  {'ok' if p['ok'] else 'MISSED'}"
        )
    el, audit = report["elements"], report["audit"]
    cam, gyro = el.get("camera/images", {}), el.get("gyro/rates", {})
    med, det = el.get("mediator/images", {}), el.get("detector/detections", {})
    reasons = ", ".join(f"{k} {v}" for k, v in audit["decision_reasons"].items()) or "-"
    lines += [
        "",
        "elements",
        f"  camera/images      {cam.get('puts')} stored ({cam.get('per_s')}/s), "
        f"{cam.get('refused')} refused by flow control, "
        f"{cam.get('skipped', {}).get('late', 0)} skipped late",
        f"  gyro/rates         {gyro.get('puts')} stored ({gyro.get('per_s')}/s), "
        f"{gyro.get('refused')} refused (dropped after waiting for credit)",
        f"  mediator           {audit['frames_decided']} frames decided: {reasons}",
        f"  mediator/images    {med.get('puts')} stored, {med.get('refused')} refused "
        "(detector's queue full)",
        f"  detector           {det.get('puts')} detections ({det.get('per_s')}/s); "
        f"{audit.get('accepted_with_reason', 0)} accepted frames with a recorded reason "
        "for no detection (consumer-lapsed)",
        "",
        f"lost (goal 0), {audit['checks']} audits while running",
    ]
    labels = {
        "frames_without_decision": "camera frames without a decision "
        f"(of {audit['camera_frames_seen']} seen)",
        "accepted_not_in_mediator": "accepted frames missing from mediator/images "
        f"(of {audit['accepted']})",
        "accepted_not_identical": "accepted frames not byte-identical "
        f"(of {audit['compared_with_camera']} compared)",
        "mediator_not_accepted": "frames in mediator/images never accepted",
        "accepted_without_detection": "accepted frames without a detection "
        f"(of {audit['detected']} detected)",
    }
    for key, label in labels.items():
        lines.append(f"  {label:<62} {audit['lost'][key]}")
    for name, count in report["unqueryable"].items():
        lines.append(f"  {'stored in ' + name + ' but not queryable':<62} {count}")
    lines.append(f"  {'total':<62} {report['lost_total']}")
    restarts = {k: v for k, v in report["restarts"].items() if v}
    goals = report["goals"]
    refusals = ", ".join(
        f"{name} {counts['refused_subscriptions']}"
        for name, counts in el.items()
        if counts.get("refused_subscriptions")
    )
    stalls = ", ".join(
        f"{x['stage']} {x['from_s']:.0f}-{x['to_s']:.0f} s ({x['input_meanwhile']} inputs)"
        for x in report["stalls"]
    )
    lines += [
        "",
        f"restarts: {restarts or 'none'}",
        f"stalls: {stalls or 'none'}",
        f"subscriptions refused by producers: {refusals or 'none'}",
        "goals: "
        + ", ".join(
            f"{name} {'ok' if goals[key] else 'MISSED'}"
            for name, key in (
                ("memory", "memory_ok"),
                ("lost", "lost_ok"),
                ("restarts", "no_restarts"),
                ("stalls", "no_stalls"),
            )
        ),
    ]
    if report["stall_stacks"]:
        lines.append("stacks of every process at the first stall: see stall_stacks in --json")
    if report["check_errors"]:
        lines.append(f"audit errors: {len(report['check_errors'])} ({report['check_errors'][0]})")
    return "\n".join(lines)
