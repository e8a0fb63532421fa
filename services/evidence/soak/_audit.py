"""Soak's audit of lost elements: accepted frames, decisions and detections checked by
querying the services as any client (see ``services.evidence.soak``)."""

from __future__ import annotations

import hashlib
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from middleware import Node
from services.lib.messages import DecisionRecord

# A camera frame still undecided this long after it was exposed counts as lost.
_UNDECIDED_AFTER_NS = 30_000_000_000


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

    def _new(self, node: Node, target: str, moved: dict[str, int]) -> list[Any]:
        """What ``target`` holds since the last pass; its cursor moves in ``moved`` only."""
        start = self._cursor.get(target, 0)
        found = node.query(target, time_range=f"[{start}..]", timeout_s=20.0)
        if found:
            moved[target] = found[-1].timestamp_ns + 1
        return found

    def check(self, node: Node, now_ns: int | None = None) -> None:
        """One pass; the order of the queries is what makes the conclusions safe.

        ``now_ns``: the wall clock (frame timestamps are wall-clock exposure starts).
        A pass whose query fails (a service restarting, or one that lost its lease on a
        loaded machine) changes nothing: its cursors move only once every query was
        answered, so the next pass reads all of it again.
        """
        moved: dict[str, int] = {}
        camera_frames = self._new(node, "camera/images", moved)
        accepted_frames = self._new(node, "mediator/images", moved)
        # After the query: whatever is at least as new as this was still held during it.
        oldest = node.buffer_info("mediator/images").oldest_ns or 0
        decisions = self._new(node, "mediator/decisions", moved)
        detections = self._new(node, "detector/detections", moved)
        self._cursor.update(moved)
        for frame in camera_frames:
            self.camera_seen.add(frame.timestamp_ns)
            self.camera_digest[frame.timestamp_ns] = _digest(frame.payload, frame.metadata)
        for element in decisions:
            record = DecisionRecord.from_metadata(element.metadata)
            ts = record.frame_timestamp_ns
            self.decided[ts] = self.decided.get(ts, False) or record.accepted
            self.reasons[record.reason] += 1
            if record.reason in EXCUSED_REASONS:
                self.excused.add(ts)
        for element in detections:
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
