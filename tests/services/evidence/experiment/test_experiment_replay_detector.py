"""The replay's detector at the speed a real run's detector had (``service_steps``)."""

from __future__ import annotations

import pytest

from services.evidence.experiment._config import ExperimentError
from services.evidence.experiment._experiment import detector_overhead_ns
from services.evidence.experiment._frames import FrameOutcome
from services.evidence.experiment._records import FrameDetections
from services.evidence.experiment._replay import QueueModel, replay_uncontrolled

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
