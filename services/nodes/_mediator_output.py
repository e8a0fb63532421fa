"""The mediator's outputs: the decider's verdicts carried out (see ``services.nodes.mediator``).

Frames forwarded go to mediator/images, whose flow-controlled subscriber (the detector) is
the load indicator; every decision goes to mediator/decisions. A record never waits and
never raises out of the mediator: one refused (a subscriber flow-controls the buffer) or
rejected is counted (``decisions_dropped``, logged) and dropped.
"""

from __future__ import annotations

import collections
import logging
import time
from dataclasses import dataclass

from middleware import (
    ClosedError,
    FlowControlRefused,
    FramegateError,
    Node,
    Producer,
    Retention,
    SubscriptionInfo,
    now_ns,
)
from services.lib.decisions import Action, Candidate, Decider, Load, Verdict, tightest_load
from services.lib.messages import DecisionRecord, FrameMeta
from services.nodes._runtime import Monotonic


@dataclass(frozen=True, slots=True)
class Frame:
    """A frame the decider knows: its candidate, and the bytes to forward it with."""

    meta: FrameMeta
    payload: bytes
    metadata: bytes
    candidate: Candidate


def _consumer(sub: SubscriptionInfo | None) -> str:
    """The flow-controlled consumer as a log line names it (its node, as ``info`` shows)."""
    if sub is None:
        return "the consumer"
    where = f"{sub.node}@{sub.host}" if sub.node and sub.host else sub.node or sub.subscription_id
    return f"the consumer {where}"


def _wall_ns(monotonic_ns: int | None) -> int | None:
    """A time of this process's monotonic clock (the producer's, the decider's) on the wall
    clock of the frames' stamps, so that a record can be set beside the detector's."""
    if monotonic_ns is None:
        return None
    return now_ns() - (time.monotonic_ns() - monotonic_ns)


class Output:
    """mediator/images and mediator/decisions, and the frames whose bytes are kept."""

    def __init__(
        self, node: Node, *, policy: str, b0_px: float, horizon_s: float, log: logging.Logger
    ) -> None:
        # Frames are taken up to ``horizon_s`` ahead (the mediator's own bound): the buffer
        # must take what the mediator takes.
        self.images: Producer = node.offer(
            "images",
            kind="frame",
            retention=Retention(max_count=64, max_bytes=256 * 2**20),
            horizon_s=horizon_s,
        )
        self.decisions: Producer = node.offer(
            "decisions", kind="decision", retention=Retention(max_count=100_000)
        )
        self.log = log
        self._policy = policy
        self._b0_px = b0_px
        self.newest_put_ns: int | None = None
        # The flow-controlled consumer (the detector): whether one was ever seen, whether
        # its subscription has lapsed, and the frames last seen waiting in its queue.
        self._consumer_capacity: int | None = None
        self._consumer: SubscriptionInfo | None = None  # the last one seen, for the log
        self.lapsed = False
        self._queued_frames: collections.deque[Frame] = collections.deque()
        self.last_load = Load(0, 0)
        self._keys = Monotonic()
        self.pending: dict[int, Frame] = {}  # frames the decider holds, by key
        self.skipped = collections.Counter[str]()
        self.reasons = collections.Counter[str]()  # every verdict recorded, by reason
        self.forwarded = 0
        self.decisions_dropped = 0
        self._policy_faults_logged = 0

    def load(self) -> Load:
        """The detector's load; full while the subscription of a consumer we had lapsed.

        A flow-controlled consumer that stops answering (stopped, frozen, partitioned)
        loses its subscription after the lease; to the producer that looks like no
        consumer at all (load 0), and frames forwarded then are lost without a trace.
        So once a flow-controlled consumer has been seen, its absence means full: frames
        are recorded ``consumer-lapsed`` (not forwarded) until a consumer is back, and the
        frames that were waiting in its queue when it lapsed get a ``consumer-lapsed``
        record too. A mediator that never had one (uncontrolled wiring) forwards as before.
        """
        load, tightest = tightest_load(self.images.subscriptions())
        if tightest is not None:
            if self.lapsed:
                self.lapsed = False
                self.log.warning("%s subscribes again: forwarding again", _consumer(tightest))
            self._consumer = tightest
            self._consumer_capacity = tightest.queue_size
            self.last_load = load
            # The newest ``queued`` frames forwarded are those not acked yet; older ones
            # were taken. Frames forwarded after this look join them (``_put``), so a lapse
            # seen later records every frame it may have cost, not only those counted here.
            while len(self._queued_frames) > load.queued:
                self._queued_frames.popleft()
            return load
        if self._consumer_capacity is None:
            return load
        full = Load(self._consumer_capacity, self._consumer_capacity)
        if not self.lapsed:
            self.lapsed = True
            waiting = list(self._queued_frames)
            self.log.warning(
                "%s no longer subscribes (it stopped, exited or became unreachable); frames "
                "are recorded consumer-lapsed, not forwarded, until a consumer subscribes "
                "(%s waiting in its queue)",
                _consumer(self._consumer),
                "1 forwarded frame was" if len(waiting) == 1 else f"{len(waiting)} were",
            )
            for frame in waiting:
                self.record(frame, Verdict(frame.candidate, Action.DROP, "consumer-lapsed"), full)
            self._queued_frames.clear()
        self.last_load = full
        return full

    def carry_out(self, decider: Decider, verdicts: list[Verdict], load: Load) -> None:
        """Put forwarded frames, record every verdict with the load the decider saw."""
        for verdict in verdicts:
            key = verdict.frame.timestamp_ns
            frame = self.pending.get(key)
            if verdict.action is not Action.HOLD:
                self.pending.pop(key, None)
            if frame is None:
                continue
            # The decision's time is before the put: the detector may take the frame while
            # the put still runs (the first one took over 40 ms under load, measured), and a
            # record timed after it says the frame went out later than it did.
            decided_ns = now_ns()
            if verdict.action is Action.FORWARD and (why := self._put(frame)) is not None:
                verdict = decider.refused(verdict.frame)
                if why == "consumer-lapsed":
                    verdict = Verdict(verdict.frame, Action.DROP, why)
            self.record(frame, verdict, load, decided_ns)
        if decider.policy_faults > self._policy_faults_logged:
            self._policy_faults_logged = decider.policy_faults
            self.log.warning(
                "policy %s broke its contract (%d times so far)",
                self._policy,
                decider.policy_faults,
            )

    def _put(self, frame: Frame) -> str | None:
        """Forward a frame: None once a consumer is told of it, else why not (``refused``;
        ``consumer-lapsed``: stored, but the consumer we had was not registered at that
        moment, a lapse between two looks at the load, so no notification will reach it)."""
        try:
            notified = self.images.put(frame.meta.timestamp_ns, frame.payload, frame.metadata)
        except FlowControlRefused:
            return "refused"
        except ClosedError:
            return "refused"  # a stop came; its record has nowhere to go either
        except FramegateError as exc:
            self.log.warning("cannot forward frame %d: %s", frame.meta.frame_id, exc)
            return "refused"
        self.newest_put_ns = frame.meta.timestamp_ns
        if notified == 0 and self._consumer_capacity is not None:
            return "consumer-lapsed"
        self._queued_frames.append(frame)
        while len(self._queued_frames) > max(1, self._consumer_capacity or 1):
            self._queued_frames.popleft()
        return None

    def summary(self) -> str:
        """The service's last log line: what became of the frames it decided on."""
        reasons = ", ".join(f"{r} {n}" for r, n in self.reasons.most_common())
        skipped = ", ".join(f"{r} {n}" for r, n in self.skipped.most_common())
        # The reasons break down the frames decided, not those forwarded: beside the
        # forwarded count they read as its parts, and summed to more than it.
        return (
            f"{sum(self.reasons.values())} frames decided ({reasons or 'none'}), "
            f"{self.forwarded} forwarded; skipped: {skipped or 'none'}"
        )

    def record(
        self, frame: Frame, verdict: Verdict, load: Load, decided_ns: int | None = None
    ) -> None:
        """Record a verdict: ``decided_ns`` is when it was reached (wall clock; now if
        None), from which the record's latency counts."""
        candidate = frame.candidate
        decided_ns = now_ns() if decided_ns is None else decided_ns
        self.reasons[verdict.reason] += 1
        self.forwarded += verdict.action is Action.FORWARD
        self.write(
            DecisionRecord(
                frame_timestamp_ns=candidate.timestamp_ns,
                frame_id=candidate.frame_id,
                blur_px=candidate.blur_px,
                quality=candidate.q,
                load=load.fill,
                accepted=verdict.action is Action.FORWARD,
                reason=verdict.reason,
                policy=self._policy,
                b0_px=self._b0_px,
                latency_ns=decided_ns - frame.meta.exposure.end_ns,
                take_seen_ns=_wall_ns(load.taken_ns),
            )
        )

    def count(self, reason: str) -> None:
        """Count a frame decided without a quality for ``reason`` (``info``'s skipped)."""
        self.skipped[reason] += 1
        self.images.count_skip(reason)

    def skip(self, key_ns: int, frame_id: int, reason: str, detail: str) -> None:
        """A frame not decided at all (bad, late, lapsed): counted, logged sparsely, recorded."""
        self.count(reason)
        count = self.skipped[reason]
        if count & (count - 1) == 0:  # 1, 2, 4, 8...: visible, never a flood
            self.log.warning("skipping frame %d (%s, %d so far): %s", key_ns, reason, count, detail)
        self.write(
            DecisionRecord(
                frame_timestamp_ns=key_ns,
                frame_id=frame_id,
                blur_px=None,
                quality=None,
                load=self.last_load.fill,
                accepted=False,
                reason=reason,
                policy=self._policy,
                b0_px=self._b0_px,
                latency_ns=0,
            )
        )

    def write(self, record: DecisionRecord) -> None:
        """Put a decision record; a refusal or rejection is counted, never raised."""
        key = self._keys.next()
        try:
            self.decisions.put(key, b"", record.metadata(key))
        except ClosedError:
            return  # a stop came: the node closes its buffers before its handlers end
        except FramegateError as exc:
            self.decisions_dropped += 1
            n = self.decisions_dropped
            if n & (n - 1) == 0:
                self.log.warning("decision record dropped (%d so far): %s", n, exc)
