"""The mediator's decision latency, for the replay: recorded per frame, or drawn as measured.

The real mediator decides a frame only once the gyro covers its exposure: from the
exposure's end to the decision, p50 15 ms and p95 about 60 ms on the 2-core machine the
experiment ran on (gyro batches, transport, CPU shared with the other services). A replay
that decides every frame the moment it arrives hides what that wait costs a policy that
holds frames (while it waits, no held frame goes out). So the replay takes latencies:

- recorded: a real run's decision records (frame id -> ``latency_ns``) of a policy that
  never holds a frame (``paper``), whose records are written at the decision itself;
- measured: drawn independently per frame from ``MEASURED_LATENCY_MS``, the 20-quantiles
  of those records (``paper`` runs, seeds 1-2, N = 2, factor 1.6), seeded, so a sweep is
  repeatable and every seed and policy sees its own fixed draw.
"""

from __future__ import annotations

import random
from collections.abc import Iterable, Sequence

from services.lib.messages import DecisionRecord

from ._frames import FrameOutcome

MEASURED_LATENCY_MS: tuple[float, ...] = (
    6.8, 8.0, 8.7, 9.7, 10.9, 11.7, 12.2, 12.8, 13.6, 14.3,
    14.7, 15.0, 15.5, 15.9, 16.7, 17.8, 19.9, 23.2, 29.0, 40.9, 361.9,
)  # fmt: skip
"""Decision latency quantiles 0, 5, ..., 95 % and the maximum, in ms (see the docstring)."""

LATENCY_MODES = ("measured", "none")

_NO_HOLD_REASONS = frozenset({"quality>load", "quality<=load"})


def measured_latencies(frames: Sequence[FrameOutcome], seed: int) -> dict[int, int]:
    """A latency per frame id drawn from ``MEASURED_LATENCY_MS`` (uniform between two
    adjacent quantiles), the same for the same frames and seed."""
    rng = random.Random(seed)
    table = MEASURED_LATENCY_MS
    out = {}
    for frame in frames:
        u = rng.random() * (len(table) - 1)
        low = int(u)
        value_ms = table[low] + (u - low) * (table[low + 1] - table[low])
        out[frame.frame_id] = round(value_ms * 1e6)
    return out


def recorded_latencies(decisions: Iterable[DecisionRecord]) -> dict[int, int]:
    """Frame id -> decision latency from a run's records, only where the record was written
    at the decision (the paper's rule never holds; other reasons may include a hold)."""
    return {
        d.frame_id: d.latency_ns
        for d in decisions
        if d.reason in _NO_HOLD_REASONS and d.latency_ns > 0
    }
