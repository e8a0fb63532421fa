"""Discrete-event replay: a run's frames through the detector's queue, in simulated time.

The same queueing rules as the real pipeline: the detector processes one frame at a time
for ``service_ns``, takes the oldest waiting frame the moment it is free (a frame put to it
idle, a hand-over later), and at most ``queue`` (N) frames count as waiting, those taken
included until their ack reaches the mediator; a frame put while N count is refused
(lost). The model's steps give a real run's detector speed, ack delays and hand-overs as
they were (``QueueModel``). ``uncontrolled``
puts every frame as it arrives (the camera's flow control); a mediator run feeds every
frame to a causal policy (``services.lib.decisions.Policy``) and applies its verdicts the
way the mediator does: held frames stay with the mediator, a held frame older than
``max_hold_ns`` is dropped as stale, FORWARD puts the frame (or loses it to a full queue),
and while frames are held the policy is asked again whenever the mediator learns of a take
and at the times the decider names (``Decider.next_due_ns``), as the mediator does. Nothing
here runs processes or touches the clock: a replay of 319 frames takes milliseconds, so
sweeps over queues, service times and policies are cheap.
"""

from __future__ import annotations

import bisect
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from services.lib.decisions import (
    Action,
    Candidate,
    Decider,
    Load,
    Policy,
    Rules,
    Verdict,
)

from ._config import ExperimentError
from ._frames import FrameOutcome


@dataclass(frozen=True, slots=True)
class QueueModel:
    """The detector and mediator timing of a replay.

    ``service_ns``: how long the detector takes per frame. ``service_steps``: (from when,
    service time) in time order, for a detector whose speed varied (a real run's, on a
    loaded machine): a frame taken at ``t`` takes the service time of the last step at or
    before ``t`` (``service_ns`` before the first). ``ack_steps``: (from when, ack delay)
    likewise: how long after a take at ``t`` the mediator learns of it (a real run's acks
    took 3 ms p50, 23 ms p90, 340 ms at most on a loaded 2-core machine, traced); until
    then the mediator counts the frame as queued, as its producer does (0 without steps:
    at once). ``handover_steps``: (from when, hand-over) likewise: how long after a frame
    is put to an idle detector at ``t`` the detector takes it (the put itself, transport,
    the detector's wake-up: 10 ms for a run's first frame, measured; 0 without steps)."""

    queue: int
    service_ns: int
    max_hold_ns: int = 250_000_000
    service_steps: tuple[tuple[int, int], ...] = ()
    ack_steps: tuple[tuple[int, int], ...] = ()
    handover_steps: tuple[tuple[int, int], ...] = ()

    def __post_init__(self) -> None:
        if (
            self.queue < 1
            or self.service_ns <= 0
            or any(s <= 0 for _t, s in self.service_steps)
            or any(a < 0 for _t, a in (*self.ack_steps, *self.handover_steps))
        ):
            raise ExperimentError(
                f"replay needs queue >= 1 and positive times, got N={self.queue}, "
                f"service {self.service_ns} ns"
            )

    def service_at(self, at_ns: int) -> int:
        """The service time of a frame taken at ``at_ns``."""
        index = bisect.bisect_right(self.service_steps, (at_ns, 2**63)) - 1
        return self.service_steps[index][1] if index >= 0 else self.service_ns

    def ack_at(self, at_ns: int) -> int:
        """How long after a take at ``at_ns`` the mediator sees it."""
        return _step_at(self.ack_steps, at_ns, 0)

    def handover_at(self, at_ns: int) -> int:
        """How long after a put at ``at_ns`` an idle detector takes the frame."""
        return _step_at(self.handover_steps, at_ns, 0)


def _step_at(steps: tuple[tuple[int, int], ...], at_ns: int, before: int) -> int:
    """The value of the last step at or before ``at_ns`` (``before`` ahead of the first)."""
    index = bisect.bisect_right(steps, (at_ns, 2**63)) - 1
    return steps[index][1] if index >= 0 else before


# Takes looked at for acks still on the way (more than a few never are: takes are a service
# time apart, acks late by at most a few of those).
_UNSEEN_SPAN = 16


class _Detector:
    """The detector's queue and processor in simulated time."""

    def __init__(self, model: QueueModel) -> None:
        self.model = model
        self.waiting: deque[int] = deque()
        self.free_ns = -(2**62)  # when the frame in processing finishes
        self.processed: list[int] = []
        self.takes_ns: list[int] = []
        self.seen_ns: list[int] = []  # when the mediator learns of each take

    def next_event_ns(self) -> int | None:
        """When the processor next finishes with a frame waiting (a take), if ever."""
        return self.free_ns if self.waiting else None

    def unseen(self, now_ns: int) -> int:
        """Takes the mediator has not learnt of by ``now_ns`` (their frames still count)."""
        return sum(1 for seen in self.seen_ns[-_UNSEEN_SPAN:] if seen > now_ns)

    def next_seen_ns(self, after_ns: int) -> int | None:
        """When the mediator next learns of a take already made, after ``after_ns``."""
        return min((s for s in self.seen_ns[-_UNSEEN_SPAN:] if s > after_ns), default=None)

    def taken_seen_ns(self, now_ns: int) -> int | None:
        """When the mediator last learnt of a take, as of ``now_ns`` (``Load.taken_ns``)."""
        return max((s for s in self.seen_ns[-_UNSEEN_SPAN:] if s <= now_ns), default=None)

    def advance(self, now_ns: int) -> None:
        """Every take up to and including ``now_ns``."""
        while self.waiting and self.free_ns <= now_ns:
            self._take(self.free_ns)

    def put(self, frame_id: int, now_ns: int) -> bool:
        """Offer a frame; False when N frames count as waiting (refused): those waiting and
        those taken whose ack has not reached the mediator's producer yet."""
        self.advance(now_ns)
        if len(self.waiting) + self.unseen(now_ns) >= self.model.queue:
            return False
        self.waiting.append(frame_id)
        if self.free_ns <= now_ns and len(self.waiting) == 1:
            # Idle: it takes the frame once the frame has reached it (the hand-over).
            self.free_ns = now_ns + self.model.handover_at(now_ns)
            self.advance(now_ns)
        return True

    def _take(self, at_ns: int) -> None:
        frame_id = self.waiting.popleft()
        self.processed.append(frame_id)
        self.takes_ns.append(at_ns)
        self.seen_ns.append(at_ns + self.model.ack_at(at_ns))
        self.free_ns = at_ns + self.model.service_at(at_ns)


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

    def load(now_ns: int) -> Load:
        # As the mediator's producer reports it: the count (a take counts once its ack is in)
        # and when it last saw a take.
        queued = min(model.queue, len(detector.waiting) + detector.unseen(now_ns))
        return Load(queued, model.queue, detector.taken_seen_ns(now_ns))

    last = [-(2**62)]  # the time of the last look

    def run_until(limit_ns: int) -> None:
        # The mediator learns of each take (its ack), and asks again when the decider says
        # it may decide otherwise with no new input; a take it has not learnt of yet only
        # moves the detector on.
        while True:
            detector.advance(last[0])
            take = detector.next_event_ns()
            seen = detector.next_seen_ns(last[0])
            due = decider.next_due_ns(last[0]) if decider.held else None
            look = min((t for t in (seen, due) if t is not None), default=None)
            if take is not None and take < limit_ns and (look is None or take < look):
                detector.advance(take)  # its ack is still on the way
                continue
            if look is None or look >= limit_ns:
                return
            last[0] = look
            detector.advance(look)
            carry_out(decider.tick(load(look), look), look)

    decided = -(2**62)
    for frame in frames:
        latency = latencies_ns.get(frame.frame_id, 0) if latencies_ns is not None else 0
        now = max(frame.arrival_ns + max(0, latency), decided)
        run_until(now)  # held frames go out while this one waits for its gyro samples
        decided = last[0] = now
        detector.advance(now)
        # As the mediator's: hold times count from the frame's arrival, not its decision.
        candidate = Candidate(
            frame.arrival_ns, frame.frame_id, frame.quality, frame.arrival_ns, frame.blur_px
        )
        carry_out(decider.frame(candidate, load(now), now), now)
    end = max(frames[-1].arrival_ns, decided) if frames else 0
    run_until(end + 2 * model.max_hold_ns)
    detector.advance(2**62)
    return tuple(detector.processed)
