"""The replay's detector at the speed a real run's detector had (``service_steps``)."""

from __future__ import annotations

import numpy as np
import pytest

from services.evidence.experiment._config import ExperimentError
from services.evidence.experiment._detector import (
    ack_steps,
    clock_offset_ns,
    detector_overhead_ns,
    detector_steps,
    handover_steps,
)
from services.evidence.experiment._frames import FrameOutcome
from services.evidence.experiment._records import FrameDetections
from services.evidence.experiment._replay import (
    QueueModel,
    _Detector,
    replay_policy,
    replay_uncontrolled,
)
from services.lib.decisions import make_policy
from services.lib.messages import DecisionRecord, frame_metadata, read_frame_metadata
from services.lib.quality import Exposure
from services.lib.vision import Box, ResultKind, encode_result

MS = 1_000_000


def test_a_frame_takes_the_service_time_of_the_last_step_before_its_take() -> None:
    model = QueueModel(queue=2, service_ns=100 * MS, service_steps=((1000 * MS, 150 * MS),))
    assert model.service_at(999 * MS) == 100 * MS
    assert model.service_at(1000 * MS) == 150 * MS
    assert model.service_at(5000 * MS) == 150 * MS


def test_a_detector_that_slowed_down_processes_fewer_frames() -> None:
    frames = tuple(
        FrameOutcome(i, i * 50 * MS, 1.0, 0.9, frozenset({"large"})) for i in range(1, 201)
    )
    steady = QueueModel(queue=2, service_ns=80 * MS)
    slowed = QueueModel(queue=2, service_ns=80 * MS, service_steps=((5000 * MS, 120 * MS),))
    assert len(replay_uncontrolled(frames, slowed)) < len(replay_uncontrolled(frames, steady))


def test_a_step_without_a_positive_time_is_refused() -> None:
    with pytest.raises(ExperimentError, match="positive"):
        QueueModel(queue=2, service_ns=80 * MS, service_steps=((0, 0),))


def test_the_detector_overhead_is_its_cycle_less_its_processing_when_never_idle() -> None:
    # Takes 120 ms apart (the camera keeps the queue full), 110 ms processing each: 10 ms
    # a frame go to taking, fetching and putting.
    arrival = {i: i * 120 * MS for i in range(50)}
    detections = [FrameDetections(i, 110 * MS, ()) for i in range(50)]
    assert detector_overhead_ns(detections, arrival) == 10 * MS
    assert detector_overhead_ns([], arrival) == 0
    # Processing longer than the cycle cannot make a negative overhead.
    slow = [FrameDetections(i, 130 * MS, ()) for i in range(50)]
    assert detector_overhead_ns(slow, arrival) == 0


def _forward(frame_id: int, key_ns: int, latency_ns: int) -> DecisionRecord:
    return DecisionRecord(
        frame_timestamp_ns=key_ns, frame_id=frame_id, blur_px=1.0, quality=0.9, load=0.0,
        accepted=True, reason="quality>load", policy="paper", b0_px=5.0, latency_ns=latency_ns,
    )  # fmt: skip


def test_steps_are_dated_by_the_detectors_own_takes() -> None:
    # Camera clock = replay time + 1 s. Frames 0-2 come back to back (each forwarded before
    # the one ahead of it was done), frame 1 slowly (a 400 ms spell); frame 3 is forwarded
    # long after frame 2 was done: the detector idled.
    offset = 1000 * MS
    arrival = {i: i * 70 * MS for i in range(4)}
    arrival[3] = 900 * MS
    forwards = [_forward(i, offset + arrival[i], 5 * MS) for i in range(4)]
    taken = [5, 113, 515, 905]
    detections = [
        FrameDetections(i, p * MS, (), offset + taken[i] * MS)
        for i, p in enumerate((105, 400, 105, 105))
    ]
    assert clock_offset_ns(forwards, arrival) == offset
    steps, overhead = detector_steps(detections, forwards, arrival, 100 * MS, 0, offset)
    # Each step starts at its take; back to back it lasts until the next take, and the
    # overhead per frame is this run's own (3 ms, 2 ms: their median, 2.5 ms).
    assert [t for t, _s in steps] == [taken[i] * MS for i in range(4)]
    assert [s for _t, s in steps[:2]] == [108 * MS, 402 * MS]
    assert overhead == 5 * MS // 2
    assert steps[2][1] == 105 * MS + overhead and steps[3][1] == 105 * MS + overhead
    # The slow spell is charged to the frames taken during it, not to those before it.
    model = QueueModel(queue=1, service_ns=100 * MS, service_steps=steps)
    assert model.service_at(200 * MS) == 402 * MS and model.service_at(100 * MS) == 108 * MS


def test_without_take_times_a_frame_is_taken_when_forwarded_and_the_detector_was_done() -> None:
    arrival = {i: i * 70 * MS for i in range(3)}
    forwards = [_forward(i, arrival[i], 10 * MS) for i in range(3)]
    detections = [FrameDetections(i, 150 * MS, ()) for i in range(3)]
    steps, overhead = detector_steps(detections, forwards, arrival, 100 * MS, 4 * MS, None)
    assert overhead == 4 * MS
    assert steps == ((10 * MS, 154 * MS), (164 * MS, 154 * MS), (318 * MS, 154 * MS))


def test_a_detections_record_says_when_the_detector_took_the_frame() -> None:
    frame = read_frame_metadata(
        frame_metadata(7, Exposure(1_000_000, 30_000_000), np.zeros((4, 6), np.uint8), None)
    )
    boxes = [Box(3, ((0, 0), (1, 0), (1, 1), (0, 1)))]
    said = encode_result(boxes, ResultKind.DETECTIONS, frame, "x/y", 5 * MS, 1234 * MS)
    silent = encode_result(boxes, ResultKind.DETECTIONS, frame, "x/y", 5 * MS)
    assert said is not None and silent is not None
    assert FrameDetections.from_metadata(said.metadata).taken_ns == 1234 * MS
    assert FrameDetections.from_metadata(silent.metadata).taken_ns is None


def test_a_take_counts_as_queued_until_its_ack_reaches_the_mediator() -> None:
    # The paper's rule at N = 1: frame 1 waits while frame 0 is processed; the detector
    # takes it at 100 ms. Frame 2 at 130 ms finds the queue empty if the mediator learnt of
    # that take at once, and full if its ack takes 50 ms (it is dropped, as the real
    # mediator drops it).
    frames = tuple(
        FrameOutcome(i, at * MS, 1.0, 0.9, frozenset({"large"}))
        for i, at in enumerate((0, 60, 130))
    )
    prompt = QueueModel(queue=1, service_ns=100 * MS)
    late = QueueModel(queue=1, service_ns=100 * MS, ack_steps=((0, 50 * MS),))
    assert replay_policy(frames, prompt, make_policy("paper")) == (0, 1, 2)
    assert replay_policy(frames, late, make_policy("paper")) == (0, 1)
    assert late.ack_at(10 * MS) == 50 * MS and prompt.ack_at(10 * MS) == 0


def test_ack_delays_are_read_from_when_the_mediator_saw_each_take() -> None:
    seen = (103, 260, 305, 520)
    records = [
        DecisionRecord(1, 1, None, None, 0.0, False, "x", "paper", 5.0, 1, s * MS) for s in seen
    ]
    detections = [
        FrameDetections(i, 100 * MS, (), t * MS) for i, t in enumerate((100, 200, 300, 400, 500))
    ]
    # 400's ack was seen only after the take at 500: no step of its own.
    assert ack_steps(detections, records, 10 * MS) == (
        (90 * MS, 3 * MS), (190 * MS, 60 * MS), (290 * MS, 5 * MS), (490 * MS, 20 * MS),
    )  # fmt: skip
    assert ack_steps(detections, records[:0], 10 * MS) == ()


def test_a_decision_record_says_when_the_mediator_last_saw_a_take() -> None:
    record = DecisionRecord(1, 2, 0.5, 0.9, 0.5, True, "commit", "adaptive", 5.0, 3, 77 * MS)
    assert DecisionRecord.from_metadata(record.metadata(5)).take_seen_ns == 77 * MS
    unknown = DecisionRecord(1, 2, 0.5, 0.9, 0.5, True, "commit", "adaptive", 5.0, 3)
    assert DecisionRecord.from_metadata(unknown.metadata(5)).take_seen_ns is None


def test_an_idle_detector_takes_a_frame_a_hand_over_after_its_put() -> None:
    frames = tuple(
        FrameOutcome(i, at * MS, 1.0, 0.9, frozenset({"large"})) for i, at in enumerate((0, 300))
    )
    handed = QueueModel(queue=1, service_ns=100 * MS, handover_steps=((0, 10 * MS),))
    assert handed.handover_at(5 * MS) == 10 * MS
    detector = _Detector(handed)
    assert detector.put(0, 0) and detector.takes_ns == []  # on its way to the detector
    detector.advance(10 * MS)
    assert detector.takes_ns == [10 * MS] and detector.free_ns == 110 * MS
    assert replay_policy(frames, handed, make_policy("paper")) == (0, 1)


def test_hand_overs_are_read_from_forwards_to_a_detector_done_with_the_frame_before() -> None:
    arrival = {i: i * 70 * MS for i in range(3)}
    arrival[2] = 600 * MS
    forwards = [_forward(i, arrival[i], 5 * MS) for i in range(3)]
    # Frame 1 came while frame 0 was processed (no hand-over of its own); frame 2 to an
    # idle detector, taken 12 ms after its forward.
    detections = [FrameDetections(i, 100 * MS, (), t * MS) for i, t in enumerate((9, 109, 617))]
    assert handover_steps(detections, forwards, arrival, 100 * MS, 0) == (
        (5 * MS, 4 * MS), (605 * MS, 12 * MS),
    )  # fmt: skip
    assert handover_steps(detections, forwards, arrival, 100 * MS, None) == ()


def test_a_take_stamped_just_after_its_ack_was_seen_is_matched_to_that_ack() -> None:
    # The mediator saw the ack 0.3 ms before the detector stamped the take.
    records = [DecisionRecord(1, 1, None, None, 0.0, False, "x", "paper", 5.0, 1, 99_700_000)]
    detections = [FrameDetections(0, 100 * MS, (), 100 * MS)]
    assert ack_steps(detections, records, 0) == ((100 * MS, 0),)
