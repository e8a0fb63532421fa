"""A device camera's stamps follow the process clock (the time model), not the system clock."""

from __future__ import annotations

import itertools
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import middleware._clock as clock_module
from middleware import ConfigError, SteadyClock
from services.nodes.sources import DeviceSource, SourceSpec

S = 1_000_000_000


def _video(path: Path, frames: int) -> Path:
    cv2 = pytest.importorskip("cv2")
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 15, (32, 24), False)
    for i in range(frames):
        writer.write(np.full((24, 32), i * 10, np.uint8))
    writer.release()
    return path


def test_a_backward_clock_step_does_not_stamp_device_frames_backward(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """NTP steps the system clock back 30 s under a device camera: its frames were stamped
    with the system clock, 30 s before the newest one stored, and every frame was refused
    as older than it until real time caught up (1,947 of 1,947 in 10 s, measured)."""
    offset = [0]
    real_time_ns = time.time_ns
    # The system clock as the process sees it (steps included), and a process clock of
    # this test's own that reads it (the module's would keep this test's step as its lead).
    monkeypatch.setattr(time, "time_ns", lambda: real_time_ns() + offset[0])
    process_clock = SteadyClock()
    monkeypatch.setattr(clock_module, "CLOCK", process_clock)
    spec = SourceSpec(kind="device", path=str(_video(tmp_path / "v.avi", 6)))
    source = DeviceSource(spec)
    stamps = []
    for frame in source.frames(threading.Event()):
        stamps.append(frame.exposure_start_ns)
        if len(stamps) == 3:
            offset[0] = -30 * S  # the step, between two reads
    assert len(stamps) == 6
    assert all(b > a for a, b in itertools.pairwise(stamps)), stamps
    assert process_clock.status().steps == 1


def test_a_missing_device_is_one_line_without_opencvs_warnings(
    capfd: pytest.CaptureFixture[str],
) -> None:
    """`framegate run camera --source device --path 0` on a machine with no camera printed
    two OpenCV `[ WARN:0@0.012] global cap_v4l.cpp ...` lines before its own error."""
    cv2 = pytest.importorskip("cv2")
    if Path("/dev/video97").exists():
        pytest.skip("this machine has a camera at index 97")
    with pytest.raises(ConfigError, match="cannot open video device '97'"):
        DeviceSource(SourceSpec(kind="device", path="97"))
    assert "WARN" not in capfd.readouterr().err
    assert cv2.utils.logging.getLogLevel() != cv2.utils.logging.LOG_LEVEL_ERROR  # restored
