"""Sanity report: how often each marker is recognized, against the true blur at the marker.

The denominator is the frames where the marker is *recognizable* (decoded in a blur-free
render of the same pose), so the rate isolates what motion blur costs; the paper's Table 1
counts the same way ("images with marker recognizable").
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from services.lib.markers import BOARD_MARKERS, MarkerDetection, detect_markers

from ._dataset import Dataset, DatasetError
from ._records import FrameTruth

DEFAULT_BINS_PX = (0.0, 1.0, 2.0, 4.0, 6.0, 10.0, math.inf)
_PERCENTILES = (10, 50, 90, 100)


@dataclass(frozen=True, slots=True)
class BlurBin:
    """Frames whose true blur at the marker is in [low_px, high_px)."""

    low_px: float
    high_px: float
    recognizable: int
    recognized: int

    @property
    def rate(self) -> float | None:
        """recognized / recognizable, None for an empty bin."""
        return self.recognized / self.recognizable if self.recognizable else None

    @property
    def label(self) -> str:
        """``"4-6"`` or ``">=10"``."""
        if math.isinf(self.high_px):
            return f">={self.low_px:g}"
        return f"{self.low_px:g}-{self.high_px:g}"


@dataclass(frozen=True, slots=True)
class MarkerReport:
    """One marker over the whole sequence."""

    name: str
    in_view: int
    recognizable: int
    recognized: int
    bins: tuple[BlurBin, ...]


@dataclass(frozen=True, slots=True)
class RecognitionReport:
    """Recognition of each marker against true blur, plus the blur distribution."""

    frame_count: int
    centre_blur_percentiles_px: tuple[tuple[int, float], ...]
    markers: tuple[MarkerReport, ...]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (report.json)."""
        return {
            "frame_count": self.frame_count,
            "centre_blur_percentiles_px": {f"p{p}": v for p, v in self.centre_blur_percentiles_px},
            "markers": [
                {
                    "name": m.name,
                    "in_view": m.in_view,
                    "recognizable": m.recognizable,
                    "recognized": m.recognized,
                    "bins": [
                        {
                            "blur_px": b.label,
                            "recognizable": b.recognizable,
                            "recognized": b.recognized,
                            "rate": b.rate,
                        }
                        for b in m.bins
                    ],
                }
                for m in self.markers
            ],
        }

    def table(self) -> str:
        """A plain-text table for the terminal."""
        pct = ", ".join(f"p{p} {v:.2f}" for p, v in self.centre_blur_percentiles_px)
        lines = [
            f"true blur at the image centre over {self.frame_count} frames (px): {pct}",
            "recognition rate against true blur at the marker "
            "(recognized / recognizable in a blur-free render):",
            "blur px   " + "".join(f"{m.name:>18}" for m in self.markers),
        ]
        for i, first in enumerate(self.markers[0].bins):
            cells = []
            for m in self.markers:
                b = m.bins[i]
                rate = "   -" if b.rate is None else f"{b.rate:4.2f}"
                cells.append(f"{rate} ({b.recognized:>3}/{b.recognizable:>3})")
            lines.append(f"{first.label:<10}" + "".join(f"{c:>18}" for c in cells))
        totals = [f"{m.recognized:>3}/{m.recognizable:>3}" for m in self.markers]
        lines.append(f"{'all':<10}" + "".join(f"{t:>18}" for t in totals))
        lines.append(f"{'in view':<10}" + "".join(f"{m.in_view:>18}" for m in self.markers))
        return "\n".join(lines)


def _matches(
    detection: MarkerDetection, centre_px: tuple[float, float], tolerance_px: float
) -> bool:
    return math.dist(detection.centre_px, centre_px) <= tolerance_px


def recognition_report(
    dataset: Dataset, *, bins_px: Sequence[float] = DEFAULT_BINS_PX,
    on_frame: Callable[[int], None] | None = None,
) -> RecognitionReport:  # fmt: skip
    """Decode every frame of a dataset with ground truth and tabulate recognition vs blur.

    A decoded marker counts only near its true position (within half its size plus its
    blur), so a false decode elsewhere is not a recognition. ``on_frame`` is called after
    each frame (progress).
    """
    truth = dataset.truth
    if truth is None:
        raise DatasetError(f"dataset {dataset.root} has no truth.json; nothing to compare with")
    names = [m.name for m in BOARD_MARKERS]
    edges = list(bins_px)
    counts = {n: np.zeros((2, len(edges) - 1), dtype=int) for n in names}
    in_view = dict.fromkeys(names, 0)
    for index, frame_truth in enumerate(truth):
        detections = detect_markers(dataset.image(index))
        _tally(frame_truth, detections, edges, counts, in_view)
        if on_frame is not None:
            on_frame(index)
    blur = np.array([t.centre_blur_px for t in truth]) if truth else np.zeros(1)
    percentiles = tuple((p, float(np.percentile(blur, p))) for p in _PERCENTILES)
    markers = []
    for name in names:
        recognizable, recognized = counts[name]
        bins = tuple(
            BlurBin(edges[i], edges[i + 1], int(recognizable[i]), int(recognized[i]))
            for i in range(len(edges) - 1)
        )
        markers.append(
            MarkerReport(name, in_view[name], int(recognizable.sum()), int(recognized.sum()), bins)
        )
    return RecognitionReport(len(truth), percentiles, tuple(markers))


def _tally(
    frame_truth: FrameTruth, detections: list[MarkerDetection], edges: list[float],
    counts: dict[str, np.ndarray], in_view: dict[str, int],
) -> None:  # fmt: skip
    for marker in frame_truth.markers:
        in_view[marker.name] += int(marker.in_view)
        if not marker.detected_sharp:
            continue
        column = int(np.searchsorted(edges, marker.blur_px, side="right")) - 1
        column = min(max(column, 0), len(edges) - 2)
        tolerance = marker.size_px / 2 + marker.blur_px
        found = any(
            d.name == marker.name and _matches(d, marker.centre_px, tolerance) for d in detections
        )
        counts[marker.name][0, column] += 1
        counts[marker.name][1, column] += int(found)
