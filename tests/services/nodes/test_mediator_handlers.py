"""The mediator as handlers, fed by the test on its own thread with its own times: no
executor, no camera or gyro process, no thread waits for anything."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from types import SimpleNamespace

import numpy as np
import pytest

from middleware import (
    DataObject,
    FramegateError,
    NetworkConfig,
    Node,
    Notification,
    Subscription,
    TransportError,
    now_ns,
)
from services.lib.camera_model import CameraModel
from services.lib.decisions import GyroMissing, Load
from services.lib.messages import DecisionRecord, frame_metadata
from services.lib.quality import Exposure, GyroSamples
from services.lib.rewind import SourceClock
from services.nodes import _mediator_output, _mediator_pairing
from services.nodes._mediator_restart import MISSED_TRIES
from services.nodes.mediator import Mediator, MediatorConfig
from tests.conftest import free_port

MS = 1_000_000
IMAGE = np.zeros((48, 64), dtype=np.uint8)
CAMERA = CameraModel(width_px=64, height_px=48, fx_px=50.0, fy_px=50.0, cx_px=32.0, cy_px=24.0)
WAIT_MS = 150.0
Answer = Callable[[list[DataObject] | FramegateError], object]


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
        # The camera's stream is under way (its start asks the camera's clock, and there is
        # no camera here): the frames fed are decided at once.
        self.mediator._camera_epoch = self.epoch = "C0.1"
        self.seq = 0

    def restart(self) -> None:
        """The camera restarted: a new epoch (no greeting here, so the mediator takes the
        new epoch as the camera's), its sequence starting over."""
        self.seq = 0
        self.epoch = f"C{int(self.epoch[1:].split('.')[0]) + 1}.1"

    def frame(self, start_ms: int) -> None:
        self.seq += 1
        exposure = Exposure(start_ms * MS, 10 * MS)
        metadata = frame_metadata(self.seq, exposure, IMAGE, CAMERA)
        element = DataObject(exposure.start_ns, IMAGE.tobytes(), metadata)
        note = Notification(
            "camera", "images", exposure.start_ns, self.seq, element=element, epoch=self.epoch
        )
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
    metadata = frame_metadata(7, Exposure(20 * MS, 10 * MS), IMAGE, CAMERA)
    stored = DataObject(20 * MS, IMAGE.tobytes(), metadata)
    asked: list[str] = []
    later: list[Callable[[int], object]] = []

    def ask_query(
        target: str, answer: Answer, time_range: str, timeout_s: float, session: object
    ) -> None:
        asked.append(time_range)  # answered at once here; the executor runs it later
        answer(TransportError("the camera did not answer") if len(asked) == 1 else [stored])

    mediator._node.ask_query = ask_query  # type: ignore[method-assign,assignment]
    mediator._node.at = lambda deadline_ns, fn: later.append(fn)  # type: ignore[method-assign,assignment,return-value]
    mediator.starts.missed(10 * MS, 30 * MS)
    assert fed.records == [] and len(later) == 1
    later.pop()(0)
    assert asked == [f"[{10 * MS + 1}..{30 * MS - 1}]"] * 2
    assert fed.reasons() == ["mediator-lapsed"] and fed.records[0].frame_timestamp_ns == 20 * MS


def test_the_look_up_of_lapsed_frames_is_asked_a_bounded_number_of_times(fed: Fed) -> None:
    mediator = fed.mediator
    asked: list[str] = []
    later: list[Callable[[int], object]] = []

    def ask_query(
        target: str, answer: Answer, time_range: str, timeout_s: float, session: object
    ) -> None:
        asked.append(time_range)
        answer(TransportError("the camera did not answer"))

    mediator._node.ask_query = ask_query  # type: ignore[method-assign,assignment]
    mediator._node.at = lambda deadline_ns, fn: later.append(fn)  # type: ignore[method-assign,assignment,return-value]
    mediator.starts.missed(10 * MS, 30 * MS)
    while later:
        later.pop()(0)
    assert len(asked) == MISSED_TRIES and fed.records == []


def test_a_restarted_camera_stream_waits_for_its_clock_without_holding_the_handlers(
    fed: Fed,
) -> None:
    # The camera's clock is asked when its stream starts over (a rewind is judged by it);
    # the question used to block the executor for a round trip, up to a second for a camera
    # gone again. Now the stream's frames wait, and are decided when the answer comes.
    mediator = fed.mediator
    asked: list[Callable[[SourceClock | None], object]] = []
    mediator._offsets.ask = lambda service, then: asked.append(then)  # type: ignore[method-assign]
    fed.gyro(0, 200)
    fed.frame(10)
    assert len(fed.records) == 1 and asked == []  # a stream under way asks nothing
    fed.restart()
    fed.frame(50)
    fed.frame(100)
    assert len(fed.records) == 1 and len(asked) == 1  # returned at once; nothing decided
    assert mediator.starts.holding and mediator.next_deadline_ns() is None
    mediator.on_time(time.monotonic_ns())  # nothing yet, however often asked
    assert len(fed.records) == 1
    clock = SourceClock("host", 2, 0, 0, 100_000)
    asked[0](clock)  # the executor runs the answer
    mediator._offsets.add(clock, clock)  # and the measurement asked at the restart
    mediator.on_time(time.monotonic_ns())
    assert not mediator.starts.holding
    assert [r.frame_timestamp_ns for r in fed.records] == [10 * MS, 50 * MS, 100 * MS]


def test_a_camera_that_restarts_again_before_its_clock_answered_removes_nothing(
    fed: Fed,
) -> None:
    # Two starts in a row: the first is carried out without its clock (no rewind can be
    # proven), the second waits for its own and the first one's answer.
    mediator = fed.mediator
    asked: list[Callable[[SourceClock | None], object]] = []
    mediator._offsets.ask = lambda service, then: asked.append(then)  # type: ignore[method-assign]
    fed.gyro(0, 300)
    fed.frame(200)
    fed.restart()
    fed.frame(100)  # started over, stamped before the frame forwarded
    fed.restart()
    fed.frame(150)  # and again, before the first restart's clock answered
    assert len(asked) == 2 and mediator.starts.holding
    asked[1](SourceClock("host", 3, 0, 0, 100_000))
    mediator.on_time(time.monotonic_ns())
    assert mediator.starts.holding  # the stream before it has not answered yet
    asked[0](None)
    clock = SourceClock("host", 3, 0, 0, 100_000)
    mediator._offsets.add(clock, clock)  # the measurement asked at the restart
    mediator.on_time(time.monotonic_ns())
    assert not mediator.starts.holding and mediator.images.info().rewinds == ()
    assert fed.reasons()[0] != "out-of-order" and fed.reasons()[1:] == ["out-of-order"] * 2


def test_a_brief_gyro_outage_is_counted_and_a_long_one_warned(
    fed: Fed, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A loaded machine made 52 warning pairs in 10 minutes out of late gyro batches.
    mediator = fed.mediator
    fed.gyro(0, 5)
    with caplog.at_level(logging.WARNING, logger="framegate.mediator"):
        fed.frame(10)
        mediator.on_time(time.monotonic_ns() + int(WAIT_MS * MS))  # out, but briefly
        fed.gyro(6, 100)
        fed.frame(50)  # covered again
        assert fed.reasons() == ["gyro-missing-reject", "quality>load"]
        assert not [r for r in caplog.records if "gyro" in r.getMessage()]
        monkeypatch.setattr(_mediator_pairing, "_OUTAGE_SAY_NS", 0)  # now out long enough
        fed.frame(200)
        mediator.on_time(time.monotonic_ns() + int(WAIT_MS * MS))
        fed.gyro(101, 300)
        fed.frame(250)
    said = [r.getMessage() for r in caplog.records if "gyro" in r.getMessage()]
    assert len(said) == 2, said
    assert "does not cover frame" in said[0] and "(1 briefer outages before" in said[0]
    assert "covers frames again" in said[1]


def test_a_subscription_registered_again_by_the_same_camera_keeps_its_clock_samples(
    fed: Fed, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Issue 30: the mediator stopped 20 s (SIGSTOP) and resumed, its subscription lapsed and
    # the same camera process registered it again: the clock samples were forgotten, and the
    # frames that came before they were measured again went clock-unmeasured (4 in that
    # run), though the camera's clock was the one measured all along.
    mediator = fed.mediator
    asked: list[Callable[[SourceClock | None], object]] = []
    mediator._offsets.ask = lambda service, then: asked.append(then)  # type: ignore[method-assign]
    fed.gyro(0, 300)
    fed.frame(10)
    fed.epoch, fed.seq = "C0.2", 0  # the same producer instance (C0), a new registration
    monkeypatch.setattr(Subscription, "registered_epoch", property(lambda _: fed.epoch))
    fed.frame(50)
    fed.frame(100)
    clock = SourceClock("host", 1, 0, 0, 100_000)
    for then in list(asked):
        then(clock)  # the stream's start asked the camera's clock: the same clock
    mediator.on_time(time.monotonic_ns() + int(WAIT_MS * MS))  # every wait has passed
    assert not mediator.starts.holding
    assert len(fed.records) == 3 and "clock-unmeasured" not in fed.reasons(), fed.reasons()
    # Another instance is another process: its clock is measured afresh.
    fed.restart()
    fed.frame(150)
    assert mediator._offsets.current() is None


def test_frames_after_a_gyro_restart_wait_for_its_clock(
    fed: Fed, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Issue 30, the gyro's side of a restart: a gyro restarted under another clock was
    # paired by the offset measured of the one before until the next measurement (up to a
    # period, 2 s), its samples taken for another moment's motion.
    producer = {"epoch": "G0"}
    monkeypatch.setattr(Subscription, "producer_epoch", property(lambda _: producer["epoch"]))
    mediator = fed.mediator
    fed.gyro(0, 300)
    fed.frame(10)
    assert fed.reasons() == ["quality>load"]
    producer["epoch"] = "G1"  # another gyro process greeted the subscription
    fed.gyro(301, 400)
    fed.frame(320)
    mediator.on_time(time.monotonic_ns() + int(WAIT_MS * MS))  # its wait has passed
    assert fed.reasons() == ["quality>load", "clock-unmeasured"]
    clock = SourceClock("host", 2, 0, 0, 100_000)
    mediator._offsets.add(clock, clock)  # measured: the new gyro's clock
    fed.gyro(401, 500)  # the same instance, later batches: nothing forgotten
    fed.frame(420)
    assert fed.reasons()[-1] == "quality>load"


def test_a_made_up_epoch_is_skipped_and_starts_nothing_over(
    fed: Fed, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A peer's notifications under made-up epochs on the mediator's camera key each counted
    # as a camera restart: the clock samples were dropped (162 of 173 frames then decided
    # clock-unmeasured) and two lines logged per forgery. Only the camera's greeting
    # starts a stream over; the forgery is decided as a frame (skipping frames of epochs
    # other than the greeted one would let one forged greeting skip every real frame).
    real = fed.epoch
    monkeypatch.setattr(Subscription, "registered_epoch", property(lambda _: real))
    mediator = fed.mediator
    asked: list[Callable[[SourceClock | None], object]] = []
    mediator._offsets.ask = lambda service, then: asked.append(then)  # type: ignore[method-assign]
    fed.gyro(0, 200)
    fed.frame(10)
    fed.epoch, fed.seq = "F1.1", 0
    fed.frame(20)  # the forgery: seq 1 of an epoch the camera never greeted us with
    fed.epoch, fed.seq = real, 1
    fed.frame(30)
    assert asked == [] and mediator._offsets.current() is not None  # nothing started over
    assert len(fed.records) == 3
    assert not {"out-of-order", "clock-unmeasured"} & set(fed.reasons())


def test_a_forged_greeting_does_not_make_the_real_frames_foreign(
    fed: Fed, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A peer's greeting under a made-up epoch came after the camera's own: the camera's
    # frames are still decided.
    monkeypatch.setattr(Subscription, "registered_epoch", property(lambda _: "F9.1"))
    fed.gyro(0, 200)
    fed.frame(10)
    fed.restart()
    fed.frame(30)
    assert len(fed.records) == 2
    assert not {"out-of-order", "clock-unmeasured"} & set(fed.reasons())


def test_a_frame_far_ahead_of_the_cameras_own_clock_holds_nothing_back(fed: Fed) -> None:
    # One frame stamped 9 s ahead (inside the 10 s horizon) became the time-order
    # reference: the next 136 real frames were dropped out-of-order.
    mediator = fed.mediator
    asked: list[Callable[[SourceClock | None], object]] = []
    mediator._offsets.ask = lambda service, then: asked.append(then)  # type: ignore[method-assign]
    fed.gyro(0, 300)
    fed.restart()
    fed.frame(10)
    clock = SourceClock("host", 2, 0, 0, 100_000)  # the camera's clock is ours
    asked[0](clock)
    mediator._offsets.add(clock, clock)
    mediator.on_time(time.monotonic_ns())
    fed.frame((now_ns() + 5 * 10**9) // MS)
    fed.frame(50)
    assert fed.reasons()[1] == "future-stamp"
    assert fed.reasons()[2] != "out-of-order"


def test_clock_measurements_never_pile_up(fed: Fed) -> None:
    # While frames waited for the clocks, every gyro batch asked for a measurement: with
    # answers slower than a batch, 80 questions a second went to camera and gyro, whose
    # bounded inboxes dropped them, and the clocks stayed unknown for minutes.
    mediator = fed.mediator
    asked: list[Callable[[SourceClock | None], object]] = []
    mediator._offsets.ask = lambda service, then: asked.append(then)  # type: ignore[method-assign]
    now = time.monotonic_ns()
    mediator._measure(now)
    assert len(asked) == 2 and mediator._offsets.measuring
    for _ in range(10):
        mediator._measure(now)
    assert len(asked) == 2  # one measurement out at a time
    for then in asked:
        then(None)
    assert not mediator._offsets.measuring
    mediator._measure(now)
    assert len(asked) == 4


def test_a_lapse_records_a_frame_forwarded_after_the_last_look_at_the_load(
    fed: Fed, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The mediator looks at the load (nothing queued), forwards a frame, and the next look
    # finds the consumer's subscription gone (a mediator resumed after SIGSTOP forwards
    # before it has read the consumer's token withdrawn). That frame was never taken: it
    # gets a consumer-lapsed record, as the frames counted queued at the last look do.
    consumer = SimpleNamespace(node="detector", host="h", subscription_id="d1", queue_size=2)
    live = [True]

    def tightest(_subscriptions: object) -> tuple[Load, object]:
        return (Load(0, 2), consumer) if live[0] else (Load(0, 0), None)

    monkeypatch.setattr(_mediator_output, "tightest_load", tightest)
    monkeypatch.setattr(fed.mediator.out.images, "put", lambda *_args, **_kw: 1)
    fed.gyro(0, 40)
    fed.frame(10)
    assert [r.accepted for r in fed.records] == [True], fed.reasons()
    live[0] = False
    fed.gyro(41, 80)
    fed.frame(50)
    lapsed = [r.frame_timestamp_ns for r in fed.records if r.reason == "consumer-lapsed"]
    assert lapsed == [10 * MS, 50 * MS], fed.reasons()


def test_the_summary_breaks_down_the_frames_decided_not_those_forwarded(fed: Fed) -> None:
    fed.gyro(0, 5)
    fed.frame(10)
    fed.frame(80)
    fed.mediator.on_time(time.monotonic_ns() + int(WAIT_MS * MS))  # gyro-missing-reject
    assert fed.mediator.out.summary().startswith(
        "2 frames decided (gyro-missing-reject 2), 0 forwarded; skipped: "
    )
