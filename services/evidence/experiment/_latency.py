"""The mediator's decision latency, for the replay: recorded per frame, or drawn as measured.

The real mediator decides a frame only once the gyro covers its exposure: from the
exposure's end to the decision, p50 15 ms and p95 about 60 ms on the 2-core machine the
experiment ran on (gyro batches, transport, CPU shared with the other services). A replay
that decides every frame the moment it arrives hides what that wait costs a policy that
holds frames (while it waits, no held frame goes out). So the replay takes latencies:

- recorded: a real run's decision records (frame id -> ``latency_ns``): the first record of
  each frame (``decision_latencies``; a held frame's first record is its hold);
- measured: drawn independently per frame from ``MEASURED_LATENCY_MS``, the 20-quantiles
  of those records (``paper`` runs, seeds 1-2, N = 2, factor 1.6), seeded, so a sweep is
  repeatable and every seed and policy sees its own fixed draw.
"""

from __future__ import annotations

import random
from collections.abc import Iterable, Sequence

from services.lib.messages import DecisionRecord

from ._frames import FrameOutcome

MEASURED_LATENCY_MS: tuple[tuple[float, float], ...] = (
    (0.00, 6.8), (0.05, 8.0), (0.10, 8.7), (0.15, 9.7), (0.20, 10.9), (0.25, 11.7),
    (0.30, 12.2), (0.35, 12.8), (0.40, 13.6), (0.45, 14.3), (0.50, 14.7), (0.55, 15.0),
    (0.60, 15.5), (0.65, 15.9), (0.70, 16.7), (0.75, 17.8), (0.80, 19.9), (0.85, 23.2),
    (0.90, 29.0), (0.95, 40.9), (0.96, 44.7), (0.97, 51.5), (0.98, 64.4), (0.99, 115.7),
    (1.00, 361.9),
)  # fmt: skip
"""(quantile, decision latency in ms) of the measured records (see the module docstring)."""

LATENCY_MODES = ("measured", "none")


def measured_latencies(frames: Sequence[FrameOutcome], seed: int) -> dict[int, int]:
    """A latency per frame id drawn from ``MEASURED_LATENCY_MS`` (the quantile function,
    linear between the measured quantiles), the same for the same frames and seed."""
    rng = random.Random(seed)
    table = MEASURED_LATENCY_MS
    out = {}
    for frame in frames:
        u = rng.random()
        upper = next(i for i in range(1, len(table)) if table[i][0] >= u)
        (p0, v0), (p1, v1) = table[upper - 1], table[upper]
        value_ms = v0 + (u - p0) / (p1 - p0) * (v1 - v0)
        out[frame.frame_id] = round(value_ms * 1e6)
    return out


def decision_latencies(first_decisions: Iterable[DecisionRecord]) -> dict[int, int]:
    """Frame id -> decision latency from each frame's first record, written when the mediator
    first decided it (whatever the policy). Frames it skipped undecided (latency 0: bad
    metadata, lapsed) are left out."""
    return {d.frame_id: d.latency_ns for d in first_decisions if d.latency_ns > 0}
