"""The mediator's decision latency in the replay: recorded or drawn as measured, and used."""

from __future__ import annotations

from collections.abc import Sequence

from services.evidence.experiment._frames import FrameOutcome
from services.evidence.experiment._latency import (
    MEASURED_LATENCY_MS,
    decision_latencies,
    measured_latencies,
)
from services.evidence.experiment._replay import QueueModel, replay_policy
from services.lib.decisions import Action, Verdict, View
from services.lib.decisions import Candidate as DecisionCandidate
from services.lib.messages import DecisionRecord

MS = 1_000_000
PERIOD = 50 * MS


def _frames(count: int) -> tuple[FrameOutcome, ...]:
    return tuple(
        FrameOutcome(i + 1, (i + 1) * PERIOD, 1.0, 0.8, frozenset({"large"})) for i in range(count)
    )


class _Recorder:
    """Holds every frame one tick, and records when it was asked what."""

    name = "recorder"

    def __init__(self) -> None:
        self.decided: dict[int, int] = {}
        self.ticks: list[int] = []

    def on_frame(self, frame: DecisionCandidate, view: View) -> Sequence[Verdict]:
        self.decided[frame.frame_id] = view.now_ns
        return [Verdict(frame, Action.HOLD, "held")]

    def next_due_ns(self, view: View) -> int | None:
        return None

    def on_tick(self, view: View) -> Sequence[Verdict]:
        self.ticks.append(view.now_ns)
        return [Verdict(f, Action.FORWARD, "go") for f in view.held]


def test_the_replay_decides_each_frame_its_latency_after_it_arrives() -> None:
    frames = _frames(6)
    latencies = {1: 5 * MS, 2: 30 * MS, 3: 80 * MS, 4: 0, 5: 12 * MS, 6: 7 * MS}
    policy = _Recorder()
    replay_policy(frames, QueueModel(queue=2, service_ns=40 * MS), policy, latencies)
    arrival = {f.frame_id: f.arrival_ns for f in frames}
    # Frame 4 arrives at 200 ms but frame 3 was decided at 230 ms: never before the last.
    want = {1: 55, 2: 130, 3: 230, 4: 230, 5: 262, 6: 307}
    assert {k: v // MS for k, v in policy.decided.items()} == want
    # While it waits for a frame's gyro samples the mediator forwards nothing: no tick
    # falls between a frame's arrival and its decision.
    for frame_id, decided in policy.decided.items():
        start = max(arrival[frame_id], policy.decided.get(frame_id - 1, 0))
        assert not [t for t in policy.ticks if start <= t < decided]


def test_without_latencies_each_frame_is_decided_on_arrival() -> None:
    frames = _frames(4)
    policy = _Recorder()
    replay_policy(frames, QueueModel(queue=2, service_ns=40 * MS), policy)
    assert policy.decided == {f.frame_id: f.arrival_ns for f in frames}


def test_measured_latencies_are_repeatable_and_within_the_measured_range() -> None:
    frames = _frames(200)
    first, again = measured_latencies(frames, 3), measured_latencies(frames, 3)
    assert first == again
    assert first != measured_latencies(frames, 4)
    low, high = MEASURED_LATENCY_MS[0][1] * MS, MEASURED_LATENCY_MS[-1][1] * MS
    assert all(low <= v <= high for v in first.values())
    ranked = sorted(first.values())
    assert ranked[100] < 20 * MS  # the median is ~15 ms


def _record(frame_id: int, reason: str, latency_ns: int) -> DecisionRecord:
    return DecisionRecord(
        frame_timestamp_ns=frame_id, frame_id=frame_id, blur_px=1.0, quality=0.8, load=0.0,
        accepted=reason == "quality>load", reason=reason, policy="paper", b0_px=5.0,
        latency_ns=latency_ns,
    )  # fmt: skip


def test_decision_latencies_leave_out_frames_skipped_undecided() -> None:
    records = [
        _record(1, "quality>load", 12 * MS),
        _record(2, "quality<=load", 9 * MS),
        _record(3, "deadline", 150 * MS),  # a held frame's first record: its hold
        _record(4, "bad-metadata", 0),
    ]
    assert decision_latencies(records) == {1: 12 * MS, 2: 9 * MS, 3: 150 * MS}
