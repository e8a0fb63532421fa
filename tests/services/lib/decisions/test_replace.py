"""``replace``: hold the best frames, one per free slot, forward them as the detector needs."""

from __future__ import annotations

import random

import pytest

from services.lib.decisions import Action, Decider, Rules, make_policy

from .sequences import MS, play, run_detector


def _replace(max_hold_ms: float = 250.0) -> Decider:
    return Decider(make_policy("replace"), Rules(max_hold_ns=int(max_hold_ms * MS)))


def test_idle_detector_gets_the_frame_at_once() -> None:
    play(_replace(), "frame t=0 f=1 q=0.2 queue=0/2 -> 1 forward idle")


def test_busy_detector_holds_the_sharpest_and_forwards_it_when_the_queue_empties() -> None:
    play(
        _replace(),
        """
        frame t=0  f=1 q=0.2 queue=0/2 -> 1 forward idle
        frame t=10 f=2 q=0.3 queue=1/2 -> 2 hold held               # one slot free: one held
        frame t=20 f=3 q=0.6 queue=1/2 -> 2 drop replaced ; 3 hold held
        frame t=30 f=4 q=0.5 queue=1/2 -> 4 drop worse-than-held
        tick  t=35           queue=1/2 -> -
        tick  t=40           queue=0/2 -> 3 forward forwarded-held  # the detector took one
        """,
    )


def test_equal_quality_prefers_the_newer_frame() -> None:
    play(
        _replace(),
        """
        frame t=0  f=1 q=0.5 queue=1/2 -> 1 hold held
        frame t=10 f=2 q=0.5 queue=1/2 -> 1 drop replaced ; 2 hold held
        """,
    )


def test_one_candidate_is_held_for_each_free_slot() -> None:
    play(
        _replace(),
        """
        frame t=0  f=1 q=0.4 queue=1/3 -> 1 hold held
        frame t=10 f=2 q=0.2 queue=1/3 -> 2 hold held              # two slots free
        frame t=20 f=3 q=0.3 queue=1/3 -> 2 drop replaced ; 3 hold held
        frame t=30 f=4 q=0.1 queue=1/3 -> 4 drop worse-than-held
        tick  t=40           queue=0/3 -> 1 forward forwarded-held  # oldest first
        tick  t=41           queue=1/3 -> -
        tick  t=80           queue=0/3 -> 3 forward forwarded-held
        """,
    )


def test_a_frame_held_for_the_maximum_fills_a_free_slot() -> None:
    play(
        _replace(max_hold_ms=50),
        """
        frame t=0  f=1 q=0.4 queue=1/2 -> 1 hold held
        tick  t=49           queue=1/2 -> -
        tick  t=50           queue=1/2 -> 1 forward held-max
        frame t=60 f=2 q=0.9 queue=2/2 -> 2 drop queue-full
        """,
    )


def test_slots_taken_by_someone_else_let_the_worst_held_frames_go() -> None:
    play(
        _replace(),
        """
        frame t=0  f=1 q=0.4 queue=1/3 -> 1 hold held
        frame t=10 f=2 q=0.2 queue=1/3 -> 2 hold held
        tick  t=20           queue=2/3 -> 2 drop no-slot
        """,
    )


def test_held_frames_older_than_a_forwarded_frame_are_superseded() -> None:
    # A gyro-missing frame accepted at once overtakes the held ones.
    from services.lib.decisions import GyroMissing

    play(
        Decider(make_policy("replace"), Rules(gyro_missing=GyroMissing.ACCEPT)),
        """
        frame t=0  f=1 q=0.4 queue=1/2 -> 1 hold held
        frame t=10 f=2 q=-   queue=1/2 -> 2 forward gyro-missing-accept ; 1 drop superseded
        """,
    )


@pytest.mark.parametrize("capacity", [2, 3])
def test_replace_uses_every_queue_slot(capacity: int) -> None:
    # A detector slower than the hold time: every slot ends up holding a chosen frame.
    rng = random.Random(capacity)
    qualities = [rng.uniform(0.05, 1.0) for _ in range(200)]
    run = run_detector(
        _replace(max_hold_ms=40),
        qualities,
        frame_period_ns=10 * MS,
        service_ns=100 * MS,
        capacity=capacity,
    )
    assert run.max_queued == capacity
    assert run.max_waiting == capacity + 0  # held + queued never exceeds the queue size
    finals = {v.frame.frame_id: v for v in run.verdicts if v.action is not Action.HOLD}
    assert len(finals) == len(qualities)  # every frame gets a final verdict


@pytest.mark.parametrize("capacity", [2, 3])
def test_replace_waits_with_one_candidate_per_free_slot_at_the_pipeline_pace(
    capacity: int,
) -> None:
    # The experiment's working point: the detector needs 1.6 frame periods per frame.
    rng = random.Random(10 + capacity)
    qualities = [rng.uniform(0.05, 1.0) for _ in range(300)]
    run = run_detector(
        _replace(),
        qualities,
        frame_period_ns=33 * MS,
        service_ns=53 * MS,
        capacity=capacity,
    )
    assert run.max_waiting == capacity
    processed_q = [qualities[k - 1] for k in run.processed]
    # Chosen frames are sharper than the stream on average: the selection works.
    assert sum(processed_q) / len(processed_q) > sum(qualities) / len(qualities)
    assert len(run.processed) >= 0.9 * len(qualities) * 33 / 53


def test_replace_decides_every_frame_exactly_once_finally() -> None:
    rng = random.Random(7)
    qualities = [rng.uniform(0.05, 1.0) for _ in range(100)]
    run = run_detector(
        _replace(max_hold_ms=60),
        qualities,
        frame_period_ns=10 * MS,
        service_ns=35 * MS,
        capacity=2,
    )
    finals = [v.frame.frame_id for v in run.verdicts if v.action is not Action.HOLD]
    assert sorted(finals) == list(range(1, 101))
    forwarded = [v.frame.frame_id for v in run.verdicts if v.action is Action.FORWARD]
    assert forwarded == sorted(forwarded)
    assert run.processed == forwarded
