"""``framegate record`` of a running pipeline keeps every element its buffers still hold,
byte for byte, and says what it lost apart from what the buffers lost.

Real processes: a camera and a gyro replaying a small simulated approach (``launch``), and
``record`` as a user runs it; the file is then compared element by element with what the
buffers hold.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from middleware import DataObject, FramegateError, NetworkConfig, Node, TimeRange
from services.tools.bag import open_bag, recording_info
from tests.conftest import REPO, child_env, free_port, wait_until
from tests.helpers.frames import simulated_frames
from tests.helpers.timing import answered, scaled

pytestmark = pytest.mark.integration

STARTUP_S = 300.0
BUFFERS = ("camera/images", "camera/info", "gyro/rates")
LIMIT = ("--duration", "4", "--json")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulated_frames(tmp_path_factory.mktemp("approach") / "data")


@pytest.fixture
def pipeline(dataset: Path, tmp_path: Path) -> Iterator[dict[str, str]]:
    """Camera and gyro replaying ``dataset`` in a loop; the environment that reaches them."""
    source = f"source: replay, path: {dataset}, loop: true"
    # A minute of frames: the comparison after the recording must still find them held.
    camera = f"{{{source}, retention_frames: 1000}}"
    deploy = tmp_path / "sensors.yaml"
    deploy.write_text(
        f"services:\n  camera:\n    args: {camera}\n  gyro:\n    args: {{{source}}}\n"
    )
    env = child_env()
    env["FRAMEGATE_LOCAL_PORT"] = str(free_port())
    env["FRAMEGATE_RUNTIME_DIR"] = str(tmp_path / "run")
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "launch", str(deploy), "--no-colour"],
        cwd=REPO,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        yield env
    finally:
        proc.terminate()
        proc.wait(timeout=STARTUP_S)


def _record(pipeline: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    """``framegate record *args`` against the pipeline, to its end."""
    return subprocess.run(
        [sys.executable, "-m", "services.cli", "record", *args],
        cwd=REPO,
        env=pipeline,
        capture_output=True,
        text=True,
        timeout=STARTUP_S,
    )


def _held(node: Node, target: str, since_ns: int) -> dict[int, DataObject]:
    """What ``target`` holds from ``since_ns`` on (not all it holds: a minute of frames is
    too much to fetch in time on a loaded machine)."""
    span = TimeRange(since_ns, None)
    elements = answered(
        lambda: node.query(target, time_range=span, timeout_s=scaled(30)), f"{target}'s elements"
    )
    return {e.timestamp_ns: e for e in elements}


def _recorded(out: Path) -> tuple[dict[str, str], dict[str, dict[int, DataObject]]]:
    """The recording's account and its elements, by buffer and timestamp."""
    recorded: dict[str, dict[int, DataObject]] = {}
    with open_bag(out) as bag:
        account = _recording_account(bag.metadata)
        for buffer_of, element in bag.elements():
            recorded.setdefault(buffer_of.name, {})[element.timestamp_ns] = element
    return account, recorded


def test_record_keeps_every_element_its_buffers_hold(
    pipeline: dict[str, str], tmp_path: Path
) -> None:
    port = int(pipeline["FRAMEGATE_LOCAL_PORT"])
    with Node(network=NetworkConfig(local_port=port)) as node:

        def producing() -> bool:
            try:
                return node.buffer_info("camera/images", timeout_s=2.0).puts >= 5
            except FramegateError:
                return False

        wait_until(producing, STARTUP_S, "the camera to store frames")
        out = tmp_path / "run.mcap"
        result = _record(pipeline, *BUFFERS, "-o", str(out), *LIMIT)
        assert result.returncode == 0, result.stderr
        account, recorded = _recorded(out)
        assert set(recorded) == set(BUFFERS), list(recorded)
        # At once, while the buffers still hold what was recorded.
        held = {target: _held(node, target, min(recorded[target])) for target in BUFFERS}
    summary = {row["name"]: row for row in json.loads(result.stdout)["buffers"]}
    started_ns, stopped_ns = int(account["started_ns"]), int(account["stopped_ns"])
    for target in BUFFERS:
        row, file, buffer = summary[target], recorded[target], held[target]
        assert row["recorded"] == len(file) > 0, row
        # The file starts at the recording's start for every buffer (its newest element
        # then), however long after the start the recorder reached it.
        assert min(file) <= started_ns, f"{target}: starts {min(file) - started_ns} ns late"
        inside = {t: e for t, e in buffer.items() if min(file) <= t <= stopped_ns}
        assert inside, f"{target}: the buffer no longer holds any of the recording"
        # Nothing held is missing, except (on a machine too busy to fetch it within a
        # second of the stop, or to hand it over before the file closes) a tail after the
        # last element recorded, counted as evicted or dropped: never a hole.
        missing = sorted(set(inside) - set(file))
        assert all(t > max(file) for t in missing), f"{target}: held but not recorded: {missing}"
        assert len(missing) <= row["evicted"] + row["dropped"], (target, len(missing), row)
        for t, element in inside.items():
            if t not in file:
                continue
            assert file[t].payload == element.payload, f"{target} @ {t}: payload differs"
            assert file[t].metadata == element.metadata, f"{target} @ {t}: metadata differs"
    # The camera's description, put once at its start, is in the file (as a latched topic).
    assert len(recorded["camera/info"]) == 1
    # `info FILE.mcap` gives the recorder's account of the two losses.
    told = {b.name: b for b in recording_info(out).buffers}
    assert set(told) == set(BUFFERS)
    assert all(b.evicted == summary[n]["evicted"] for n, b in told.items()), told
    assert all(b.dropped == summary[n]["dropped"] for n, b in told.items()), told
    assert told["gyro/rates"].recorded == len(recorded["gyro/rates"])


def _recording_account(bag_metadata: list[Any]) -> dict[str, str]:
    return next(m.metadata for m in bag_metadata if m.name == "framegate.recording")


def test_record_ends_at_its_duration_in_the_producers_stamps_and_counts_what_it_missed(
    pipeline: dict[str, str], tmp_path: Path
) -> None:
    """--duration counts from the recording's start: the stop instant is exactly start +
    duration (not the instant a busy machine noticed it), nothing the producers stamped
    later is in the file, and every element the buffers held before it is in the file or
    counted as lost (evicted or dropped): never missing uncounted."""
    duration_s = 3
    port = int(pipeline["FRAMEGATE_LOCAL_PORT"])
    with Node(network=NetworkConfig(local_port=port)) as node:
        wait_until(
            lambda: _puts(node, "camera/images") >= 5, STARTUP_S, "the camera to store frames"
        )
        out = tmp_path / "run.mcap"
        argv = ["camera/images", "gyro/rates", "-o", str(out)]
        result = _record(pipeline, *argv, "--duration", str(duration_s), "--json")
        assert result.returncode == 0, result.stderr
        # The producers run on: wait until each buffer holds elements stamped after the stop.
        account, elements = _recorded(out)
        recorded = {target: list(elements.get(target, {})) for target in argv[:2]}
        started_ns, stopped_ns = int(account["started_ns"]), int(account["stopped_ns"])
        for target in recorded:
            wait_until(
                lambda t=target: (_newest(node, t) or 0) > stopped_ns,  # type: ignore[misc]
                STARTUP_S,
                f"{target} to store an element stamped after the stop",
            )
        held = {t: _held(node, t, min(stamps, default=0)) for t, stamps in recorded.items()}
    assert stopped_ns - started_ns == duration_s * 1_000_000_000
    summary = json.loads(result.stdout)
    assert summary["duration_s"] == duration_s
    rows = {row["name"]: row for row in summary["buffers"]}
    for target, stamps in recorded.items():
        row = rows[target]
        assert stamps, f"{target}: nothing recorded"
        assert row["recorded"] == len(stamps) == len(set(stamps)), row
        # The span ends at the stop instant, in the producer's own stamps.
        assert max(stamps) <= stopped_ns, (
            f"{target}: recorded past the stop by {max(stamps) - stopped_ns} ns"
        )
        assert any(t > stopped_ns for t in held[target])
        # Everything held in the recorded span is in the file or counted lost.
        inside = [t for t in held[target] if min(stamps) <= t <= stopped_ns]
        absent = set(inside) - set(stamps)
        assert len(absent) <= row["evicted"] + row["dropped"], (target, len(absent), row)
        assert all(t > max(stamps) for t in absent), f"{target}: a gap inside the recording"


def _newest(node: Node, target: str) -> int | None:
    try:
        return node.buffer_info(target, timeout_s=2.0).newest_ns
    except FramegateError:
        return None


def _puts(node: Node, target: str) -> int:
    try:
        return node.buffer_info(target, timeout_s=2.0).puts
    except FramegateError:
        return 0
