"""The decider: the mediator's decisions as a pure state machine (no I/O, no threads).

The mediator feeds it (``frame`` for each assessed frame, ``tick`` while frames are held,
``refused`` when a put to the detector is refused) and carries out the verdicts it returns.
Time is whatever int-nanosecond clock the caller passes in: the mediator passes its monotonic
clock, a replay passes recorded times, so a recorded sequence decides the same every time.

Rules kept here for every policy, in this order:

1. the processing clock: a drop of the detector's queue count below what was forwarded
   is the detector taking frames; the time between two takes estimates its service time
   (``View.detector``) when a frame was seen waiting in between (left queued at the first
   take, or forwarded after it and still queued at a later look): the detector was busy
   all along, so the second take came the moment it was free. With N = 1 only the second
   case ever happens. A take is dated by ``Load.taken_ns`` (when the producer saw it) when
   the caller knows that, else by the look that noticed it. The hand-over: a frame
   forwarded to an empty queue while the detector was free is taken as soon as it gets
   there; the time until that take was seen (``View.detector.handover_ns``, the median of
   recent ones) is how much earlier than the detector's need a frame must leave (0 in a
   replay, where a put is taken at once; transport and the detector's wake-up in a real
   pipeline). The service time is the lower quartile of recent samples, which acks that
   arrive late (they only lengthen samples) cannot drag up;
2. due held frames first: the policy's ``on_tick`` runs before a new frame is decided, so
   older frames go out before newer ones;
3. late frames: a frame whose key is not newer than every frame seen is dropped
   (``out-of-order``): the detector's buffer only takes increasing keys. The caller
   bounds the keys that may become this reference (the mediator skips frames stamped
   beyond a horizon of its clock before they get here) and calls ``restart_order`` when
   the source starts over (a new producer epoch), so no gap outlasts one frame;
4. the gyro-missing rule: a frame without a quality is forwarded only when the detector
   is idle (``idle``, the default), always (``accept``) or never (``reject``);
5. the minimum quality: q < q_min is dropped (``below-minimum``);
6. the policy decides the frame (``on_frame``), then held frames again (``on_tick``);
7. ordering: once a frame is forwarded, held frames older than it can never be, and are
   dropped (``superseded``); a FORWARD out of time order becomes a drop (``out-of-order``);
8. the maximum hold: a frame held ``max_hold_ns`` or longer is dropped (``stale``);
9. a policy that breaks its contract (no verdict for the frame, a verdict on a frame it
   does not hold, two verdicts on one frame) is repaired, never trusted: the extra verdict
   is ignored, a forgotten frame is dropped (``no-verdict``), and ``policy_faults`` counts it.
"""

from __future__ import annotations

import enum
import statistics
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

from ._policy import Policy
from ._records import Action, Candidate, DetectorClock, Load, Verdict, View

DEFAULT_MAX_HOLD_NS = 250_000_000
_SERVICE_SAMPLES = 16


class GyroMissing(enum.Enum):
    """What to do with a frame whose exposure the gyro does not cover."""

    IDLE = "idle"
    ACCEPT = "accept"
    REJECT = "reject"
    DEFAULT = IDLE


@dataclass(frozen=True, slots=True)
class Rules:
    """The decider's settings that hold for every policy."""

    q_min: float = 0.0
    gyro_missing: GyroMissing = GyroMissing.DEFAULT
    max_hold_ns: int = DEFAULT_MAX_HOLD_NS
    recent_count: int = 64


class Decider:
    """Frames and the detector's load in, verdicts out (see the module docstring)."""

    def __init__(self, policy: Policy, rules: Rules | None = None) -> None:
        self.policy = policy
        self.rules = rules or Rules()
        self._held: list[Candidate] = []
        self._recent: deque[float] = deque(maxlen=self.rules.recent_count)
        self._newest_seen_ns: int | None = None
        self._newest_forwarded_ns: int | None = None
        # Processing clock: the queue count we expect if the detector took nothing.
        self._expected_queued: int | None = None
        self._last_take_ns: int | None = None
        self._waiting_after_take = False
        self._service: deque[int] = deque(maxlen=_SERVICE_SAMPLES)
        # The hand-over: when a frame went to an idle detector, until its take is seen.
        self._handed_at: int | None = None
        self._handovers: deque[int] = deque(maxlen=_SERVICE_SAMPLES)
        self._now_ns = 0
        # Inside one call: the load the caller gave plus what this call forwarded.
        self._load = Load(0, 0)
        self.policy_faults = 0

    # -- what the caller sees ----------------------------------------------------------------
    @property
    def held(self) -> tuple[Candidate, ...]:
        """Frames held for later, oldest first (their payloads stay with the caller)."""
        return tuple(self._held)

    @property
    def detector(self) -> DetectorClock:
        handover = int(statistics.median(self._handovers)) if self._handovers else None
        return DetectorClock(self._last_take_ns, self._service_estimate(), handover)

    def _service_estimate(self) -> int | None:
        """The lower quartile of the recent service samples. A sample is the time between
        two takes as the acks reported them. An ack that comes late makes one sample long
        and the next short; a wait the count reported that was only an ack in flight adds
        idle time to a sample, and nothing shortens one that way. The median followed those
        (a detector thought busy is given its next frame late, idles, and the next samples
        are longer still); the lower quartile does not, and is exact when every take comes
        one service time after the last."""
        if not self._service:
            return None
        ranked = sorted(self._service)
        return ranked[(len(ranked) - 1) // 4]

    def view(self, now_ns: int) -> View:
        """What a policy would see now."""
        return View(
            now_ns=now_ns,
            load=self._load,
            held=tuple(self._held),
            recent_q=tuple(self._recent),
            detector=self.detector,
            max_hold_ns=self.rules.max_hold_ns,
        )

    # -- feeding it ------------------------------------------------------------------------
    def frame(self, frame: Candidate, load: Load, now_ns: int) -> list[Verdict]:
        """Decide on a newly assessed frame; returns every verdict this caused, in order."""
        self._observe(load, now_ns)
        out = self._apply(self.policy.on_tick(self.view(now_ns)), None)
        out += self._decide_new(frame, now_ns)
        out += self._apply(self.policy.on_tick(self.view(now_ns)), None)
        out += self._expire(now_ns)
        return out

    def tick(self, load: Load, now_ns: int) -> list[Verdict]:
        """Let time pass: held frames may be forwarded (the queue drained) or go stale."""
        self._observe(load, now_ns)
        out = self._apply(self.policy.on_tick(self.view(now_ns)), None)
        out += self._expire(now_ns)
        return out

    def next_due_ns(self, now_ns: int) -> int | None:
        """When ``tick`` may decide something with no new input: the policy's next due time
        or a held frame's maximum hold, whichever comes first (None: nothing is held)."""
        if not self._held:
            return None
        times = [f.arrived_ns + self.rules.max_hold_ns for f in self._held]
        due = self.policy.next_due_ns(self.view(now_ns))
        if due is not None:
            times.append(due)
        return max(now_ns + 1, min(times))

    def restart_order(self, floor_ns: int | None = None) -> None:
        """The source started over (a new producer epoch, a clock step): forget the newest
        frame seen. ``floor_ns``: the newest key the detector's buffer holds, below which
        nothing can be forwarded (None: keep the decider's own)."""
        self._newest_seen_ns = None
        if floor_ns is not None:
            self._newest_forwarded_ns = floor_ns

    def refused(self, frame: Candidate) -> Verdict:
        """The detector's buffer refused a forwarded frame: it is dropped after all."""
        self._expected_queued = max(0, (self._expected_queued or 0) - 1)
        self._load = Load(max(0, self._load.queued - 1), self._load.capacity)
        return Verdict(frame, Action.DROP, "refused")

    # -- the rules ---------------------------------------------------------------------------
    def _observe(self, load: Load, now_ns: int) -> None:
        self._now_ns = now_ns
        expected = self._expected_queued
        if expected is not None and load.queued < expected:
            # The producer's time of the take if it has one: the count is only looked at
            # when a frame arrives or a held one is due, so "now" can be a frame period late,
            # and service times measured between such looks come out on that grid.
            taken, last = load.taken_ns, self._last_take_ns
            usable = taken is not None and taken <= now_ns and (last is None or taken > last)
            at = taken if usable and taken is not None else now_ns
            # Only a take the producer dated counts: one noticed by a later look is late
            # by however long that look came after it.
            if usable and self._handed_at is not None and at >= self._handed_at:
                self._handovers.append(at - self._handed_at)
            self._handed_at = None
            if self._waiting_after_take and self._last_take_ns is not None:
                # Busy all along: the takes since the last one came back to back.
                self._service.append((at - self._last_take_ns) // (expected - load.queued))
            self._last_take_ns = at
            self._waiting_after_take = load.queued > 0
        elif load.queued > 0 and expected is not None and expected > 0:
            # A frame forwarded earlier still waits: the detector has been busy since its
            # last take (it never idles with a frame queued). Not a frame handed to a
            # detector that was free by then: it was taken at once, and the count still
            # shows it only until the ack of that take arrives (up to 160 ms later on a
            # loaded machine, measured); counted as a wait, the idle time before it became
            # a service time, and the clock ran slow until the detector idled most of the
            # time (N = 1). Until a service time is known every wait counts.
            self._waiting_after_take = self._last_take_ns is not None and (
                self._handed_at is None or not self._service
            )
        elif load.queued == 0:
            self._waiting_after_take = False
        self._expected_queued = load.queued
        self._load = load

    def _decide_new(self, frame: Candidate, now_ns: int) -> list[Verdict]:
        newest = self._newest_seen_ns
        if newest is not None and frame.timestamp_ns <= newest:
            return [Verdict(frame, Action.DROP, "out-of-order")]
        self._newest_seen_ns = frame.timestamp_ns
        if frame.q is None:
            rule = self.rules.gyro_missing
            go = rule is GyroMissing.ACCEPT or (rule is GyroMissing.IDLE and self._load.idle)
            action = Action.FORWARD if go else Action.DROP
            reason = frame.unpaired or f"gyro-missing-{rule.value}"
            return self._apply([Verdict(frame, action, reason)], frame)
        if frame.q < self.rules.q_min:
            verdicts = [Verdict(frame, Action.DROP, "below-minimum")]
        else:
            verdicts = self._apply(self.policy.on_frame(frame, self.view(now_ns)), frame)
        self._recent.append(frame.q)
        return verdicts

    def _apply(self, verdicts: Iterable[Verdict], new: Candidate | None) -> list[Verdict]:
        out: list[Verdict] = []
        open_ = {f.timestamp_ns for f in self._held}
        if new is not None:
            open_.add(new.timestamp_ns)
        for verdict in verdicts:
            key = verdict.frame.timestamp_ns
            if key not in open_:
                self.policy_faults += 1  # a frame it does not hold, or a second verdict
                continue
            held = any(f.timestamp_ns == key for f in self._held)
            if verdict.action is Action.HOLD:
                if not held:
                    self._held.append(verdict.frame)
                    self._held.sort(key=lambda f: f.timestamp_ns)
                out.append(verdict)
                open_.discard(key)
                continue
            open_.discard(key)
            self._held = [f for f in self._held if f.timestamp_ns != key]
            if verdict.action is Action.FORWARD:
                last = self._newest_forwarded_ns
                if last is not None and key <= last:
                    out.append(Verdict(verdict.frame, Action.DROP, "out-of-order"))
                    continue
                out.append(verdict)
                out += self._forwarded(key)
            else:
                out.append(verdict)
        if new is not None and new.timestamp_ns in open_:
            self.policy_faults += 1
            out.append(Verdict(new, Action.DROP, "no-verdict"))
        return out

    def _forwarded(self, key: int) -> list[Verdict]:
        if self._load.queued == 0 and self._detector_free():
            self._handed_at = self._now_ns  # nothing else to take: the next take is this
        self._newest_forwarded_ns = key
        self._load = Load(self._load.queued + 1, self._load.capacity)
        self._expected_queued = (self._expected_queued or 0) + 1
        older = [f for f in self._held if f.timestamp_ns < key]
        self._held = [f for f in self._held if f.timestamp_ns > key]
        return [Verdict(f, Action.DROP, "superseded") for f in older]

    def _detector_free(self) -> bool:
        """Whether the detector should be done with its last frame by now (by the service
        time measured; unknown counts as free)."""
        service = self.detector.service_ns
        last = self._last_take_ns
        return service is None or last is None or self._now_ns >= last + service

    def _expire(self, now_ns: int) -> list[Verdict]:
        limit = self.rules.max_hold_ns
        stale = [f for f in self._held if now_ns - f.arrived_ns >= limit]
        self._held = [f for f in self._held if now_ns - f.arrived_ns < limit]
        return [Verdict(f, Action.DROP, "stale") for f in stale]
