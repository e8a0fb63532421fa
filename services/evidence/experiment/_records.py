"""What one run of the pipeline leaves behind, as plain records."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from middleware import field_text, validate_metadata
from services.lib.messages import DecisionRecord

from ._config import RunKind

_NS = "{urn:framegate:1}"


@dataclass(frozen=True, slots=True)
class FrameDetections:
    """What the detector found in one frame it processed.

    ``markers``: (marker id, centre x px, centre y px) of every decoded marker;
    ``taken_ns``: when the detector took the frame up (the frames' clock; None if it did not
    say).
    """

    frame_id: int
    processing_ns: int
    markers: tuple[tuple[int, float, float], ...]
    taken_ns: int | None = None

    @classmethod
    def from_metadata(cls, metadata: bytes) -> FrameDetections:
        """Read ``detections`` metadata (schemas/detections.xsd)."""
        root = validate_metadata(metadata, "detections")
        markers = []
        for element in root.iter(_NS + "marker"):
            marker_id = int(element.findtext(_NS + "id") or -1)
            corners = [float(v) for v in (element.findtext(_NS + "corners_px") or "").split()]
            xs, ys = corners[0::2], corners[1::2]
            markers.append((marker_id, sum(xs) / len(xs), sum(ys) / len(ys)))
        taken = field_text(root, "taken_ns")
        return cls(
            frame_id=int(field_text(root, "frame_id") or 0),
            processing_ns=int(field_text(root, "processing_ns") or 0),
            markers=tuple(markers),
            taken_ns=int(taken) if taken else None,
        )


@dataclass(frozen=True, slots=True)
class RunRecord:
    """One configuration run through the service processes, collected before they stopped.

    ``stored``/``dropped`` are camera/images puts and flow-control refusals; ``skipped_late``
    frames the camera neither stored nor refused (it fell a frame period behind, e.g. under
    CPU load). ``forwarded`` is mediator/images puts (None without a mediator).
    ``decisions`` holds the final decision per frame, ``first_decisions`` the first (written
    when the mediator first decided the frame: its decision latency). ``attempts`` and
    ``startup_s``: how many starts it took and the start-up time that worked; ``drained``
    False when the detector stopped making progress before it had processed all it was
    given (collected anyway). ``cpu_s`` is CPU time per service process; ``load_avg`` the
    1-minute load average before and after the run; ``cpu_busy_pct`` the machine's CPU use
    over the run.
    """

    kind: RunKind
    seed: int
    frame_count: int
    stored: int
    dropped: int
    skipped_late: int
    forwarded: int | None
    detections: tuple[FrameDetections, ...]
    decisions: tuple[DecisionRecord, ...]
    first_decisions: tuple[DecisionRecord, ...]
    gyro_batches: int
    gyro_dropped: int
    wall_s: float
    attempts: int
    startup_s: float
    drained: bool
    load_avg: tuple[float, float]
    cpu_busy_pct: float
    cpu_s: dict[str, float]

    @property
    def processed_ids(self) -> list[int]:
        """Frame ids the detector processed, in order."""
        return sorted(d.frame_id for d in self.detections)

    def summary(self) -> dict[str, Any]:
        """Counters and timing for results.json (without per-frame lists)."""
        processing = sorted(d.processing_ns / 1e6 for d in self.detections)
        latency = sorted(d.latency_ns / 1e6 for d in self.decisions)
        reasons: dict[str, int] = {}
        for decision in self.decisions:
            reasons[decision.reason] = reasons.get(decision.reason, 0) + 1
        return {
            "frames": self.frame_count,
            "stored": self.stored,
            "dropped_at_camera": self.dropped,
            "skipped_late": self.skipped_late,
            "forwarded": self.forwarded,
            "processed": len(self.detections),
            "accepted": sum(d.accepted for d in self.decisions) if self.decisions else None,
            "decision_reasons": reasons,
            "processing_ms": _spread(processing),
            "decision_latency_ms": _spread(latency),
            "gyro_batches": self.gyro_batches,
            "gyro_dropped": self.gyro_dropped,
            "wall_s": round(self.wall_s, 2),
            "attempts": self.attempts,
            "startup_s": self.startup_s,
            "drained": self.drained,
            "load_avg_1min": [round(v, 2) for v in self.load_avg],
            "cpu_busy_pct": round(self.cpu_busy_pct, 1),
            "cpu_s": {k: round(v, 2) for k, v in self.cpu_s.items()},
        }


def _spread(sorted_values: list[float]) -> dict[str, float] | None:
    if not sorted_values:
        return None
    n = len(sorted_values)
    return {
        "mean": round(sum(sorted_values) / n, 2),
        "p50": round(sorted_values[n // 2], 2),
        "p95": round(sorted_values[min(n - 1, int(0.95 * n))], 2),
        "max": round(sorted_values[-1], 2),
    }
