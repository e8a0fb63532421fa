"""Discrete-event replay: a run's frames through the detector's queue, in simulated time.

The same queueing rules as the real pipeline: the detector processes one frame at a time
for ``service_ns``, takes the oldest waiting frame the moment it is free, and at most
``queue`` (N) frames wait; a frame put while N wait is refused (lost). ``uncontrolled``
puts every frame as it arrives (the camera's flow control); a mediator run feeds every
frame to a causal policy (``services.lib.decisions.Policy``) and applies its verdicts the
way the mediator does: held frames stay with the mediator, a held frame older than
``max_hold_ns`` is dropped as stale, FORWARD puts the frame (or loses it to a full queue),
and while frames are held the policy is asked again whenever the detector takes a frame and
at the times the decider names (``Decider.next_due_ns``), as the mediator does. Nothing
here runs processes or touches the clock: a replay of 319 frames takes milliseconds, so
sweeps over queues, service times and policies are cheap.
"""

from __future__ import annotations

import statistics
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from services.lib.decisions import (
    Action,
    Candidate,
    Decider,
    DetectorClock,
    Load,
    Policy,
    Rules,
    Verdict,
)

from ._config import ExperimentError
from ._frames import FrameOutcome


@dataclass(frozen=True, slots=True)
class QueueModel:
    """The detector and mediator timing of a replay."""

    queue: int
    service_ns: int
    max_hold_ns: int = 250_000_000

    def __post_init__(self) -> None:
        if self.queue < 1 or self.service_ns <= 0:
            raise ExperimentError(
                f"replay needs queue >= 1 and positive times, got N={self.queue}, "
                f"service {self.service_ns} ns"
            )


class _Detector:
    """The detector's queue and processor in simulated time."""

    def __init__(self, model: QueueModel) -> None:
        self.model = model
        self.waiting: deque[int] = deque()
        self.free_ns = -(2**62)  # when the frame in processing finishes
        self.processed: list[int] = []
        self.takes_ns: list[int] = []
        self.intervals_ns: list[int] = []

    def next_event_ns(self) -> int | None:
        """When the processor next finishes with a frame waiting (a take), if ever."""
        return self.free_ns if self.waiting else None

    def advance(self, now_ns: int) -> None:
        """Every take up to and including ``now_ns``."""
        while self.waiting and self.free_ns <= now_ns:
            self._take(self.free_ns)

    def put(self, frame_id: int, now_ns: int) -> bool:
        """Offer a frame; False when N frames already wait (refused)."""
        self.advance(now_ns)
        if len(self.waiting) >= self.model.queue:
            return False
        self.waiting.append(frame_id)
        if self.free_ns <= now_ns:
            self._take(now_ns)
        return True

    def _take(self, at_ns: int) -> None:
        waited = self.free_ns == at_ns  # back to back: the interval measures the service
        frame_id = self.waiting.popleft()
        self.processed.append(frame_id)
        if self.takes_ns and waited:
            self.intervals_ns.append(at_ns - self.takes_ns[-1])
        self.takes_ns.append(at_ns)
        self.free_ns = at_ns + self.model.service_ns

    def clock(self) -> DetectorClock:
        service = int(statistics.median(self.intervals_ns[-15:])) if self.intervals_ns else None
        return DetectorClock(self.takes_ns[-1] if self.takes_ns else None, service)


def replay_uncontrolled(frames: Sequence[FrameOutcome], model: QueueModel) -> tuple[int, ...]:
    """Frame ids processed when every frame is put as it arrives (no mediator)."""
    detector = _Detector(model)
    for frame in frames:
        detector.put(frame.frame_id, frame.arrival_ns)
    detector.advance(2**62)
    return tuple(detector.processed)


def replay_policy(
    frames: Sequence[FrameOutcome],
    model: QueueModel,
    policy: Policy,
    latencies_ns: Mapping[int, int] | None = None,
) -> tuple[int, ...]:
    """Frame ids processed when a mediator with ``policy`` sits before the detector: the
    mediator's own ``Decider`` decides, fed the replay's times and queue counts.

    ``latencies_ns`` (frame id -> ns from exposure end to the mediator's decision, e.g. a
    real run's decision records) makes the mediator decide each frame that much after its
    exposure ended (never before the previous decision); as in the real mediator, held
    frames may go out meanwhile (a frame waits for its gyro samples on a deadline of its
    own, not by blocking the mediator). Without them every frame is decided the moment it
    arrives."""
    decider = Decider(policy, Rules(max_hold_ns=model.max_hold_ns))
    detector = _Detector(model)

    def carry_out(verdicts: Sequence[Verdict], now_ns: int) -> None:
        for verdict in verdicts:
            if verdict.action is Action.FORWARD and not detector.put(
                verdict.frame.frame_id, now_ns
            ):
                decider.refused(verdict.frame)

    def load() -> Load:
        # As the mediator's producer reports it: the count and when the last take was seen.
        taken = detector.takes_ns[-1] if detector.takes_ns else None
        return Load(len(detector.waiting), model.queue, taken)

    last = [-(2**62)]  # the time of the last look

    def run_until(limit_ns: int) -> None:
        # The mediator sees each take, and asks again when the decider says it may decide
        # otherwise with no new input.
        while True:
            take = detector.next_event_ns()
            due = decider.next_due_ns(last[0]) if decider.held else None
            now = min((t for t in (take, due) if t is not None), default=None)
            if now is None or now >= limit_ns:
                return
            last[0] = now
            detector.advance(now)
            carry_out(decider.tick(load(), now), now)

    decided = -(2**62)
    for frame in frames:
        latency = latencies_ns.get(frame.frame_id, 0) if latencies_ns is not None else 0
        now = max(frame.arrival_ns + max(0, latency), decided)
        run_until(now)  # held frames go out while this one waits for its gyro samples
        decided = last[0] = now
        detector.advance(now)
        candidate = Candidate(frame.arrival_ns, frame.frame_id, frame.quality, now, frame.blur_px)
        carry_out(decider.frame(candidate, load(), now), now)
    end = max(frames[-1].arrival_ns, decided) if frames else 0
    run_until(end + 2 * model.max_hold_ns)
    detector.advance(2**62)
    return tuple(detector.processed)
