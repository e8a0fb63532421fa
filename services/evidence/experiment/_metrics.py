"""Scoring a run against the simulator's ground truth."""

from __future__ import annotations

import math
from collections.abc import Sequence

from services.lib.sim import FrameTruth

from ._config import MARKER_NAMES
from ._records import FrameDetections, RunRecord


def recognized_frames(
    detections: Sequence[FrameDetections], truth: Sequence[FrameTruth]
) -> dict[str, list[int]]:
    """Per marker, the processed frames in which it was decoded near its true position.

    Near means within half its size plus its blur of the true centre, as in the simulator's
    recognition report, so a false decode elsewhere in the frame does not count.
    """
    found: dict[str, list[int]] = {name: [] for name in MARKER_NAMES}
    for frame in detections:
        if not 0 <= frame.frame_id < len(truth):
            continue
        frame_truth = truth[frame.frame_id]
        for marker in frame_truth.markers:
            if marker.name not in found:
                continue
            tolerance = marker.size_px / 2 + marker.blur_px
            if any(
                marker_id == marker.marker_id and math.dist((x, y), marker.centre_px) <= tolerance
                for marker_id, x, y in frame.markers
            ):
                found[marker.name].append(frame.frame_id)
    return found


def recognized_counts(record: RunRecord, truth: Sequence[FrameTruth]) -> dict[str, int]:
    """How many frames of one run recognized each marker."""
    return {name: len(ids) for name, ids in recognized_frames(record.detections, truth).items()}


def blur_pairs(record: RunRecord, truth: Sequence[FrameTruth]) -> tuple[list[float], list[float]]:
    """(mediator's estimated blur, true blur at the image centre) for every frame it rated."""
    estimated, true = [], []
    for decision in record.decisions:
        if decision.blur_px is None or not math.isfinite(decision.blur_px):
            continue
        if 0 <= decision.frame_id < len(truth):
            estimated.append(decision.blur_px)
            true.append(truth[decision.frame_id].centre_blur_px)
    return estimated, true
