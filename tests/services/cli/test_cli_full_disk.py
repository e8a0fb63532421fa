"""A recording that runs out of disk says so in one line and exits non-zero, and what it
wrote plays up to its last complete chunk; so does one whose recorder is killed."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from middleware import NetworkConfig, Node, Retention, make_metadata
from services.tools.bag import recording_info
from tests.conftest import REPO, child_env, wait_until
from tests.helpers.timing import scaled
from tests.services.cli.conftest import TIMEOUT_S, Cli

pytestmark = pytest.mark.integration


@pytest.fixture
def tiny_disk(tmp_path: Path) -> Iterator[Path]:
    mount = tmp_path / "tiny"
    mount.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mount)],
        capture_output=True, text=True,
    )  # fmt: skip
    if done.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs to fill: {done.stderr.strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


# 51 KiB every 0.1 s: a chunk closes each second by age (on the command's main thread), and
# the disk (1 MiB) is full after a few of them. 200 KiB every 20 ms: the 4 MiB chunk fills
# first and the writer's thread closes it (a busy recording: its error must end it too).
@pytest.mark.parametrize(
    ("size", "period_s"), [(51_200, 0.1), (204_800, 0.02)], ids=["quiet", "busy"]
)
def test_full_disk_stops_the_recording_with_one_line(
    listen_net: NetworkConfig, cli: Cli, tiny_disk: Path, size: int, period_s: float
) -> None:
    with Node("cam", listen_net) as service:
        log = service.offer("log", retention=Retention(max_count=200))
        recorder = cli.start(
            "record", "cam/log", "-o", str(tiny_disk / "run.mcap"), "--compression", "none",
            "--duration", "120",
        )  # fmt: skip
        assert log.wait_for_subscribers(1, timeout_s=scaled(30))
        noise = (bytes(range(256)) * (size // 256 + 1))[:size]
        t = time.time_ns()
        deadline = time.monotonic() + scaled(60)
        while recorder.poll() is None and time.monotonic() < deadline:
            t += 1_000_000
            log.put(t, noise, make_metadata("generic", t), wait_s=1.0)
            time.sleep(period_s)
        # It stopped when the disk filled, not at the end of its 120 s.
        ended_when_full = recorder.poll() is not None
    _out, err = recorder.communicate(timeout=TIMEOUT_S)
    assert ended_when_full, err
    assert recorder.returncode == 1, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines[-1].startswith("error: ") and "No space left on device" in lines[-1], err
    assert "Traceback" not in err
    if period_s < 0.1:
        return  # its first chunk (4 MiB) never fitted on the disk: nothing to play
    # What fitted before the disk filled is there to play (whole chunks only).
    info = recording_info(tiny_disk / "run.mcap")
    assert info.status == "recovered" and info.messages > 0, info


def test_a_killed_recorder_leaves_every_chunk_it_closed(
    listen_net: NetworkConfig, cli: Cli, tmp_path: Path
) -> None:
    out = tmp_path / "run.mcap"
    with Node("cam", listen_net) as service:
        log = service.offer("log", retention=Retention(max_count=1000))
        recorder = cli.start("record", "cam/log", "-o", str(out), "--duration", "120")
        assert log.wait_for_subscribers(1, timeout_s=scaled(30))
        t = time.time_ns()
        put = 0

        def chunks_written() -> bool:
            nonlocal t, put
            t += 1_000_000
            log.put(t, b"x" * 1000, make_metadata("generic", t), wait_s=1.0)
            put += 1
            time.sleep(0.01)
            # A chunk is closed at least every second: wait for two of them.
            return out.exists() and out.stat().st_size > 4096 and put > 300

        wait_until(chunks_written, 60, "a recording with closed chunks")
        recorder.kill()  # SIGKILL: no summary, no footer
        recorder.wait(timeout=TIMEOUT_S)
    info = recording_info(out)
    assert info.status == "recovered" and "cut short" in info.integrity, info
    assert 0 < info.messages <= put, (info.messages, put)


def test_a_killed_recorder_keeps_where_and_when_it_started(
    listen_net: NetworkConfig, cli: Cli, tmp_path: Path
) -> None:
    out = tmp_path / "run.mcap"
    with Node("cam", listen_net) as service:
        log = service.offer("log", retention=Retention(max_count=1000))
        before_ns = time.time_ns()
        recorder = cli.start("record", "cam/log", "-o", str(out), "--duration", "120")
        assert log.wait_for_subscribers(1, timeout_s=scaled(30))
        t = time.time_ns()

        def a_chunk_written() -> bool:
            nonlocal t
            t += 1_000_000
            log.put(t, b"x" * 1000, make_metadata("generic", t), wait_s=1.0)
            time.sleep(0.01)
            return out.exists() and out.stat().st_size > 4096  # a chunk is closed each second

        wait_until(a_chunk_written, 60, "a recording with a closed chunk")
        recorder.kill()  # SIGKILL: no end record
        recorder.wait(timeout=TIMEOUT_S)
    shown = subprocess.run(
        [sys.executable, "-m", "services.cli", "info", str(out), "--json"],
        cwd=REPO, env=child_env(), capture_output=True, text=True,
        timeout=TIMEOUT_S, check=False,
    )  # fmt: skip
    assert shown.returncode == 0, shown
    data = json.loads(shown.stdout)
    assert data["recorded_host"] == socket.gethostname(), data
    assert before_ns <= data["recorded_start_ns"] <= time.time_ns(), data
    assert data["recorded_stop_ns"] is None, data
    text = subprocess.run(
        [sys.executable, "-m", "services.cli", "info", str(out)],
        cwd=REPO, env=child_env(), capture_output=True, text=True,
        timeout=TIMEOUT_S, check=False,
    )  # fmt: skip
    assert "the recorder never stopped" in text.stdout, text
