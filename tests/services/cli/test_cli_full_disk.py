"""A recording that runs out of disk says so in one line and exits non-zero."""

from __future__ import annotations

import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from middleware import NetworkConfig, Node, Retention, make_metadata
from tests.services.cli.conftest import TIMEOUT_S, Cli

pytestmark = pytest.mark.integration


@pytest.fixture
def tiny_disk(tmp_path: Path) -> Iterator[Path]:
    mount = tmp_path / "tiny"
    mount.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mount)],
        capture_output=True, text=True,
    )  # fmt: skip
    if done.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs to fill: {done.stderr.strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def test_full_disk_stops_the_recording_with_one_line(
    listen_net: NetworkConfig, cli: Cli, tiny_disk: Path
) -> None:
    with Node("cam", listen_net) as service:
        log = service.offer("log", retention=Retention(max_count=1000))
        recorder = cli.start(
            "record", "cam/log", "-o", str(tiny_disk / "run.mcap"), "--compression", "none",
            "--duration", "120",
        )  # fmt: skip
        assert log.wait_for_subscribers(1, timeout_s=30)
        noise = bytes(range(256)) * 200  # 51 KiB: six of them fill the disk
        t = time.time_ns()
        deadline = time.monotonic() + 60
        while recorder.poll() is None and time.monotonic() < deadline:
            t += 1_000_000
            log.put(t, noise, make_metadata("generic", t), wait_s=1.0)
            time.sleep(0.01)
        _out, err = recorder.communicate(timeout=TIMEOUT_S)
    assert recorder.returncode == 1, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines[-1].startswith("error: ") and "No space left on device" in lines[-1], err
    assert "Traceback" not in err
