"""The mediator as handlers, fed by the test on its own thread with its own times: no
executor, no camera or gyro process, no thread waits for anything."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from middleware import DataObject, NetworkConfig, Node, Notification, TransportError, now_ns
from services.lib.camera_model import CameraModel
from services.lib.decisions import GyroMissing, Load
from services.lib.messages import DecisionRecord, frame_metadata
from services.lib.quality import Exposure, GyroSamples
from services.lib.rewind import SourceClock
from services.nodes.mediator import _MISSED_TRIES, Mediator, MediatorConfig
from tests.conftest import free_port

MS = 1_000_000
IMAGE = np.zeros((48, 64), dtype=np.uint8)
CAMERA = CameraModel(width_px=64, height_px=48, fx_px=50.0, fy_px=50.0, cx_px=32.0, cy_px=24.0)
WAIT_MS = 150.0


class Fed:
    """A mediator whose handlers the test calls, and the decisions it recorded."""

    def __init__(self, node: Node, policy: str = "paper") -> None:
        config = MediatorConfig(
            gyro_missing=GyroMissing.REJECT, gyro_wait_ms=WAIT_MS, policy=policy
        )
        self.mediator = Mediator(node, config, "mediator")
        self.records: list[DecisionRecord] = []
        write = self.mediator.out.write

        def keep(record: DecisionRecord) -> None:
            self.records.append(record)
            write(record)

        self.mediator.out.write = keep  # type: ignore[method-assign]
        clock = SourceClock("host", 1, 0, 0, 100_000)
        self.mediator._offsets.add(clock, clock)  # both clocks measured: they agree
        self.seq = 0

    def frame(self, start_ms: int) -> None:
        self.seq += 1
        exposure = Exposure(start_ms * MS, 10 * MS)
        metadata = frame_metadata(self.seq, exposure, IMAGE, CAMERA)
        element = DataObject(exposure.start_ns, IMAGE.tobytes(), metadata)
        note = Notification("camera", "images", exposure.start_ns, self.seq, element=element)
        self.mediator.on_camera(note)

    def gyro(self, first_ms: int, last_ms: int) -> None:
        t = np.arange(first_ms * MS, (last_ms + 1) * MS, MS, dtype=np.int64)
        samples = GyroSamples(t, np.full((t.size, 3), 0.1))
        element = DataObject(int(t[-1]), samples.to_bytes(), b"")
        note = Notification("gyro", "rates", int(t[-1]), self.seq, element=element)
        self.mediator.on_gyro([note])

    def reasons(self) -> list[str]:
        return [r.reason for r in self.records]


@pytest.fixture
def fed() -> Iterator[Fed]:
    with Node("mediator", NetworkConfig(local_port=free_port())) as node:
        yield Fed(node)


def test_a_frame_waits_for_gyro_coverage_and_is_decided_when_it_comes(fed: Fed) -> None:
    fed.gyro(0, 5)
    fed.frame(10)
    assert fed.records == [] and fed.mediator.pairing.waiting == 1
    due = fed.mediator.next_deadline_ns()
    assert due is not None and due > time.monotonic_ns()  # the frame's own gyro deadline
    fed.gyro(6, 40)  # covers the exposure (10..20 ms)
    assert len(fed.records) == 1 and fed.records[0].quality is not None, fed.reasons()
    assert fed.mediator.pairing.waiting == 0


def test_while_the_gyro_is_out_frames_are_decided_at_once(fed: Fed) -> None:
    fed.gyro(0, 5)
    fed.frame(10)
    fed.frame(80)  # waits behind the first one, on a deadline of its own
    assert fed.records == [] and fed.mediator.pairing.waiting == 2
    fed.mediator.on_time(time.monotonic_ns() + int(WAIT_MS * MS))  # both deadlines passed
    assert fed.reasons() == ["gyro-missing-reject"] * 2
    # No sample since: the gyro is out, and a new frame waits for nothing.
    fed.frame(150)
    assert fed.reasons() == ["gyro-missing-reject"] * 3
    assert fed.mediator.next_deadline_ns() is None
    # Samples again: frames wait for coverage again, and are paired.
    fed.gyro(6, 200)
    fed.frame(210)
    assert len(fed.records) == 3 and fed.mediator.pairing.waiting == 1
    fed.gyro(201, 260)
    assert len(fed.records) == 4 and fed.records[-1].quality is not None, fed.reasons()


def test_a_held_frame_goes_out_at_its_deadline_not_a_poll_later() -> None:
    # ``replace`` holds a frame while a slot is free and one frame waits, and forwards it
    # once it was held the maximum hold time: the mediator's one deadline is that moment,
    # and the handler run then carries the verdict out.
    with Node("mediator", NetworkConfig(local_port=free_port())) as node:
        fed = Fed(node, policy="replace")
        mediator = fed.mediator
        mediator.out.load = lambda: Load(1, 2)  # type: ignore[method-assign]
        fed.gyro(0, 40)
        fed.frame(10)
        assert fed.reasons() == ["held"]
        held = mediator.decider.held[0]
        due = mediator.next_deadline_ns()
        assert due == held.arrived_ns + mediator.decider.rules.max_hold_ns
        mediator.on_time(due - 1)
        assert fed.reasons() == ["held"]  # not a nanosecond early
        mediator.on_time(due)
        assert fed.reasons() == ["held", "held-max"] and fed.records[-1].accepted
        assert mediator.next_deadline_ns() is None  # nothing left to wake for


def test_a_decision_records_when_the_mediator_last_saw_the_detector_take() -> None:
    # What the mediator knew of the detector's queue, on the frames' clock: an experiment
    # sets it beside the detector's own take times (how late each ack came).
    with Node("mediator", NetworkConfig(local_port=free_port())) as node:
        fed = Fed(node)
        before = now_ns()
        seen_mono = time.monotonic_ns() - 40 * MS  # a take seen 40 ms ago
        fed.mediator.out.load = lambda: Load(0, 2, seen_mono)  # type: ignore[method-assign]
        fed.gyro(0, 40)
        fed.frame(10)
        after = now_ns()
        seen = fed.records[-1].take_seen_ns
        # On the wall clock, 40 ms before the moment it was set (a stall between the two
        # clock reads can only make it earlier; a second of slack for that).
        assert seen is not None and before - 1040 * MS <= seen <= after - 40 * MS
        fed.mediator.out.load = lambda: Load(0, 2)  # type: ignore[method-assign]
        fed.gyro(41, 100)
        fed.frame(80)
        assert fed.records[-1].take_seen_ns is None  # no take seen: nothing to say


def test_frames_stored_while_lapsed_are_looked_up_again_when_the_camera_does_not_answer(
    fed: Fed,
) -> None:
    # On a loaded machine the look-up of the frames stored while the mediator's subscription
    # had lapsed can go unanswered; without asking again those frames got no record at all.
    mediator = fed.mediator
    mediator._newest_camera_ns = 10 * MS
    metadata = frame_metadata(7, Exposure(20 * MS, 10 * MS), IMAGE, CAMERA)
    stored = DataObject(20 * MS, IMAGE.tobytes(), metadata)
    asked: list[str] = []
    later: list[Callable[[int], object]] = []

    def query(target: str, time_range: str, timeout_s: float) -> list[DataObject]:
        asked.append(time_range)
        if len(asked) == 1:
            raise TransportError("the camera did not answer")
        return [stored]

    mediator._node.query = query  # type: ignore[method-assign,assignment]
    mediator._node.at = lambda deadline_ns, fn: later.append(fn)  # type: ignore[method-assign,assignment,return-value]
    mediator._record_missed(30 * MS)
    assert fed.records == [] and len(later) == 1
    mediator._newest_camera_ns = 40 * MS  # frames came meanwhile: the range stays the gap's
    later.pop()(0)
    assert asked == [f"[{10 * MS + 1}..{30 * MS - 1}]"] * 2
    assert fed.reasons() == ["mediator-lapsed"] and fed.records[0].frame_timestamp_ns == 20 * MS


def test_the_look_up_of_lapsed_frames_is_asked_a_bounded_number_of_times(fed: Fed) -> None:
    mediator = fed.mediator
    mediator._newest_camera_ns = 10 * MS
    asked: list[str] = []
    later: list[Callable[[int], object]] = []

    def query(target: str, time_range: str, timeout_s: float) -> list[DataObject]:
        asked.append(time_range)
        raise TransportError("the camera did not answer")

    mediator._node.query = query  # type: ignore[method-assign,assignment]
    mediator._node.at = lambda deadline_ns, fn: later.append(fn)  # type: ignore[method-assign,assignment,return-value]
    mediator._record_missed(30 * MS)
    while later:
        later.pop()(0)
    assert len(asked) == _MISSED_TRIES and fed.records == []
