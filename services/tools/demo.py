"""``framegate demo``: the simulator-fed pipeline on this host, with a live status view.

Four processes — camera and gyro rendering the simulated bumpy approach live, the mediator,
and a detector emulating a computer 1.6x too slow for the frame rate — meet through the
loopback rendezvous (no router, no configuration). This process only watches, through the
same public API any client uses.
"""

from __future__ import annotations

import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from middleware import BufferInfo, FramegateError, NetworkConfig, Node
from services.launch import Deployment, Supervisor, pipeline, process_specs
from services.lib.markers import BOARD_MARKERS
from services.lib.messages import read_detections


@dataclass(frozen=True, slots=True)
class DemoConfig:
    """What the demo runs."""

    duration_s: float = 30.0
    seed: int = 1
    policy: str = "paper"
    b0_px: float = 5.0
    queue: int = 2
    service_factor: float = 1.6
    show_logs: bool = False


def demo_deployment(config: DemoConfig) -> Deployment:
    """The pipeline (deploy/local.yaml) with the demo's settings."""
    return pipeline(
        {
            "camera": {"seed": config.seed},
            "gyro": {"seed": config.seed},
            "mediator": {"policy": config.policy, "b0": config.b0_px},
            "detector": {"queue": config.queue, "service_factor": config.service_factor},
        },
        name="demo",
    )


@dataclass
class Status:
    """What the status view shows, read from the services' own buffer descriptions."""

    buffers: dict[str, BufferInfo] = field(default_factory=dict)

    def get(self, name: str) -> BufferInfo | None:
        return self.buffers.get(name)

    def counts(self) -> dict[str, Any]:
        cam, gyro = self.get("camera/images"), self.get("gyro/rates")
        out, dec = self.get("mediator/images"), self.get("mediator/decisions")
        det = self.get("detector/detections")
        load = max((s.fill for s in out.subscriptions), default=0.0) if out else 0.0
        return {
            "frames": cam.puts if cam else 0,
            "dropped_at_camera": cam.refused if cam else 0,
            "camera_hz": cam.rate_hz if cam else 0.0,
            "gyro_batches": gyro.puts if gyro else 0,
            "decisions": dec.puts if dec else 0,
            "accepted": out.puts if out else 0,
            "load": load,
            "detections": det.puts if det else 0,
            "detections_hz": det.rate_hz if det else 0.0,
        }


def read_status(node: Node) -> Status:
    status = Status()
    try:
        for service in node.services(timeout_s=1.0):
            for buffer in service.buffers:
                status.buffers[buffer.name] = buffer
    except FramegateError:
        pass
    return status


def _line(counts: dict[str, Any], elapsed_s: float) -> str:
    rejected = max(0, counts["decisions"] - counts["accepted"])
    return (
        f"{elapsed_s:5.1f}s  camera {counts['frames']:4d} frames ({counts['camera_hz']:4.1f}/s, "
        f"{counts['dropped_at_camera']} dropped)  gyro {counts['gyro_batches']:5d} batches  "
        f"mediator {counts['accepted']:4d} accepted / {rejected:4d} rejected, "
        f"load {counts['load']:.2f}  detector {counts['detections']:4d} "
        f"({counts['detections_hz']:4.1f}/s)"
    )


class MarkerTally:
    """Counts, per board marker, the processed frames that recognized it (read as we go)."""

    def __init__(self) -> None:
        self._names = {m.marker_id: m.name for m in BOARD_MARKERS}
        self._after_ns = 0
        self.seen: Counter[str] = Counter()

    def update(self, node: Node) -> None:
        try:
            elements = node.query("detector/detections", time_range=f"[{self._after_ns + 1}..]")
        except FramegateError:
            return
        for element in elements:
            _frame, ids = read_detections(element.metadata)
            for marker_id in set(ids):
                self.seen[self._names.get(marker_id, str(marker_id))] += 1
            self._after_ns = max(self._after_ns, element.timestamp_ns)


def run_demo(
    config: DemoConfig, network: NetworkConfig, stop: threading.Event | None = None
) -> dict[str, Any]:
    """Run the pipeline for ``duration_s`` (or until ``stop``) with a status line per second;
    return a summary."""
    specs = process_specs(demo_deployment(config), None, network)
    supervisor = Supervisor(specs, quiet=not config.show_logs)
    started = time.monotonic()
    last_print = 0.0
    counts: dict[str, Any] = {}
    tally = MarkerTally()
    with Node(network=network) as node:
        supervisor.start()

        def tick() -> None:
            nonlocal last_print, counts
            now = time.monotonic()
            if now - last_print < 1.0:
                return
            last_print = now
            counts = read_status(node).counts()
            tally.update(node)
            print(_line(counts, now - started), flush=True)

        try:
            supervisor.run(config.duration_s, on_tick=tick, stop=stop)
        except KeyboardInterrupt:
            supervisor.stop()
    summary = {
        **counts,
        "rejected": max(0, counts.get("decisions", 0) - counts.get("accepted", 0)),
        "restarts": supervisor.restarts(),
        "markers_recognized": dict(tally.seen),
        "duration_s": round(time.monotonic() - started, 1),
    }
    return summary


def print_summary(summary: dict[str, Any]) -> None:
    out = sys.stdout
    out.write(
        f"\nsummary after {summary['duration_s']} s: {summary.get('frames', 0)} frames, "
        f"{summary.get('dropped_at_camera', 0)} dropped at the camera, "
        f"{summary.get('accepted', 0)} accepted and {summary['rejected']} rejected by the "
        f"mediator, {summary.get('detections', 0)} frames processed by the detector\n"
    )
    if summary["markers_recognized"]:
        seen = ", ".join(f"{k} {v}" for k, v in sorted(summary["markers_recognized"].items()))
        out.write(f"markers recognized (frames): {seen}\n")
