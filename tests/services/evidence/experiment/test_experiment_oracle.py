"""The offline-optimal oracle and the discrete-event replay."""

from __future__ import annotations

import itertools

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.evidence.experiment import (
    MARKER_NAMES,
    FrameOutcome,
    QueueModel,
    feasible,
    optimal_schedule,
    replay_policy,
    replay_uncontrolled,
)
from services.evidence.experiment._sweep import marker_counts, oracle_counts
from services.lib.decisions import make_policy

PERIOD = 100


def test_oracle_takes_every_frame_when_the_detector_keeps_up() -> None:
    schedule = optimal_schedule([0, 100, 200], [1, 1, 1], service_ns=50, capacity=1)
    assert schedule.frames == (0, 1, 2) and schedule.value == 3


def test_oracle_skips_a_frame_to_reach_two_better_ones() -> None:
    # Service 150, no waiting place: frame 0 (worth 2) blocks frame 1 (3), not frame 2 (3);
    # frame 1 alone would block frame 2. Best: 0 and 2.
    schedule = optimal_schedule([0, 100, 200], [2, 3, 3], service_ns=150, capacity=0)
    assert schedule.frames == (0, 2) and schedule.value == 5


def test_oracle_uses_the_queue_to_keep_a_frame_waiting() -> None:
    # Service 300 > two periods: with one waiting place frame 1 waits for frame 0.
    assert optimal_schedule([0, 100], [1, 1], service_ns=300, capacity=1).value == 2
    assert optimal_schedule([0, 100], [1, 1], service_ns=300, capacity=0).value == 1


def test_oracle_rejects_arrivals_out_of_order() -> None:
    with pytest.raises(Exception, match="time order"):
        optimal_schedule([100, 0], [1, 1], service_ns=10, capacity=1)


@settings(max_examples=30, deadline=None)
@given(
    st.lists(st.integers(0, 3), min_size=1, max_size=9),
    st.integers(1, 350),
    st.integers(0, 2),
)
def test_oracle_equals_brute_force_over_every_subset(
    values: list[int], service_ns: int, capacity: int
) -> None:
    arrivals = [i * PERIOD for i in range(len(values))]
    best = max(
        sum(values[i] for i in chosen)
        for r in range(len(values) + 1)
        for chosen in itertools.combinations(range(len(values)), r)
        if feasible(arrivals, chosen, service_ns=service_ns, capacity=capacity)
    )
    schedule = optimal_schedule(arrivals, values, service_ns=service_ns, capacity=capacity)
    assert schedule.value == best
    assert feasible(arrivals, schedule.frames, service_ns=service_ns, capacity=capacity)


def _frames(qualities: list[float], marks: list[int]) -> tuple[FrameOutcome, ...]:
    return tuple(
        FrameOutcome(
            frame_id=i,
            arrival_ns=1_000_000 + i * 66_666_667,
            blur_px=None,
            quality=q,
            recognized=frozenset(n for bit, n in enumerate(MARKER_NAMES) if m >> bit & 1),
        )
        for i, (q, m) in enumerate(zip(qualities, marks, strict=True))
    )


@settings(max_examples=20, deadline=None)
@given(
    st.lists(st.tuples(st.floats(0.05, 1.0), st.integers(0, 7)), min_size=2, max_size=60),
    st.integers(1, 3),
    st.sampled_from([1.3, 1.6, 2.0]),
)
def test_oracle_is_never_below_any_policy_on_the_same_run(
    frames: list[tuple[float, int]], queue: int, factor: float
) -> None:
    outcomes = _frames([q for q, _ in frames], [m for _, m in frames])
    model = QueueModel(queue=queue, service_ns=round(factor * 66_666_667))
    oracle = oracle_counts(outcomes, model)
    runs = [replay_uncontrolled(outcomes, model)]
    runs += [
        replay_policy(outcomes, model, make_policy(p))
        for p in ("paper", "replace", "deadline", "adaptive")
    ]
    for processed in runs:
        counts = marker_counts(outcomes, processed)
        for name in MARKER_NAMES:
            assert counts[name] <= oracle[name]
        assert sum(counts.values()) <= oracle["total"]


def test_uncontrolled_replay_drops_frames_while_n_wait() -> None:
    outcomes = _frames([1.0] * 6, [1] * 6)
    # Service 2.5 periods, N = 1: 0 runs, 1 waits, 2 is refused, 3 waits once 1 has
    # started, 4 is refused, 5 arrives as 3 starts (a take comes before an arrival).
    processed = replay_uncontrolled(outcomes, QueueModel(queue=1, service_ns=166_666_667))
    assert processed == (0, 1, 3, 5)
