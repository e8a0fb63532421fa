"""The records that go into and come out of the mediator's decisions."""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable
from dataclasses import dataclass

from middleware import SubscriptionInfo, tightest_flow
from services.lib.quality import QualityInputError


class Action(enum.Enum):
    """What happens to a frame: sent to the detector, kept for later, or let go."""

    FORWARD = "forward"
    HOLD = "hold"
    DROP = "drop"


@dataclass(frozen=True, slots=True)
class Candidate:
    """A frame the mediator has assessed and must decide on.

    ``q`` is None when the gyro did not cover the exposure (the gyro-missing rule decides);
    ``arrived_ns`` is the mediator's clock when the frame arrived (hold times count from it).
    ``unpaired``: why a frame has no quality, if not because the gyro does not cover it
    (``clock-offset``: camera and gyro clocks disagree too much to pair them); it becomes
    the decision's reason, the gyro-missing rule still decides.
    """

    timestamp_ns: int
    frame_id: int
    q: float | None
    arrived_ns: int
    blur_px: float | None = None
    unpaired: str | None = None

    def __post_init__(self) -> None:
        if self.q is not None and not (math.isfinite(self.q) and 0.0 < self.q <= 1.0):
            raise QualityInputError(
                f"frame {self.frame_id}: quality must be in (0, 1], got {self.q!r}"
            )


@dataclass(frozen=True, slots=True)
class Load:
    """The detector's notification queue as the mediator's producer counts it.

    ``queued``: frames waiting (the one in processing does not count); ``capacity``: its size
    N. ``capacity`` 0 means no flow-controlled consumer: nothing holds frames back.
    ``taken_ns``: when the producer last saw the detector take a frame (the decider's clock),
    if it knows; the decider otherwise dates a take by when it notices the count fall.
    """

    queued: int
    capacity: int
    taken_ns: int | None = None

    def __post_init__(self) -> None:
        if self.capacity < 0 or self.queued < 0:
            raise QualityInputError(f"queue counts must be >= 0, got {self.queued}/{self.capacity}")

    @property
    def fill(self) -> float:
        """The paper's load indicator: queued / N in [0, 1] (0 with no consumer)."""
        return queue_load(self.queued, self.capacity) if self.capacity else 0.0

    @property
    def free(self) -> int:
        """Slots left in the queue (0 when full; N with no consumer is unbounded: 1)."""
        if self.capacity == 0:
            return 1
        return max(0, self.capacity - self.queued)

    @property
    def idle(self) -> bool:
        """Nothing waits for the detector: the next frame it needs must come now."""
        return self.queued == 0


def tightest_load(
    subscriptions: Iterable[SubscriptionInfo],
) -> tuple[Load, SubscriptionInfo | None]:
    """The detector's load from a producer's subscriptions: that of the flow-controlled
    subscription that will refuse first (``middleware.tightest_flow``, as the demo
    reads it), and that subscription; Load(0, 0) and None without one."""
    tightest = tightest_flow(subscriptions)
    if tightest is None:
        return Load(0, 0), None
    queued = min(tightest.queued, tightest.queue_size)
    return Load(queued, tightest.queue_size, tightest.taken_ns), tightest


def queue_load(pending: int, capacity: int) -> float:
    """System load in [0, 1]: pending notifications over the queue's capacity (paper §4.3)."""
    if capacity <= 0:
        raise QualityInputError(f"queue capacity must be positive, got {capacity}")
    if pending < 0:
        raise QualityInputError(f"pending count must be >= 0, got {pending}")
    return min(pending / capacity, 1.0)


@dataclass(frozen=True, slots=True)
class Verdict:
    """One decision on one frame, and why (the reason is recorded in mediator/decisions)."""

    frame: Candidate
    action: Action
    reason: str


@dataclass(frozen=True, slots=True)
class DetectorClock:
    """What the mediator has seen of the detector's processing.

    ``last_take_ns``: when the detector last took a frame from its queue (mediator clock);
    ``service_ns``: the lower quartile of the times between takes while frames were waiting
    (None until seen), an estimate of how long the detector needs per frame; ``handover_ns``: the
    median time from forwarding a frame to an idle detector until its take was seen (None
    until seen): a frame the detector needs at ``t`` must leave that much before ``t``.
    """

    last_take_ns: int | None = None
    service_ns: int | None = None
    handover_ns: int | None = None


@dataclass(frozen=True, slots=True)
class View:
    """Everything the mediator knows at the moment of a decision; what a policy sees.

    ``held``: frames held for later, oldest first; ``recent_q``: the qualities of the last
    frames assessed (oldest first, the frame at hand not included); ``max_hold_ns``: the
    longest a frame may be held (the decider drops it as stale after that).
    """

    now_ns: int
    load: Load
    held: tuple[Candidate, ...]
    recent_q: tuple[float, ...]
    detector: DetectorClock
    max_hold_ns: int

    def held_for_ns(self, frame: Candidate) -> int:
        """How long ``frame`` has been waiting in the mediator."""
        return self.now_ns - frame.arrived_ns
