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
    Verdict,
    make_policy,
)

from .sequences import MS, QueueRun, run_detector


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


def _with_service_measured() -> Decider:
    """N = 1: frames 1 and 2 taken at 0 and 100 ms while frame 2 waited (service 100 ms);
    frame 3, forwarded at 190 ms, is planned to be taken when frame 2 is done, at 200 ms."""
    decider = _adaptive()
    decider.frame(Candidate(70 * MS, 1, 0.8, 0), Load(0, 1), 0)
    decider.frame(Candidate(140 * MS, 2, 0.8, 70 * MS), Load(0, 1, taken_ns=0), 70 * MS)
    decider.tick(Load(1, 1, taken_ns=0), 80 * MS)
    decider.tick(Load(0, 1, taken_ns=100 * MS), 140 * MS)
    assert decider.detector.service_ns == 100 * MS
    out = decider.frame(
        Candidate(210 * MS, 3, 0.8, 190 * MS), Load(0, 1, taken_ns=100 * MS), 190 * MS
    )
    assert [(v.frame.frame_id, v.action) for v in out] == [(3, Action.FORWARD)]
    return decider


def _verdicts(verdicts: list[Verdict]) -> list[tuple[int, Action, str]]:
    return [(v.frame.frame_id, v.action, v.reason) for v in verdicts]


def test_a_take_counted_late_does_not_cost_the_candidate() -> None:
    # At 210 ms the count still shows frame 3 queued: its take (due at 200 ms) is not seen
    # yet, its ack in flight. Frame 4 is held for the slot that take freed, not dropped as
    # if the queue were full, and goes once the take is seen.
    decider = _with_service_measured()
    frame = Candidate(280 * MS, 4, 0.9, 210 * MS)
    assert _verdicts(decider.frame(frame, Load(1, 1, taken_ns=100 * MS), 210 * MS)) == [
        (4, Action.HOLD, "held")
    ]
    # Seen at 215 ms: the detector needs its next frame at 300 ms, before frame 5 is in.
    assert _verdicts(decider.tick(Load(0, 1, taken_ns=215 * MS), 215 * MS)) == [
        (4, Action.FORWARD, "deadline")
    ]


def test_a_queue_really_full_still_drops_the_candidate() -> None:
    # Frame 4 comes at 195 ms, while frame 3 waits for the detector (busy with frame 2
    # until 200 ms): the queue is full, and held plus queued frames stay within N.
    decider = _with_service_measured()
    frame = Candidate(280 * MS, 4, 0.9, 195 * MS)
    assert _verdicts(decider.frame(frame, Load(1, 1, taken_ns=100 * MS), 195 * MS)) == [
        (4, Action.DROP, "queue-full")
    ]


@pytest.mark.parametrize("ack_delay_ms", [30, 60])
def test_takes_counted_late_cost_no_frames_with_one_slot(ack_delay_ms: int) -> None:
    # The detector's acks arrive tens of ms after its takes on a loaded machine: frames
    # decided in between see the queue full. Adaptive still keeps the detector as busy as
    # when every take is counted at once, and never has a forward refused.
    rng = random.Random(3)
    qualities = [rng.uniform(0.2, 1.0) for _ in range(300)]

    def run(delay_ns: int) -> QueueRun:
        return run_detector(
            _adaptive(), qualities, frame_period_ns=66_666_667, service_ns=107 * MS,
            capacity=1, ack_delays_ns=(delay_ns,) if delay_ns else (),
        )  # fmt: skip

    prompt, late = run(0), run(ack_delay_ms * MS)
    assert late.refused == 0
    assert len(late.processed) >= len(prompt.processed) - 2
    assert late.idle_ns <= prompt.idle_ns + 107 * MS  # at most about one frame's worth


@pytest.mark.parametrize("seed", [0, 2, 3])
def test_acks_that_come_late_now_and_then_do_not_slow_its_clock(seed: int) -> None:
    # A detector of 100-125 ms a frame; one take in five is seen 20-160 ms late (its ack
    # held up on a loaded machine), the others after 1-5 ms, as traced at load 20. The
    # clock never runs slower than the detector (a detector thought busy would idle), and
    # the detector stays about as busy as when every take is seen at once.
    rng = random.Random(5)
    qualities = [rng.uniform(0.2, 1.0) for _ in range(300)]
    steps = tuple(round(rng.uniform(-7, 18) * MS) for _ in range(97))
    draw = random.Random(seed)
    late_acks = tuple(
        round((draw.uniform(1, 5) if draw.random() < 0.8 else draw.uniform(20, 160)) * MS)
        for _ in range(61)
    )

    def run(ack_delays_ns: tuple[int, ...]) -> tuple[QueueRun, Decider]:
        decider = _adaptive()
        out = run_detector(
            decider, qualities, frame_period_ns=66_666_667, service_ns=107 * MS,
            capacity=1, tick_ns=2 * MS, ack_delays_ns=ack_delays_ns, service_steps_ns=steps,
        )  # fmt: skip
        return out, decider

    (prompt, _), (late, decider) = run(()), run(late_acks)
    service = decider.detector.service_ns
    assert service is not None and service <= 115 * MS  # the detector's mean is 112.5
    assert late.refused == 0
    assert len(late.processed) >= len(prompt.processed) - 8
    assert late.idle_ns <= prompt.idle_ns + 1_000 * MS
