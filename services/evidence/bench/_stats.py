"""Order statistics of benchmark samples: median, percentiles, min/max and ratios.

Plain Python on purpose: the samples are few (one per run) or modest (latencies of one
run), and the definitions must be obvious from the code — the percentile is numpy's default
("linear" interpolation between closest ranks).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Summary:
    """Median, min and max of one side's samples (one sample per run)."""

    median: float
    min: float
    max: float
    count: int

    def as_json(self) -> dict[str, float | int]:
        return {"median": self.median, "min": self.min, "max": self.max, "count": self.count}


def percentile(values: Sequence[float], q: float) -> float:
    """The q-th percentile (0 <= q <= 100), interpolating linearly between closest ranks."""
    if not values:
        raise ValueError("percentile of no values")
    if not 0.0 <= q <= 100.0:
        raise ValueError(f"percentile q={q} is outside 0..100")
    ordered = sorted(values)
    position = (len(ordered) - 1) * q / 100.0
    low = math.floor(position)
    high = min(low + 1, len(ordered) - 1)
    fraction = position - low
    return ordered[low] + (ordered[high] - ordered[low]) * fraction


def median(values: Sequence[float]) -> float:
    """The middle value (the mean of the two middle ones for an even count)."""
    return percentile(values, 50.0)


def summarize(values: Sequence[float]) -> Summary:
    """Median, min, max and count; ValueError for no values."""
    if not values:
        raise ValueError("summary of no values")
    return Summary(median(values), float(min(values)), float(max(values)), len(values))


def ratio(framegate: float | None, raw: float | None) -> float | None:
    """framegate / raw, or None when either is missing or raw is not positive."""
    if framegate is None or raw is None or raw <= 0 or math.isnan(raw) or math.isnan(framegate):
        return None
    return framegate / raw
