"""A camera or gyro that joins its timeline late (restarted by ``launch``, or started after its
source took long to open) counts as ``late`` only frames or samples it really could not make in
time: those due before it was running are not its own."""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from middleware import FramegateError, NetworkConfig, Node
from tests.conftest import REPO, child_env, free_port, wait_until
from tests.helpers.frames import simulated_frames

pytestmark = pytest.mark.integration

# The shared start instant lies this far back: 15 frames/s make 1,800 frames "due" already.
BEHIND_S = 120
BACKLOG = BEHIND_S * 15
STARTUP_S = 300.0


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulated_frames(tmp_path_factory.mktemp("tiny") / "approach")


def _replay_behind(service: str, dataset: Path) -> Iterator[int]:
    """A looping replay ``service`` whose launch instant was BEHIND_S ago; its rendezvous port."""
    port = free_port()
    env = child_env()
    env["FRAMEGATE_LOCAL_PORT"] = str(port)
    env["FRAMEGATE_START_AT_NS"] = str(time.time_ns() - BEHIND_S * 1_000_000_000)
    argv = ["run", service, "--source", "replay", "--path", str(dataset), "--loop"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli", *argv],
        cwd=REPO,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        yield port
    finally:
        proc.terminate()
        proc.wait(timeout=STARTUP_S)


@pytest.fixture
def camera(dataset: Path) -> Iterator[int]:
    yield from _replay_behind("camera", dataset)


@pytest.fixture
def gyro(dataset: Path) -> Iterator[int]:
    yield from _replay_behind("gyro", dataset)


def test_a_camera_that_joins_late_does_not_count_the_frames_before_it_ran(camera: int) -> None:
    with Node(network=NetworkConfig(local_port=camera)) as node:

        def stored_some() -> object:
            try:
                info = node.buffer_info("camera/images", timeout_s=2.0)
            except FramegateError:
                return None
            return info if info.puts >= 10 else None

        info = wait_until(stored_some, STARTUP_S, "the camera to store 10 frames")
    late = info.skipped.get("late", 0)
    # Before the fix every frame of the backlog was counted late at once (>= BACKLOG); a
    # busy machine may still miss a few of the frames due while the camera ran.
    assert late < BACKLOG // 10, f"{late} late of a {BACKLOG}-frame backlog: {info}"


def test_a_gyro_that_joins_late_does_not_count_the_samples_before_it_ran(gyro: int) -> None:
    with Node(network=NetworkConfig(local_port=gyro)) as node:

        def stored_some() -> object:
            try:
                info = node.buffer_info("gyro/rates", timeout_s=2.0)
            except FramegateError:
                return None
            return info if info.puts >= 10 else None

        info = wait_until(stored_some, STARTUP_S, "the gyro to store 10 batches")
    late = info.skipped.get("late", 0)
    # Before the fix every sample due since the launch instant was counted late at once
    # (BEHIND_S s of samples at the dataset's rate, >= 100 per second); a busy machine may
    # still miss a few batches (0.5 s stale each) while the gyro ran.
    assert late < BEHIND_S * 100 // 10, f"{late} late of {BEHIND_S} s behind: {info}"


def test_a_replayed_frame_that_cannot_be_read_is_skipped_and_counted(
    dataset: Path, tmp_path: Path
) -> None:
    """One frame image of a replayed dataset is gone: that frame is counted ``unreadable``
    and the camera goes on (it died, and under ``launch`` would die again at each restart)."""
    import shutil

    broken = tmp_path / "broken"
    shutil.copytree(dataset, broken)
    images = sorted(p for p in broken.rglob("*.png"))
    images[1].unlink()
    port = free_port()
    env = child_env()
    env["FRAMEGATE_LOCAL_PORT"] = str(port)
    argv = ["run", "camera", "--source", "replay", "--path", str(broken), "--loop"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli", *argv],
        cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        with Node(network=NetworkConfig(local_port=port)) as node:

            def past_the_gap() -> object:
                assert proc.poll() is None, "the camera ended"
                try:
                    info = node.buffer_info("camera/images", timeout_s=2.0)
                except FramegateError:
                    return None
                return info if info.skipped.get("unreadable") and info.puts >= 3 else None

            wait_until(past_the_gap, STARTUP_S, "frames after the unreadable one")
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=STARTUP_S)
    assert proc.returncode == 0, err
    assert "Traceback" not in err, err
