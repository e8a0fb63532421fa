"""The replay's detector at the speed a real run's detector had (``service_steps``)."""

from __future__ import annotations

import pytest

from services.tools.experiment._config import ExperimentError
from services.tools.experiment._frames import FrameOutcome
from services.tools.experiment._replay import QueueModel, replay_uncontrolled

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
