"""The soak's lost-element audit, fed by a fake pipeline (no processes)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import pytest

from middleware import DataObject, NotFoundError, Retention
from services.evidence.soak import Audit, MemorySeries, find_stalls
from services.lib.messages import DecisionRecord

MS = 1_000_000


def _decision(frame_ts: int, accepted: bool) -> DecisionRecord:
    return DecisionRecord(
        frame_timestamp_ns=frame_ts,
        frame_id=frame_ts // MS,
        blur_px=1.0,
        quality=0.8,
        load=0.0,
        accepted=accepted,
        reason="quality>load" if accepted else "quality<=load",
        policy="paper",
        b0_px=5.0,
        latency_ns=1,
    )


@dataclass
class _Info:
    oldest_ns: int | None
    retention: Retention = field(default_factory=Retention)


class FakePipeline:
    """Answers the audit's queries from plain dicts, as the services' buffers would."""

    def __init__(self) -> None:
        self.buffers: dict[str, dict[int, DataObject]] = {
            name: {}
            for name in (
                "camera/images",
                "mediator/images",
                "mediator/decisions",
                "detector/detections",
            )
        }

    def frame(self, ts: int, payload: bytes = b"image") -> None:
        self.buffers["camera/images"][ts] = DataObject(ts, payload + b"%d" % ts, b"<m/>")

    def decide(self, ts: int, accepted: bool, *, forward: bool = True, detect: bool = True) -> None:
        key = 10**12 + ts
        record = _decision(ts, accepted)
        self.buffers["mediator/decisions"][key] = DataObject(key, b"", record.metadata(key))
        if accepted and forward:
            self.buffers["mediator/images"][ts] = self.buffers["camera/images"][ts]
        if accepted and detect:
            self.buffers["detector/detections"][ts] = DataObject(ts, b"", b"<d/>")

    def query(self, target: str, *, time_range: str, timeout_s: float) -> list[DataObject]:
        start = int(time_range.strip("[]").split("..")[0])
        found = self.buffers[target]
        return [found[t] for t in sorted(found) if t >= start]

    def buffer_info(self, target: str) -> _Info:
        held = self.buffers[target]
        return _Info(min(held) if held else None)


# Frame timestamps here are ms after the epoch; "now" is a minute later.
NOW = 60_000 * MS


def _audit(pipe: FakePipeline, now_ns: int = NOW) -> Audit:
    audit = Audit()
    audit.check(pipe, now_ns)  # type: ignore[arg-type]
    return audit


def test_a_healthy_pipeline_loses_nothing() -> None:
    pipe = FakePipeline()
    for i in range(1, 11):
        pipe.frame(i * MS)
        pipe.decide(i * MS, accepted=i % 3 != 0)
    audit = _audit(pipe)
    summary = audit.summary()
    assert summary["lost"] == dict.fromkeys(summary["lost"], 0)
    assert summary["accepted"] == 7
    assert summary["compared_with_camera"] == 7


def test_frames_before_the_mediator_s_first_decision_are_not_counted() -> None:
    pipe = FakePipeline()
    for i in range(1, 6):
        pipe.frame(i * MS)
    for i in range(3, 6):
        pipe.decide(i * MS, accepted=True)
    assert _audit(pipe).summary()["lost"]["frames_without_decision"] == 0


def test_a_skipped_frame_an_unforwarded_accept_and_a_missing_detection_are_lost() -> None:
    pipe = FakePipeline()
    for i in range(1, 8):
        pipe.frame(i * MS)
    pipe.decide(1 * MS, True)
    pipe.decide(3 * MS, True)  # frame 2 got no decision
    pipe.decide(4 * MS, True, forward=False, detect=False)  # accepted, never forwarded
    pipe.decide(5 * MS, True, detect=False)  # no detection, though 6 was detected
    pipe.decide(6 * MS, True)
    lost = _audit(pipe, now_ns=8 * MS).lost  # frame 7 may still be decided
    assert lost["frames_without_decision"] == {2 * MS}
    assert lost["accepted_not_in_mediator"] == {4 * MS}
    assert lost["accepted_without_detection"] == {4 * MS, 5 * MS}


def test_an_accepted_frame_with_a_consumer_lapsed_record_is_counted_not_lost() -> None:
    pipe = FakePipeline()
    for i in range(1, 5):
        pipe.frame(i * MS)
    pipe.decide(1 * MS, True)
    pipe.decide(2 * MS, True, detect=False)  # waiting in the detector's queue...
    key = 10**12 + 2 * MS + 1  # ... when its subscription lapsed: the mediator says so
    lapsed = DecisionRecord(2 * MS, 2, 1.0, 0.8, 1.0, False, "consumer-lapsed", "paper", 5.0, 1)
    pipe.buffers["mediator/decisions"][key] = DataObject(key, b"", lapsed.metadata(key))
    pipe.decide(3 * MS, True, detect=False)  # no record why: lost
    pipe.decide(4 * MS, True)
    audit = _audit(pipe, now_ns=8 * MS)
    assert audit.lost["accepted_without_detection"] == {3 * MS}
    assert audit.summary()["accepted_with_reason"] == 1
    assert audit.summary()["decision_reasons"]["consumer-lapsed"] == 1


def test_an_altered_frame_in_mediator_images_is_not_identical() -> None:
    pipe = FakePipeline()
    for i in range(1, 4):
        pipe.frame(i * MS)
        pipe.decide(i * MS, True)
    pipe.buffers["mediator/images"][2 * MS] = DataObject(2 * MS, b"tampered", b"<m/>")
    pipe.frame(9 * MS)
    pipe.decide(9 * MS, False)  # rejected, yet it shows up in mediator/images
    pipe.buffers["mediator/images"][9 * MS] = pipe.buffers["camera/images"][9 * MS]
    lost = _audit(pipe).lost
    assert lost["accepted_not_identical"] == {2 * MS}
    assert lost["mediator_not_accepted"] == {9 * MS}


def test_later_audits_read_only_what_is_new_and_keep_counting() -> None:
    pipe = FakePipeline()
    audit = Audit()
    pipe.frame(1 * MS)
    pipe.decide(1 * MS, True)
    audit.check(pipe, NOW)  # type: ignore[arg-type]
    pipe.frame(2 * MS)
    pipe.frame(3 * MS)
    pipe.decide(3 * MS, True)
    audit.check(pipe, NOW)  # type: ignore[arg-type]
    assert audit.summary()["checks"] == 2
    assert audit.lost["frames_without_decision"] == {2 * MS}
    assert audit.compared == 2


def test_a_pass_with_an_unanswered_query_changes_nothing_and_the_next_reads_it_all() -> None:
    """A service that does not answer (restarting, or a lost lease on a loaded machine) must
    not make the audit skip what the other buffers returned in that pass."""
    pipe = FakePipeline()
    for i in (1, 2):
        pipe.frame(i * MS)
        pipe.decide(i * MS, True)
    answer = pipe.query

    def detector_gone(target: str, *, time_range: str, timeout_s: float) -> list[DataObject]:
        if target == "detector/detections":
            raise NotFoundError("no live service named 'detector'")
        return answer(target, time_range=time_range, timeout_s=timeout_s)

    pipe.query = detector_gone  # type: ignore[method-assign]
    audit = Audit()
    with pytest.raises(NotFoundError):
        audit.check(pipe, NOW)  # type: ignore[arg-type]
    assert audit.summary()["frames_decided"] == 0 and audit.checks == 0
    pipe.query = answer  # type: ignore[method-assign]
    audit.check(pipe, NOW)  # type: ignore[arg-type]
    summary = audit.summary()
    assert summary["accepted_seen_in_mediator"] == 2 and summary["detected"] == 2, summary
    assert not any(summary["lost"].values()), summary


def test_memory_growth_is_measured_after_the_warm_up_on_the_last_pid() -> None:
    series = MemorySeries()
    for t in range(0, 100, 5):
        series.samples.append((float(t), 1, (50 if t < 20 else 100) * 2**20))
    series.samples[-1] = (95.0, 1, 104 * 2**20)
    summary = series.summary(warmup_s=20, goal=0.05)
    assert summary["rss_after_warmup_mib"] == 100.0
    assert summary["ok"] is True
    assert 0 < summary["growth"] < 0.02
    assert series.summary(warmup_s=0, goal=0.05)["ok"] is False


def test_frames_left_undecided_by_a_stalled_mediator_are_lost() -> None:
    pipe = FakePipeline()
    for i in range(1, 4):
        pipe.frame(i * MS)
        pipe.decide(i * MS, True)
    audit = Audit()
    # The mediator stops deciding; the camera stores a few more frames, then nothing.
    for i in range(4, 45):
        pipe.frame(i * 1000 * MS)
    audit.check(pipe, 44_000 * MS)  # type: ignore[arg-type]
    assert audit.lost["frames_without_decision"] == {i * 1000 * MS for i in range(4, 14)}
    audit.check(pipe, NOW)  # type: ignore[arg-type]
    assert audit.lost["frames_without_decision"] == {i * 1000 * MS for i in range(4, 30)}
    # A decision that comes late after all takes its frame off the list.
    pipe.decide(4000 * MS, True)
    audit.check(pipe, 44_000 * MS)  # type: ignore[arg-type]
    assert 4000 * MS not in audit.lost["frames_without_decision"]


def _point(t: float, camera: tuple[int, int], decisions: int) -> dict[str, Any]:
    return {
        "t": t,
        "buffers": {"camera/images": list(camera), "mediator/decisions": [decisions, 0]},
    }


def test_a_stage_whose_output_stands_still_while_input_arrives_is_stalled() -> None:
    timeline = [_point(t, (t, 0), t) for t in range(0, 50, 10)]
    timeline += [_point(t, (50, t - 50), 50) for t in range(50, 120, 10)]
    timeline += [_point(t, (50 + t - 120, 70), 50 + t - 120) for t in range(120, 150, 10)]
    assert find_stalls(timeline) == [
        {"stage": "mediator", "from_s": 50, "to_s": 120, "input_meanwhile": 70}
    ]
    # Nothing arriving is not a stall.
    assert find_stalls([_point(t, (5, 0), 5) for t in range(0, 100, 10)]) == []
