"""``adaptive``: thresholds from the recent qualities, on the detector's processing clock."""

from __future__ import annotations

import random

import pytest

from services.lib.decisions import (
    POLICIES,
    Action,
    AdaptivePolicy,
    Candidate,
    Decider,
    Load,
    Rules,
    make_policy,
)

from .sequences import MS, run_detector


def _adaptive() -> Decider:
    return Decider(make_policy("adaptive"), Rules(max_hold_ns=250 * MS))


def test_adaptive_is_a_policy_by_name() -> None:
    assert "adaptive" in POLICIES
    assert make_policy("adaptive").name == "adaptive"


@pytest.mark.parametrize("capacity", [1, 2, 3])
def test_held_and_queued_frames_never_outnumber_the_queue(capacity: int) -> None:
    rng = random.Random(capacity)
    qualities = [rng.uniform(0.05, 1.0) for _ in range(300)]
    run = run_detector(
        _adaptive(), qualities, frame_period_ns=33 * MS, service_ns=53 * MS, capacity=capacity
    )
    assert run.max_waiting <= capacity
    finals = {v.frame.frame_id for v in run.verdicts if v.action is not Action.HOLD}
    assert len(finals) == len(qualities)  # every frame gets a final verdict


def test_with_one_slot_it_lets_the_detector_idle_rather_than_take_a_blurred_frame() -> None:
    # Every third frame is blurred. The paper's rule (and the camera) takes whatever comes
    # when the queue empties; adaptive skips a blurred frame at the cost of a short idle.
    rng = random.Random(7)
    qualities = [0.05 if i % 3 == 0 else rng.uniform(0.6, 1.0) for i in range(300)]

    def mean_processed_q(policy: str) -> float:
        run = run_detector(
            Decider(make_policy(policy)), qualities,
            frame_period_ns=33 * MS, service_ns=53 * MS, capacity=1,
        )  # fmt: skip
        chosen = [qualities[k - 1] for k in run.processed]
        return sum(chosen) / len(chosen)

    paper, adaptive = mean_processed_q("paper"), mean_processed_q("adaptive")
    assert adaptive > paper + 0.1
    assert mean_processed_q("adaptive") > 0.6  # almost no blurred frame processed


def test_it_measures_the_service_time_and_keeps_the_detector_busy() -> None:
    qualities = [0.8] * 200  # all equally sharp: nothing to wait for
    decider = _adaptive()
    run = run_detector(decider, qualities, frame_period_ns=33 * MS, service_ns=53 * MS, capacity=1)
    assert decider.detector.service_ns == 53 * MS
    # One frame per service time, as many as the detector can process.
    assert len(run.processed) >= 0.95 * 200 * 33 / 53


def test_the_real_time_margin_is_a_high_quantile_of_recent_latencies_less_the_last() -> None:
    # Latency = the mediator's clock at the decision minus the camera's stamp (any constant
    # offset cancels). Every frame arrives 1 ms after its stamp; what varies is the wait for
    # its gyro samples, after which it is decided: that is the latency that counts.
    decider = _adaptive()
    policy = decider.policy
    assert isinstance(policy, AdaptivePolicy)
    offset = 5_000 * MS
    for i, lag_ms in enumerate([10] * 6 + [60] * 2 + [10]):
        ts = i * 33 * MS
        arrived = ts + offset + MS
        decider.frame(Candidate(ts, i + 1, 0.9, arrived), Load(0, 2), ts + offset + lag_ms * MS)
    # Next frame: one period after this one's exposure, decided up to 60 ms after it, where
    # this one took 10 ms: 50 ms later than one period after this decision.
    assert policy.margin_ns() == 50 * MS


def test_without_latency_spread_there_is_no_margin() -> None:
    decider = _adaptive()
    policy = decider.policy
    assert isinstance(policy, AdaptivePolicy)
    for i in range(20):
        ts = i * 33 * MS
        decider.frame(Candidate(ts, i + 1, 0.9, ts + 12 * MS), Load(0, 2), ts)
    assert policy.margin_ns() == 0
