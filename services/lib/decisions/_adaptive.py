"""``adaptive`` (beyond the paper): thresholds from the recent qualities, on the detector's clock.

What the mediator can know causally: the quality of the frame at hand, the recent
distribution of qualities (``View.recent_q``), how many frames wait for the detector, and
the processing clock (when it will be free: its last take plus the service time the decider
measures). The policy holds one candidate, the best frame since the last forward (a newer
frame wins within ``recency_q``: on an approach a newer frame shows larger markers), and
values frames by ``min(q, cap_q)``: above about 0.7 recognition no longer depends on q, so
sharper frames there are equally good and the newest of them is best. Thresholds are
quantiles of the recent values, so they follow the floor instead of fixed numbers.

When the candidate goes to the detector, by the detector's state:

- frames wait (k of N): commit it now if its value reaches the quantile ``commit_quantile``
  · k / (N − 1) of the recent values (the paper's rule "q > load" made relative to the
  floor), else keep it as the candidate for the slot after them;
- nothing waits but the detector is busy: with N ≥ 2 commit it now if it reaches the
  ``busy_quantile`` (a good frame now, and the hold starts over for the next slot); else
  hold it until the detector needs it (when the next frame, one period away, would come
  too late): the slot gets the best of every frame until then;
- the detector is idle: forward it if it reaches the ``idle_quantile``, else let the
  detector idle for at most ``idle_wait`` frame periods waiting for a better one.

The real-time margin. The mediator decides a frame only once the gyro covers its exposure,
and while it waits for those samples it forwards nothing, so a held frame cannot go out
between the next frame's arrival and its decision. "The next frame" therefore comes one
frame period after this one's exposure plus *its* decision latency, not one period after
this decision. The policy measures each frame's latency at its decision as ``now_ns −
timestamp_ns`` (the mediator's clock minus the camera's: an unknown constant offset plus
the latency, so only the excess over the smallest recent one is used) and expects the next
decision at this one's time plus a period plus the ``latency_quantile`` of the recent
excesses, less this frame's own: a held frame the detector would need before then goes
now. The decision's time, not the frame's ``arrived_ns``: the mediator's clock when the
frame came in is earlier by the wait for its gyro samples, and the next frame waits as
long, so counting from the arrival expects the next decision too early and lets the
detector idle.

A held frame and the frames queued never outnumber the queue's N slots (the experiment's
oracle bounds every policy under that rule); a full queue drops the candidate. The count of
queued frames moves only when the detector's ack of a take arrives, which can be tens of ms
after the take on a loaded machine: a full count that the policy's processing clock says
the detector is already past (``_taken_unseen``) keeps the candidate held until the take is
seen, rather than losing it to a slot that is in fact free. Until the
decider has measured the service time, the policy forwards when nothing waits, as
``replace`` does.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

from ._records import Action, Candidate, Verdict, View


@dataclass(frozen=True, slots=True)
class AdaptiveParams:
    """The policy's parameters. The defaults were chosen by a random and local search
    (400 points) on the replay of calibration seeds 101-103 (default floor, N = 1, 2, 3,
    service 1.6 frame periods), maximising the worst gain over ``paper`` across N plus the
    worst captured share at N = 2; the seeds reported are others."""

    cap_q: float = 0.6
    recency_q: float = 0.03
    commit_quantile: float = 0.8
    busy_quantile: float = 0.4
    idle_quantile: float = 0.1
    idle_wait: float = 0.6
    slack_ns: int = 5_000_000
    latency_quantile: float = 0.9
    latency_window: int = 32


class AdaptivePolicy:
    """One candidate, committed by quantile thresholds of the recent qualities."""

    name = "adaptive"

    def __init__(self, params: AdaptiveParams | None = None) -> None:
        self.params = params or AdaptiveParams()
        self._free_at_ns: int | None = None  # when the detector finishes what it was given
        self._last_decision_ns: int | None = None  # the last frame's decision (mediator clock)
        self._last_timestamp_ns: int | None = None
        self._period_ns: int | None = None
        self._lags: deque[int] = deque(maxlen=self.params.latency_window)

    # -- values and thresholds ---------------------------------------------------------------
    def _value(self, frame: Candidate) -> float:
        assert frame.q is not None
        return min(frame.q, self.params.cap_q)

    def _reaches(self, frame: Candidate, level: float, view: View) -> bool:
        """Whether the frame's value reaches the ``level`` quantile of the recent values."""
        if level <= 0.0:
            return True
        if level >= 1.0:
            return False
        if len(view.recent_q) < 8:
            return True  # too few to rank: as the paper's rule with a free slot
        ranked = sorted(min(q, self.params.cap_q) for q in view.recent_q)
        return self._value(frame) >= ranked[int(level * (len(ranked) - 1))]

    def _pick(self, frames: Sequence[Candidate]) -> Candidate:
        best = frames[0]
        for frame in frames[1:]:
            if self._value(frame) >= self._value(best) - self.params.recency_q:
                best = frame
        return best

    def margin_ns(self) -> int:
        """How much later than one frame period after the last decision the next frame
        will be decided: the ``latency_quantile`` of the recent latencies, less the last
        frame's own (0 with no spread; below 0 when the last frame was decided late, so
        that the next one may already be waiting)."""
        if len(self._lags) < 4:
            return 0
        ranked = sorted(self._lags)
        high = ranked[min(len(ranked) - 1, int(self.params.latency_quantile * len(ranked)))]
        return high - self._lags[-1]

    # -- the processing clock ----------------------------------------------------------------
    def _needs_at_ns(self, view: View, service_ns: int) -> int:
        """When the detector runs out of the work it has been given."""
        # Its own account of what it forwarded is exact; a take is seen only at the next
        # look, so it serves only when nothing was forwarded yet.
        free = self._free_at_ns
        if free is None:
            take = view.detector.last_take_ns
            free = take + service_ns if take is not None else view.now_ns
        if view.load.queued > 0:
            free = max(free, view.now_ns + view.load.queued * service_ns)
        return free

    def _forward(self, frame: Candidate, view: View, reason: str) -> Verdict:
        service = view.detector.service_ns
        if service is None:
            # No account without a service time: one kept with 0 would say the detector is
            # free (and has taken what waits) long before it is.
            self._free_at_ns = None
        else:
            self._free_at_ns = max(view.now_ns, self._needs_at_ns(view, service)) + service
        return Verdict(frame, Action.FORWARD, reason)

    # -- the decision ------------------------------------------------------------------------
    def _decide(self, best: Candidate, view: View, *, arrival: bool) -> Verdict | None:
        """FORWARD for the candidate, or None to keep holding it."""
        load = view.load
        service = view.detector.service_ns
        if service is None:
            return self._forward(best, view, "idle") if load.idle else None
        p = self.params
        period = self._period_ns or service
        if load.queued > 0:
            level = p.commit_quantile * load.queued / max(1, load.capacity - 1)
            return self._forward(best, view, "commit") if self._reaches(best, level, view) else None
        needs_at = self._needs_at_ns(view, service)
        busy = needs_at > view.now_ns
        if busy and load.capacity >= 2 and self._reaches(best, p.busy_quantile, view):
            return self._forward(best, view, "commit-busy")
        # The next frame is decided one period after this one (or after the last one), plus
        # the real-time margin: until then nothing held can go out.
        last = self._last_decision_ns if self._last_decision_ns is not None else view.now_ns
        next_arrival = max(
            view.now_ns, (view.now_ns if arrival else last) + period + self.margin_ns()
        )
        # It must leave the hand-over time before the detector needs it (0 in a replay).
        handover = view.detector.handover_ns or 0
        if next_arrival <= needs_at - handover + p.slack_ns:
            return None  # another frame comes before the detector needs one
        if self._reaches(best, p.idle_quantile, view):
            return self._forward(best, view, "deadline" if busy else "idle")
        if next_arrival - needs_at > p.idle_wait * period:
            return self._forward(best, view, "idle-waited")
        return None  # the detector idles until the next frame: this one is too blurred

    def _taken_unseen(self, view: View) -> bool:
        """Whether the count of queued frames is behind the detector: by this policy's own
        account, the oldest frame counted as queued should have been taken by now.

        The count falls only when the detector's ack of the take arrives, and that comes
        late on a busy machine (p50 3 ms, p90 60 ms, max 160 ms after the take on a 2-core
        machine at load 20, measured), while a frame is decided in between. The oldest
        frame still counted starts at the time ``_forward`` planned for it: the last one's
        start less a service time per other queued frame. (The take seen last cannot bound
        it: it is dated when its ack was fed, as late as this one's.)"""
        service = view.detector.service_ns
        if service is None or self._free_at_ns is None or view.load.queued == 0:
            return False
        return view.now_ns >= self._free_at_ns - view.load.queued * service

    def _verdicts(
        self, frames: Sequence[Candidate], new: Candidate | None, view: View
    ) -> list[Verdict]:
        full = view.load.free == 0
        if full and not self._taken_unseen(view):
            return [Verdict(f, Action.DROP, "queue-full") for f in frames]
        best = self._pick(frames)
        out = [
            Verdict(f, Action.DROP, "worse-than-held" if f is new else "replaced")
            for f in frames
            if f is not best
        ]
        # A full count the detector is already past: nothing can be put until its ack is in
        # (a put would be refused), but the slot it freed is this candidate's. Dropping it,
        # as a queue really full must, would leave that slot to a later frame or to nobody;
        # held, it is decided again when the take is seen (``on_tick``).
        verdict = None if full else self._decide(best, view, arrival=new is not None)
        if verdict is not None:
            out.append(verdict)
        elif best is new:
            out.append(Verdict(best, Action.HOLD, "held"))
        return out

    # -- the contract ------------------------------------------------------------------------
    def on_frame(self, frame: Candidate, view: View) -> Sequence[Verdict]:
        # The frame period from the camera's timestamps (exact); the latency from the gap
        # between them and the mediator's clock at this decision.
        last = self._last_timestamp_ns
        if last is not None and frame.timestamp_ns > last:
            step = frame.timestamp_ns - last
            self._period_ns = step if self._period_ns is None else (7 * self._period_ns + step) // 8
        self._last_timestamp_ns = frame.timestamp_ns
        self._last_decision_ns = view.now_ns
        self._lags.append(view.now_ns - frame.timestamp_ns)
        return self._verdicts([*view.held, frame], frame, view)

    def next_due_ns(self, view: View) -> int | None:
        service = view.detector.service_ns
        if not view.held or service is None or view.load.queued > 0:
            return None  # idle-only or committing on queue levels: only input changes it
        # ``_decide`` compares now with these: when the detector needs work, the next
        # frame's expected decision and the longest idle wait.
        needs_at = self._needs_at_ns(view, service)
        period = self._period_ns or service
        last = self._last_decision_ns if self._last_decision_ns is not None else view.now_ns
        handover = view.detector.handover_ns or 0
        times = [
            needs_at,
            needs_at - handover,
            needs_at - handover + self.params.slack_ns,
            last + period + self.margin_ns(),
            needs_at + int(self.params.idle_wait * period),
        ]
        return min((t for t in times if t > view.now_ns), default=None)

    def on_tick(self, view: View) -> Sequence[Verdict]:
        if not view.held:
            return ()
        return self._verdicts(view.held, None, view)
