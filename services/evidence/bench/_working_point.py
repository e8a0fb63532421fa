"""``working-point``: the CPU the pipeline and its middleware take at the paper's working point.

The working point: 1280×1024 mono8 frames (1.3 MB) at 30 fps and a 1 kHz gyro, through the
mediator to a detector. A replay dataset of that shape is rendered once into a temporary
directory; the four services then run from the pipeline definition (``services.launch``),
camera and gyro replaying it in a loop, as separate processes on a private loopback port.

1. **Pipeline**: over the window, each process's user+system CPU (psutil) as % of one core,
   and the element rate of each stream from the buffers' ``puts`` counters.
2. **Middleware estimate**: the same streams (size, rate, pushed as the services ask) run
   paced in bench worker processes that do nothing but move elements: framegate
   (put → take) and raw Zenoh (pub → sub) alternately, each the way the service moves it
   (the gyro: ``put_many`` of ``GYRO_BATCH`` samples, ``take_many`` on the other side; raw
   Zenoh one message per batch). A worker's CPU is then the
   middleware's cost of that stream on that side. Each service's middleware CPU is the sum
   of its streams' sides: camera = frames produced; gyro = batches produced; mediator =
   frames and batches consumed + forwarded frames produced; detector = forwarded frames
   consumed. The share is that sum over the four processes' measured CPU. It leaves out
   the small decision and detection records (no subscriber) and counts each worker's idle
   session housekeeping, so it errs high.

The goal (issue 18) is on framegate's estimated share: <= 10 % of the four processes' CPU.
The raw column is what raw Zenoh would take for the same streams (framegate - raw is
framegate's own part).
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import psutil

from middleware import FramegateError, NetworkConfig, Node
from services.launch import Supervisor, free_port, pipeline, private_specs
from services.lib.sim import ScenarioConfig, simulate
from services.nodes.detector import DetectorConfig
from services.nodes.mediator import GYRO_QUEUE, MediatorConfig

from ._options import BenchOptions
from ._procs import BenchError, WorkerGroup, free_endpoint
from ._records import Goal, Row, ScenarioResult, Side
from ._throughput import FRAME_BYTES, measure

WIDTH_PX, HEIGHT_PX = 1280, 1024
FRAME_RATE_HZ = 30.0
GYRO_RATE_HZ = 1000.0
EXPOSURE_NS = 20_000_000
FULL_FRAMES = 30  # a 1 s loop
QUICK_FRAMES = 10
SHARE_GOAL_PCT = 10.0
# The gyro service's put_many batch (``framegate run gyro --batch``, default 10).
GYRO_BATCH = 10
PROCESSES = ("camera", "gyro", "mediator", "detector")
# The queues the services subscribe with by default (the pipeline runs with defaults).
CAMERA_QUEUE = MediatorConfig().camera_queue
DETECTOR_QUEUE = DetectorConfig().queue
# Buffers whose rates the pipeline phase reads.
FRAMES, GYRO, FORWARDED = "camera/images", "gyro/rates", "mediator/images"
_START_TIMEOUT_S = 90.0


@dataclass(frozen=True, slots=True)
class Stream:
    """One stream of the pipeline as measured: buffer, element size and rate."""

    buffer: str
    size: int
    rate_hz: float
    push: bool
    # (process, "producer" | "consumer") this stream's sides are charged to.
    producer: str
    consumer: str
    # The consumer's queue, as the service subscribes (its acks depend on it).
    queue: int
    # Elements per put_many / take_many as the service moves them (0: one put each). Raw
    # Zenoh gets the same stream shape: one message per batch.
    batch: int = 0

    def as_json(self) -> dict[str, Any]:
        return {
            "buffer": self.buffer,
            "payload_bytes": self.size,
            "rate_hz": round(self.rate_hz, 2),
            "pushed": self.push,
            "producer": self.producer,
            "consumer": self.consumer,
            "batch": self.batch,
            "queue": self.queue,
        }


def run_working_point(options: BenchOptions) -> ScenarioResult:
    frames = QUICK_FRAMES if options.quick else FULL_FRAMES
    window_s = max(options.duration_s * 2, 1.0 if options.quick else 8.0)
    result = ScenarioResult(
        "working-point",
        params={
            "frame": f"{WIDTH_PX}x{HEIGHT_PX} mono8",
            "frame_rate_hz": FRAME_RATE_HZ,
            "gyro_rate_hz": GYRO_RATE_HZ,
            "loop_frames": frames,
            "pipeline_window_s": window_s,
            "estimate": "paced raw/framegate workers carrying the measured streams; "
            "see services/evidence/bench/_working_point.py",
        },
    )
    process_rows = {
        name: Row(f"{name}: process CPU", "CPU", "% of a core", False, raw=None)
        for name in PROCESSES
    }
    middleware_rows = {
        name: Row(f"{name}: middleware CPU (est.)", "CPU", "% of a core", False)
        for name in PROCESSES
    }
    share = Row("middleware share of the 4 processes (est.)", "CPU share", "%", False)
    with tempfile.TemporaryDirectory(prefix="framegate-bench-") as tmp:
        dataset = Path(tmp) / "working-point"
        began = time.monotonic()
        simulate(
            ScenarioConfig(
                width_px=WIDTH_PX,
                height_px=HEIGHT_PX,
                frame_rate_hz=FRAME_RATE_HZ,
                exposure_ns=EXPOSURE_NS,
                gyro_rate_hz=GYRO_RATE_HZ,
                frame_count=frames,
            ),
            dataset,
            progress=False,
            workers=1,
        )
        options.progress(
            f"working-point: rendered {frames} frames in {time.monotonic() - began:.0f} s"
        )
        for pair in range(options.pairs):
            cpu_pct, streams = _run_pipeline(dataset, options, window_s)
            result.params.setdefault("streams", [s.as_json() for s in streams])
            total = sum(cpu_pct.values())
            for name in PROCESSES:
                process_rows[name].framegate.append({"pair": pair, "value": cpu_pct[name]})
            estimates = _estimate(streams, options)
            for side, per_process in estimates.items():
                for name in PROCESSES:
                    middleware_rows[name].samples(side).append(
                        {"pair": pair, "value": per_process[name]}
                    )
                share.samples(side).append(
                    {
                        "pair": pair,
                        "value": 100.0 * sum(per_process.values()) / total,
                        "pipeline_cpu_pct": total,
                    }
                )
            options.progress(
                f"working-point pair {pair + 1}/{options.pairs}: "
                + ", ".join(f"{n} {cpu_pct[n]:.0f}%" for n in PROCESSES)
                + "; middleware est. "
                + ", ".join(
                    f"{side} {100.0 * sum(v.values()) / total:.1f}%"
                    for side, v in estimates.items()
                )
                + " of the total"
            )
    share.goal = Goal(
        f"framegate (with Zenoh) <= {SHARE_GOAL_PCT:g}% of the pipeline's CPU",
        SHARE_GOAL_PCT,
        False,
        share.median("framegate"),
    )
    share.note = "raw: what raw Zenoh would take for the same streams; fg-raw: framegate's own"
    result.rows = [*process_rows.values(), *middleware_rows.values(), share]
    return result


def _run_pipeline(
    dataset: Path, options: BenchOptions, window_s: float
) -> tuple[dict[str, float], list[Stream]]:
    """Run the four services; their CPU % over the window and the streams' measured rates."""
    port = free_port()
    network = NetworkConfig(local_port=port)
    replay = {"source": "replay", "path": str(dataset), "seed": None, "loop": True}
    deployment = pipeline(
        {
            "camera": replay,
            "gyro": replay,
            "detector": {"frame_period_ms": 1000.0 / FRAME_RATE_HZ},
        },
        name="working-point",
        restart=False,
    )
    specs = private_specs(deployment, port)
    logs: list[str] = []
    supervisor = Supervisor(specs, colour=False, out=logs.append, quiet=True)
    with Node(network=network) as node:
        supervisor.start()
        try:
            _wait_flowing(node, supervisor, logs)
            time.sleep(options.warmup_s * 4)  # past start-up and the first gyro backlog
            before = _snapshot(node, supervisor)
            time.sleep(window_s)
            after = _snapshot(node, supervisor)
        finally:
            supervisor.stop()
    wall_s = float(after["t"] - before["t"])
    cpu_pct = {
        name: 100.0 * (after["cpu"][name] - before["cpu"][name]) / wall_s for name in PROCESSES
    }

    def rate(buffer: str) -> float:
        return float(after["puts"][buffer] - before["puts"][buffer]) / wall_s

    gyro_bytes = int(after["bytes_each"][GYRO])
    streams = [
        Stream(FRAMES, FRAME_BYTES, rate(FRAMES), True, "camera", "mediator", CAMERA_QUEUE),
        Stream(
            GYRO, gyro_bytes, rate(GYRO), False, "gyro", "mediator", GYRO_QUEUE, batch=GYRO_BATCH
        ),
        Stream(
            FORWARDED, FRAME_BYTES, rate(FORWARDED), True, "mediator", "detector", DETECTOR_QUEUE
        ),
    ]
    return cpu_pct, streams


def _wait_flowing(node: Node, supervisor: Supervisor, logs: list[str]) -> None:
    deadline = time.monotonic() + _START_TIMEOUT_S
    while time.monotonic() < deadline:
        buffers = _buffers(node)
        if all(buffers.get(b) and buffers[b].puts > 0 for b in (FRAMES, GYRO, FORWARDED)):
            return
        if not all(_alive(pid) for pid in supervisor.pids().values()):
            break
        time.sleep(0.5)
    raise BenchError(
        "the working-point pipeline did not start moving frames within "
        f"{_START_TIMEOUT_S:.0f} s; last log lines: {' | '.join(logs[-8:])}"
    )


def _alive(pid: int | None) -> bool:
    try:
        return pid is not None and psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def _buffers(node: Node) -> dict[str, Any]:
    try:
        return {b.name: b for s in node.services(timeout_s=2.0) for b in s.buffers}
    except FramegateError:
        return {}


def _snapshot(node: Node, supervisor: Supervisor) -> dict[str, Any]:
    """CPU seconds of each process and puts of each buffer, at one moment."""
    pids = supervisor.pids()
    cpu: dict[str, float] = {}
    for name in PROCESSES:
        pid = pids.get(name)
        if pid is None:
            raise BenchError(f"working-point: the {name} process is not running")
        times = psutil.Process(pid).cpu_times()
        cpu[name] = float(times.user + times.system)
    t = time.monotonic()
    buffers = _buffers(node)
    missing = [b for b in (FRAMES, GYRO, FORWARDED) if b not in buffers]
    if missing:
        raise BenchError(f"working-point: no answer from {', '.join(missing)}")
    return {
        "t": t,
        "cpu": cpu,
        "puts": {name: info.puts for name, info in buffers.items()},
        "bytes_each": {
            name: info.payload_bytes // max(1, info.count) for name, info in buffers.items()
        },
    }


def _estimate(streams: list[Stream], options: BenchOptions) -> dict[Side, dict[str, float]]:
    """Each process's middleware CPU (% of a core) from the streams run paced, per side."""
    out: dict[Side, dict[str, float]] = {
        "raw": dict.fromkeys(PROCESSES, 0.0),
        "framegate": dict.fromkeys(PROCESSES, 0.0),
    }
    for stream in streams:
        if stream.rate_hz <= 0:
            continue
        raw_at, fg_at = free_endpoint(), free_endpoint()
        common = {"shm": True, "size": stream.size}
        per_message = max(1, stream.batch)
        raw = {"shm": True, "size": stream.size * per_message}
        with WorkerGroup() as group:
            sides = {
                "raw": (
                    group.start("raw-pub", {**raw, "listen": raw_at}),
                    group.start("raw-sub", {**raw, "connect": raw_at}),
                ),
                "framegate": (
                    group.start(
                        "fg-pub", {**common, "listen": fg_at, "buffer": "s", "batch": stream.batch}
                    ),
                    group.start(
                        "fg-sub",
                        {
                            **common,
                            "connect": fg_at,
                            "buffer": "s",
                            "queue_size": stream.queue,
                            "push": stream.push,
                            "batch": stream.batch,
                        },
                    ),
                ),
            }
            group.wait_ready()
            for side, (producer, consumer) in sides.items():
                which: Side = "raw" if side == "raw" else "framegate"
                sample = measure(
                    producer,
                    consumer,
                    options.warmup_s,
                    options.duration_s,
                    interval_s=per_message / stream.rate_hz,
                )
                out[which][stream.producer] += float(sample["cpu_producer_pct"])
                out[which][stream.consumer] += float(sample["cpu_consumer_pct"])
                options.progress(
                    f"working-point {stream.buffer} at {stream.rate_hz:.0f}/s {side}: producer "
                    f"{sample['cpu_producer_pct']:.1f}%, consumer {sample['cpu_consumer_pct']:.1f}%"
                )
    return out
