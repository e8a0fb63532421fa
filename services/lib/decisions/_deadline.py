"""``deadline`` (beyond the paper): choose at the last moment, from every frame until then.

A frame forwarded to the detector is committed: it cannot be swapped for a sharper one that
arrives while it waits in the queue. So this policy commits as late as it can. It keeps the
detector's processing clock (when what it was given will be done: each forward starts at
the later of now and the previous finish, plus the service time the decider measured) and
holds one candidate, the best frame seen since the last forward. It forwards that candidate
when the next frame (one frame period away) would come after the detector needs work, less
``slack_ns`` of idling it will accept to see one more frame. So every processing slot gets
the best of all frames that arrived before it, whatever N is; the queue stays nearly empty.

Best: higher q, but a newer frame within ``recency_q`` of the held one wins (on an approach
a newer frame is closer, so its markers are larger, and quality above about 0.5 changes
recognition little). An idle detector takes a frame at once unless its q is below the
``idle_quantile`` of the recent qualities: then it waits for the next frame (one frame
period of idling to avoid a whole service time spent on a blurred frame).

Until it has seen the detector take three frames (the service time is the shortest time
between takes), the policy forwards as ``replace`` does when the queue is empty.
"""

from __future__ import annotations

import itertools
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

from ._records import Action, Candidate, Verdict, View


@dataclass(frozen=True, slots=True)
class DeadlineParams:
    """The policy's parameters (chosen on calibration seeds; see the experiment's sweep)."""

    recency_q: float = 0.05
    slack_ns: int = 10_000_000
    idle_quantile: float = 0.1


class DeadlinePolicy:
    """Hold the best frame; forward it just before the detector needs it."""

    name = "deadline"

    def __init__(self, params: DeadlineParams | None = None) -> None:
        self.params = params or DeadlineParams()
        self._free_at_ns: int | None = None  # when the detector finishes what it was given
        self._last_arrival_ns: int | None = None
        self._period_ns: int | None = None
        self._waiting_ns: int | None = None  # an idle-time low frame given one more period
        self._takes: deque[int] = deque(maxlen=9)

    # -- the processing clock ----------------------------------------------------------------
    def _service_ns(self, view: View) -> int | None:
        """The shortest recent time between two takes: takes are never closer than one
        service time and are exactly that whenever a frame was ready (the decider's own
        estimate needs two frames queued at once, which never happens with N = 1)."""
        take = view.detector.last_take_ns
        if take is not None and (not self._takes or take > self._takes[-1]):
            self._takes.append(take)
        if len(self._takes) < 3:
            return view.detector.service_ns
        takes = list(self._takes)
        return min(b - a for a, b in itertools.pairwise(takes))

    def _needs_at_ns(self, view: View) -> int:
        """When the detector runs out of work it has been given."""
        free = self._free_at_ns if self._free_at_ns is not None else view.now_ns
        if view.load.queued > 0:
            # Frames still wait: the detector is slower than we think; it is busy until now
            # at least, and one more service per waiting frame.
            service = self._service_ns(view) or 0
            free = max(free, view.now_ns + view.load.queued * service)
        return free

    def _forward(self, frame: Candidate, view: View, reason: str) -> Verdict:
        service = self._service_ns(view) or 0
        start = max(view.now_ns, self._needs_at_ns(view))
        self._free_at_ns = start + service
        return Verdict(frame, Action.FORWARD, reason)

    def _pick(self, frames: Sequence[Candidate]) -> Candidate:
        """The best of frames in time order: a newer one wins unless clearly blurrier."""
        best = frames[0]
        for frame in frames[1:]:
            assert frame.q is not None and best.q is not None
            if frame.q >= best.q - self.params.recency_q:
                best = frame
        return best

    def _low(self, frame: Candidate, view: View) -> bool:
        if self.params.idle_quantile <= 0 or len(view.recent_q) < 8:
            return False
        ranked = sorted(view.recent_q)
        threshold = ranked[int(self.params.idle_quantile * (len(ranked) - 1))]
        assert frame.q is not None
        return frame.q < threshold

    def _choose(self, frames: Sequence[Candidate], new: Candidate | None) -> tuple[
        Candidate, list[Verdict]
    ]:  # fmt: skip
        best = self._pick(frames)
        drops = [
            Verdict(f, Action.DROP, "worse-than-held" if f is new else "replaced")
            for f in frames
            if f is not best
        ]
        return best, drops

    # -- the contract ------------------------------------------------------------------------
    def on_frame(self, frame: Candidate, view: View) -> Sequence[Verdict]:
        if self._last_arrival_ns is not None and frame.arrived_ns > self._last_arrival_ns:
            step = frame.arrived_ns - self._last_arrival_ns
            self._period_ns = step if self._period_ns is None else (7 * self._period_ns + step) // 8
        self._last_arrival_ns = frame.arrived_ns
        if view.load.free == 0:
            # Held and queued frames never outnumber the queue's N slots (as replace): the
            # oracle of the experiment bounds every policy under that rule.
            return [*(Verdict(h, Action.DROP, "queue-full") for h in view.held),
                    Verdict(frame, Action.DROP, "queue-full")]  # fmt: skip
        best, out = self._choose([*view.held, frame], frame)
        service = self._service_ns(view)
        if service is None:
            # No clock yet: as replace with one slot, forward when the queue is empty.
            if view.load.idle:
                return [*out, self._forward(best, view, "idle")]
            return [*out, Verdict(frame, Action.HOLD, "held")] if best is frame else out
        needs_at = self._needs_at_ns(view)
        period = self._period_ns or service
        last_chance = view.now_ns + period > needs_at + self.params.slack_ns
        idle = needs_at <= view.now_ns
        if idle and best is frame and self._low(frame, view) and self._waiting_ns is None:
            # Idle, and this frame is among the blurriest lately: wait one frame for another.
            self._waiting_ns = frame.timestamp_ns
            return [*out, Verdict(frame, Action.HOLD, "held-low")]
        if last_chance:
            self._waiting_ns = None
            return [*out, self._forward(best, view, "deadline")]
        return [*out, Verdict(frame, Action.HOLD, "held")] if best is frame else out

    def next_due_ns(self, view: View) -> int | None:
        if not view.held or (service := self._service_ns(view)) is None:
            return None  # without a clock it forwards only when the queue empties (input)
        best = self._pick(view.held)
        period = self._period_ns or service
        times = [self._needs_at_ns(view) - self.params.slack_ns]
        times.append(best.arrived_ns + view.max_hold_ns - period)
        if best.timestamp_ns == self._waiting_ns:
            times.append(best.arrived_ns + period)
        return min((t for t in times if t > view.now_ns), default=None)

    def on_tick(self, view: View) -> Sequence[Verdict]:
        if not view.held:
            return ()
        if view.load.free == 0:
            return [Verdict(h, Action.DROP, "queue-full") for h in view.held]
        best, out = self._choose(view.held, None)
        service = self._service_ns(view)
        if service is None:
            if view.load.idle:
                out.append(self._forward(best, view, "forwarded-held"))
            return out
        period = self._period_ns or service
        if best.timestamp_ns == self._waiting_ns and view.held_for_ns(best) < period:
            return out
        due = view.now_ns + self.params.slack_ns >= self._needs_at_ns(view)
        if due or view.held_for_ns(best) + period > view.max_hold_ns:
            self._waiting_ns = None
            out.append(self._forward(best, view, "deadline"))
        return out
