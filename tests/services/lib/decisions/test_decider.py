"""The rules the decider keeps for every policy (see ``_decider.py``'s docstring)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import pytest

import services.lib.decisions as decisions
from services.lib.decisions import (
    Action,
    Candidate,
    Decider,
    GyroMissing,
    Load,
    Rules,
    Verdict,
    View,
    make_policy,
    queue_load,
)
from services.lib.quality import QualityInputError

from .sequences import MS, play


class HoldEverything:
    """A policy that holds every frame and never lets one go: the decider must."""

    name = "hold-everything"

    def __init__(self) -> None:
        self.views: list[View] = []

    def on_frame(self, frame: Candidate, view: View) -> Sequence[Verdict]:
        self.views.append(view)
        return [Verdict(frame, Action.HOLD, "held")]

    def next_due_ns(self, view: View) -> int | None:
        return None

    def on_tick(self, view: View) -> Sequence[Verdict]:
        return ()


class Broken:
    """A policy that breaks its contract in every way it can."""

    name = "broken"

    def __init__(self) -> None:
        self.stranger = Candidate(999, 999, 0.5, arrived_ns=0)

    def on_frame(self, frame: Candidate, view: View) -> Sequence[Verdict]:
        if frame.frame_id == 1:
            return []  # no verdict at all
        return [
            Verdict(self.stranger, Action.FORWARD, "not-mine"),
            Verdict(frame, Action.DROP, "twice"),
            Verdict(frame, Action.FORWARD, "twice"),
        ]

    def next_due_ns(self, view: View) -> int | None:
        return None

    def on_tick(self, view: View) -> Sequence[Verdict]:
        return [Verdict(self.stranger, Action.DROP, "not-mine")]


def test_a_late_frame_is_dropped_as_out_of_order() -> None:
    play(
        Decider(make_policy("paper")),
        """
        frame t=0  f=5 q=0.9 queue=0/2 -> 5 forward quality>load
        frame t=10 f=3 q=0.9 queue=0/2 -> 3 drop out-of-order
        frame t=20 f=5 q=0.9 queue=0/2 -> 5 drop out-of-order   # a duplicate key
        frame t=30 f=6 q=0.9 queue=0/2 -> 6 forward quality>load
        """,
    )


def test_restart_order_lets_a_restarted_source_be_decided_at_once() -> None:
    """A far-future key would otherwise make every later frame ``out-of-order``."""
    decider = Decider(make_policy("paper"))
    idle = Load(0, 2)
    [first] = decider.frame(Candidate(1_000, 1, 0.9, arrived_ns=0), idle, 0)
    [rogue] = decider.frame(Candidate(10**15, 2, 0.9, arrived_ns=1), Load(1, 2), 1)
    assert (first.action, rogue.action) == (Action.FORWARD, Action.FORWARD)
    [late] = decider.frame(Candidate(2_000, 3, 0.9, arrived_ns=2), idle, 2)
    assert late.reason == "out-of-order"
    decider.restart_order(floor_ns=1_000)  # the detector's buffer still holds key 1000
    [again] = decider.frame(Candidate(3_000, 4, 0.9, arrived_ns=3), idle, 3)
    assert (again.action, again.reason) == (Action.FORWARD, "quality>load")
    [older] = decider.frame(Candidate(500, 5, 0.9, arrived_ns=4), idle, 4)
    assert older.reason == "out-of-order"  # below the floor: never forwarded


@pytest.mark.parametrize(
    ("rule", "idle", "busy"),
    [
        (GyroMissing.IDLE, "forward", "drop"),
        (GyroMissing.ACCEPT, "forward", "forward"),
        (GyroMissing.REJECT, "drop", "drop"),
    ],
)
def test_the_gyro_missing_rule(rule: GyroMissing, idle: str, busy: str) -> None:
    play(
        Decider(make_policy("paper"), Rules(gyro_missing=rule)),
        f"""
        frame t=0  f=1 q=- queue=0/2 -> 1 {idle} gyro-missing-{rule.value}
        frame t=10 f=2 q=- queue=1/2 -> 2 {busy} gyro-missing-{rule.value}
        """,
    )


def test_the_default_gyro_missing_rule_is_idle() -> None:
    assert Rules().gyro_missing is GyroMissing.DEFAULT
    assert GyroMissing.DEFAULT.value == "idle"


def test_a_frame_held_past_the_maximum_is_dropped_as_stale() -> None:
    play(
        Decider(HoldEverything(), Rules(max_hold_ns=100 * MS)),
        """
        frame t=0   f=1 q=0.5 queue=1/2 -> 1 hold held
        frame t=50  f=2 q=0.5 queue=1/2 -> 2 hold held
        tick  t=99            queue=1/2 -> -
        tick  t=100           queue=1/2 -> 1 drop stale
        frame t=160 f=3 q=0.5 queue=1/2 -> 3 hold held ; 2 drop stale
        """,
    )


def test_a_refused_forward_becomes_a_drop_and_the_count_is_corrected() -> None:
    decider = Decider(make_policy("paper"))
    frame = Candidate(1, 1, 0.9, arrived_ns=0)
    [verdict] = decider.frame(frame, Load(0, 2), 0)
    assert verdict.action is Action.FORWARD
    assert decider.refused(frame) == Verdict(frame, Action.DROP, "refused")
    # The refused frame never reached the queue: an unchanged count is not a take.
    decider.tick(Load(0, 2), 10 * MS)
    assert decider.detector.last_take_ns is None


def test_a_policy_that_breaks_its_contract_is_repaired_and_counted() -> None:
    decider = Decider(Broken())
    first = Candidate(1, 1, 0.5, arrived_ns=0)
    assert decider.frame(first, Load(0, 2), 0) == [Verdict(first, Action.DROP, "no-verdict")]
    second = Candidate(2, 2, 0.5, arrived_ns=MS)
    assert decider.frame(second, Load(0, 2), MS) == [Verdict(second, Action.DROP, "twice")]
    assert decider.held == ()
    assert decider.policy_faults == 1 + 2 + 2 + 2  # each tick touches a stranger too


def test_the_processing_clock_estimates_the_detector_service_time() -> None:
    decider = Decider(make_policy("paper"))
    assert decider.detector.service_ns is None
    t = 0
    decider.frame(Candidate(1, 1, 0.9, t), Load(0, 3), t)  # forwarded: expect 1 queued
    decider.frame(Candidate(2, 2, 0.9, t + 1), Load(1, 3), t + 1)  # expect 2
    decider.frame(Candidate(3, 3, 0.9, t + 2), Load(2, 3), t + 2)  # expect 3
    decider.tick(Load(2, 3), 40 * MS)  # one taken, two still waiting
    assert decider.detector.last_take_ns == 40 * MS
    decider.tick(Load(1, 3), 90 * MS)
    decider.tick(Load(0, 3), 140 * MS)
    assert decider.detector.service_ns == 50 * MS
    decider.tick(Load(0, 3), 500 * MS)  # idle time is not service time
    assert decider.detector.service_ns == 50 * MS


def test_takes_are_dated_by_the_producer_when_the_count_is_looked_at_late() -> None:
    """The mediator looks at the count only when a frame arrives (every 66 ms here) or a
    held frame is due, so takes 50 ms apart measure 66 ms or half of 66 between looks.
    With the producer's time of each take (``Load.taken_ns``) the estimate is exact."""
    takes_ms = (40, 90, 140, 190, 240)
    for dated in (False, True):
        decider = Decider(make_policy("paper"))
        for i in range(5):  # five frames forwarded at once, all waiting
            decider.frame(Candidate(i + 1, i + 1, 0.9, i), Load(i, 5), i)
        for look_ms in (66, 132, 198, 264):
            seen = [t for t in takes_ms if t <= look_ms]
            taken = seen[-1] * MS if dated else None
            decider.tick(Load(5 - len(seen), 5, taken), look_ms * MS)
        clock = decider.detector
        if dated:
            assert (clock.last_take_ns, clock.service_ns) == (240 * MS, 50 * MS)
        else:
            # On the looks' grid (66 or 33 ms between them), never the 50 ms it was.
            assert (clock.last_take_ns, clock.service_ns) == (264 * MS, 33 * MS)


def test_a_take_time_from_the_future_or_the_past_is_not_trusted() -> None:
    decider = Decider(make_policy("paper"))
    decider.frame(Candidate(1, 1, 0.9, 0), Load(0, 2), 0)
    decider.frame(Candidate(2, 2, 0.9, 1), Load(1, 2), 1)
    decider.tick(Load(1, 2, taken_ns=500 * MS), 100 * MS)  # after "now": the look's time
    assert decider.detector.last_take_ns == 100 * MS
    decider.tick(Load(0, 2, taken_ns=50 * MS), 150 * MS)  # before the last take: the look's
    assert decider.detector.last_take_ns == 150 * MS


def test_a_policy_sees_the_recent_qualities_and_the_hold_limit() -> None:
    policy = HoldEverything()
    decider = Decider(policy, Rules(max_hold_ns=7, recent_count=2))
    for i, q in enumerate([0.1, 0.2, 0.3], 1):
        decider.frame(Candidate(i, i, q, arrived_ns=0), Load(1, 2), 0)
    assert [v.recent_q for v in policy.views] == [(), (0.1,), (0.1, 0.2)]
    assert policy.views[-1].max_hold_ns == 7
    assert [f.frame_id for f in policy.views[-1].held] == [1, 2]


@pytest.mark.parametrize("q", [0.0, -0.5, 1.5, math.nan, math.inf])
def test_a_candidate_refuses_a_quality_outside_the_unit_interval(q: float) -> None:
    with pytest.raises(QualityInputError, match=r"quality must be in \(0, 1\]"):
        Candidate(1, 1, q, arrived_ns=0)


def test_load_is_queued_over_capacity_with_free_slots() -> None:
    assert (Load(1, 4).fill, Load(1, 4).free, Load(1, 4).idle) == (0.25, 3, False)
    assert (Load(0, 2).fill, Load(0, 2).idle) == (0.0, True)
    assert Load(5, 4).fill == 1.0 and Load(5, 4).free == 0
    assert (Load(0, 0).fill, Load(0, 0).free, Load(0, 0).idle) == (0.0, 1, True)
    with pytest.raises(QualityInputError, match="queue counts must be >= 0"):
        Load(-1, 2)


def test_queue_load_is_pending_over_capacity() -> None:
    assert queue_load(0, 4) == 0.0
    assert queue_load(3, 4) == 0.75
    assert queue_load(9, 4) == 1.0
    with pytest.raises(QualityInputError, match="capacity must be positive"):
        queue_load(1, 0)


def test_policies_are_made_by_name() -> None:
    assert {"paper", "replace"} <= set(decisions.POLICIES)
    assert make_policy("replace").name == "replace"
    assert make_policy(decisions.DEFAULT_POLICY).name == "paper"
    with pytest.raises(QualityInputError, match=r"unknown policy 'best': use one of .*paper"):
        make_policy("best")
    # A misspelt one, as `framegate experiment --sweep --policies papr` gives it.
    with pytest.raises(QualityInputError, match=r"'papr' \(did you mean 'paper'\?\): use one"):
        make_policy("papr")


def test_all_is_complete_and_sorted_like_ruff_sorts_it() -> None:
    names = decisions.__all__
    constants = [n for n in names if n.isupper()]
    assert names == sorted(constants) + sorted(n for n in names if not n.isupper())
    for name in names:
        assert hasattr(decisions, name), name


def test_the_processing_clock_measures_the_service_time_with_a_queue_of_one() -> None:
    # N = 1: a take always empties the queue, so only a frame forwarded after a take and
    # still seen waiting at a later look shows that the detector was busy all along.
    decider = Decider(make_policy("paper"))
    decider.frame(Candidate(1, 1, 0.9, 0), Load(0, 1), 0)  # forwarded to an idle detector
    decider.tick(Load(0, 1), 10 * MS)  # taken
    decider.frame(Candidate(2, 2, 0.9, 20 * MS), Load(0, 1), 20 * MS)  # forwarded, waits
    decider.tick(Load(1, 1), 30 * MS)  # still waiting: the detector is busy
    decider.tick(Load(0, 1), 60 * MS)  # taken the moment the detector was free
    assert decider.detector.service_ns == 50 * MS
    decider.frame(Candidate(3, 3, 0.9, 200 * MS), Load(0, 1), 200 * MS)  # idle: taken at once
    decider.tick(Load(0, 1), 210 * MS)  # never seen waiting: not a service time
    assert decider.detector.service_ns == 50 * MS


def test_the_hand_over_is_from_forwarding_to_an_idle_detector_until_the_take_seen() -> None:
    decider = Decider(make_policy("paper"))
    # Nothing queued, nothing taken yet: the frame goes to an idle detector at 100 ms.
    verdicts = decider.frame(Candidate(1, 1, 0.9, arrived_ns=100 * MS), Load(0, 1), 100 * MS)
    assert [v.action for v in verdicts] == [Action.FORWARD]
    assert decider.detector.handover_ns is None
    # The producer saw the detector take it at 112 ms; the mediator looks at 130 ms.
    decider.tick(Load(0, 1, taken_ns=112 * MS), 130 * MS)
    assert decider.detector.handover_ns == 12 * MS


def test_a_take_only_noticed_by_a_later_look_is_no_hand_over_sample() -> None:
    decider = Decider(make_policy("paper"))
    decider.frame(Candidate(1, 1, 0.9, arrived_ns=100 * MS), Load(0, 1), 100 * MS)
    decider.tick(Load(0, 1), 130 * MS)  # taken some time before 130 ms: when is unknown
    assert decider.detector.handover_ns is None
