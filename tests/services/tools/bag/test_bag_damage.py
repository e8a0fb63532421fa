"""Recordings that survive: a file cut short plays up to its last complete chunk, and a
damaged one is a one-line error or a stated partial recovery, never a traceback."""

from __future__ import annotations

import random
import subprocess
import sys
from pathlib import Path

import pytest

from middleware import DataObject, Retention, make_metadata
from services.tools.bag import BagError, BagWriter, recording_info
from tests.conftest import REPO, child_env, free_port
from tests.helpers.timing import scaled

N = 300


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("bag") / "run.mcap"
    with BagWriter(path, images=False, compression="zstd", overwrite=False) as writer:
        writer.add_buffer("cam", "log", kind="generic", retention=Retention())
        for t in range(1, N + 1):
            # Incompressible payloads, so that the file has several chunks.
            payload = random.Random(t).randbytes(40_000)
            writer.write("cam/log", DataObject(t, payload, make_metadata("generic", t)))
    return path


def test_a_complete_recording_is_described_as_such(recording: Path) -> None:
    info = recording_info(recording)
    assert info.status == "complete" and info.messages == N and info.chunks >= 3


@pytest.mark.parametrize("keep", [0.5, 0.8, 0.95])
def test_a_file_cut_short_keeps_every_whole_chunk_before_the_cut(
    recording: Path, tmp_path: Path, keep: float
) -> None:
    data = recording.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * keep)])
    info = recording_info(cut)
    assert info.status == "recovered" and "cut short" in info.integrity
    assert 0 < info.messages < N
    assert info.end_ns == info.messages  # stamps 1..N in order: nothing after a gap


@pytest.mark.parametrize("where", [0.1, 0.35, 0.5, 0.8, 0.97, 0.999])
def test_a_flipped_byte_is_one_error_or_a_stated_recovery(
    recording: Path, tmp_path: Path, where: float
) -> None:
    data = bytearray(recording.read_bytes())
    at = int(len(data) * where)
    data[at] ^= 0xFF
    bad = tmp_path / "flipped.mcap"
    bad.write_bytes(bytes(data))
    result = subprocess.run(
        [sys.executable, "-m", "services.cli", "info", str(bad)],
        cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=scaled(60), check=False,
    )  # fmt: skip
    assert "Traceback" not in result.stderr, result.stderr
    if result.returncode == 0:  # recovered: it says what was lost
        assert "recovered" in result.stdout or "complete" in result.stdout, result.stdout
        if "complete" in result.stdout.split("Status:")[1].splitlines()[0]:
            pytest.fail(f"a flipped byte at {at} went unnoticed: {result.stdout}")
    else:
        assert result.returncode == 1
        assert len(result.stderr.strip().splitlines()) == 1 and result.stderr.startswith("error: ")


def test_a_file_cut_before_its_first_chunk_is_a_bag_error(recording: Path, tmp_path: Path) -> None:
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(recording.read_bytes()[:1000])
    with pytest.raises(BagError, match="cut short before its first complete chunk"):
        recording_info(cut)


def test_not_an_mcap_file_is_a_bag_error(tmp_path: Path) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x00" * 100)
    with pytest.raises(BagError, match="not an MCAP file"):
        recording_info(junk)


def _play(path: Path) -> subprocess.CompletedProcess[str]:
    """``framegate play --fast --exit-when-done`` on a private rendezvous port."""
    env = child_env()
    env["FRAMEGATE_LOCAL_PORT"] = str(free_port())
    return subprocess.run(
        [sys.executable, "-m", "services.cli", "play", str(path), "--fast", "--exit-when-done",
         "--start-delay", "0"],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=scaled(120), check=False,
    )  # fmt: skip


@pytest.mark.integration
@pytest.mark.parametrize("where", [0.1, 0.5, 0.97, 0.999])
def test_play_of_a_flipped_byte_is_one_error_line_or_a_stated_recovery(
    recording: Path, tmp_path: Path, where: float
) -> None:
    data = bytearray(recording.read_bytes())
    data[int(len(data) * where)] ^= 0xFF
    bad = tmp_path / "flipped.mcap"
    bad.write_bytes(bytes(data))
    result = _play(bad)
    assert "Traceback" not in result.stderr, result.stderr
    lines = result.stderr.strip().splitlines()
    if result.returncode == 0:  # played what was whole, and said what it recovered
        assert any("recovered" in line for line in lines), result.stderr
    else:
        assert result.returncode == 1, result.stderr
        assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr


@pytest.mark.integration
def test_play_of_a_cut_short_file_says_how_much_it_recovered(
    recording: Path, tmp_path: Path
) -> None:
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(recording.read_bytes()[: int(recording.stat().st_size * 0.6)])
    result = _play(cut)
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    assert any("recovered" in line for line in result.stderr.splitlines()), result.stderr


@pytest.mark.parametrize(
    "text",
    ['{"max_count": 1.5}', '{"max_count": NaN}', '{"max_count": 1e400}', '{"max_bytes": true}'],
)
def test_a_recorded_retention_that_is_no_whole_number_is_a_bag_error(text: str) -> None:
    """A file's channel says how much its buffer keeps; 1.5 broke eviction at the first put
    (a traceback from ``play``), NaN and true were taken."""
    from services.tools.bag._format import retention_from_json

    with pytest.raises(BagError, match=r"bad framegate\.retention"):
        retention_from_json(text, "x.mcap")


@pytest.mark.parametrize(
    ("lost_from_byte", "ending"),
    [
        (
            1_000,
            "the 500 bytes after its last complete chunk and anything not yet written are lost",
        ),
        (1_500, "anything not yet written is lost"),  # it said "... written are lost"
    ],
)
def test_a_cut_recording_says_what_is_lost_in_a_sentence(lost_from_byte: int, ending: str) -> None:
    from services.tools.bag._scan import Integrity

    integrity = Integrity(
        complete=False, size_bytes=1_500, messages=3, start_ns=1, end_ns=3,
        lost_from_byte=lost_from_byte, cut_short=True,
    )  # fmt: skip
    text = integrity.describe("the end")
    head = "recovered 3 messages up to the end; the file was cut short at byte 1500"
    assert text == f"{head} (no summary): {ending}"
