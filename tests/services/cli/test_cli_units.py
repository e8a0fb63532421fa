"""The CLI's pure parts: time flags, hz statistics, and the MCAP layout (no network)."""

from __future__ import annotations

import argparse
import json
import re
import threading
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import pytest
from mcap.reader import make_reader

from middleware import (
    BufferInfo,
    DataObject,
    QueryError,
    Retention,
    SchemaError,
    make_metadata,
    validate_metadata,
)
from services.cli import query
from services.cli._common import recording_input, recording_output
from services.cli.hz import Sample, window_stats
from services.cli.play import _retention
from services.tools.bag import (
    BagError,
    BagWriter,
    RecordedBuffer,
    frame_layout,
    open_bag,
    shift_element,
)
from tests.services.cli.conftest import HEIGHT, MS, WIDTH, frame_metadata, frame_payload

SECOND = 1_000_000_000


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("now", (0, True)),
        ("-5s", (-5 * SECOND, True)),
        ("-1.5m", (-90 * SECOND, True)),
        ("now(-2s)", (-2 * SECOND, True)),
        ("1763820000000000000", (1763820000000000000, False)),
        ("2026-11-22T14:00:00.5Z", (1795356000 * SECOND + SECOND // 2, False)),
    ],
)
def test_cli_times_are_absolute_or_relative(text: str, expected: tuple[int, bool]) -> None:
    assert query.parse_cli_time(text, "--from") == expected


def test_an_integer_time_out_of_range_is_named_out_of_range_with_the_range() -> None:
    with pytest.raises(QueryError, match=r"--from: time .* is out of range: times lie between 0"):
        query.parse_cli_time("99999999999999999999999", "--from")
    with pytest.raises(QueryError, match=r"bad time 'soon' for --from"):
        query.parse_cli_time("soon", "--from")


def test_a_range_older_than_the_buffer_is_named_with_its_retention() -> None:
    buffer = BufferInfo(
        service="cam", buffer="images", kind="frame", retention=Retention(max_count=64),
        count=64, payload_bytes=64, oldest_ns=100 * SECOND, newest_ns=104 * SECOND,
        rate_hz=15.0, puts=900, refused=0, rejected=0,
    )  # fmt: skip
    note = query.retention_note(buffer, 40 * SECOND)
    assert note is not None
    assert note.startswith("the range starts 1 min 0 s before cam/images's oldest element")
    assert "it keeps max 64 elements, max 512.0 MiB" in note
    # A range within what the buffer holds, or with no start, needs no note.
    assert query.retention_note(buffer, 100 * SECOND) is None
    assert query.retention_note(buffer, None) is None


def test_a_bad_time_names_the_flag_and_the_accepted_forms() -> None:
    with pytest.raises(QueryError, match=r"bad time 'yesterday' for --to: write now, -5s"):
        query.parse_cli_time("yesterday", "--to")


def test_negative_relative_times_parse_as_values_not_options() -> None:
    parser = argparse.ArgumentParser()
    query.register(parser.add_subparsers())
    args = parser.parse_args(["query", "cam/images", "--from", "-5s", "--to", "now"])
    assert (args.start, args.end) == ("-5s", "now")


def test_hz_statistics_skip_intervals_across_missed_elements() -> None:
    samples = [
        Sample(seq=1, timestamp_ns=0, arrival_ns=0, payload_bytes=100),
        Sample(seq=2, timestamp_ns=10 * MS, arrival_ns=10 * MS, payload_bytes=300),
        # seq 3 was missed: the 20 ms gap is not an interval, but it counts for the rate
        Sample(seq=4, timestamp_ns=30 * MS, arrival_ns=31 * MS, payload_bytes=None),
        Sample(seq=5, timestamp_ns=42 * MS, arrival_ns=41 * MS, payload_bytes=200),
    ]
    stats = window_stats(samples)
    assert stats["rate_hz"] == pytest.approx(4 / 0.041)  # arrivals, as ros2 topic hz
    assert stats["stamp_rate_hz"] == pytest.approx(4 / 0.042)
    assert (stats["min_s"], stats["max_s"]) == (pytest.approx(0.010), pytest.approx(0.010))
    assert stats["std_s"] == pytest.approx(0.0)
    assert stats["stamp_std_s"] == pytest.approx(0.001)
    assert stats["mean_bytes"] == 200
    assert stats["bandwidth_bytes_s"] == pytest.approx(200 * 4 / 0.041)
    assert window_stats(samples[:1])["rate_hz"] is None


def test_hz_reports_arrivals_first_and_the_stamps_rate_beside_it() -> None:
    # A recording of 15 Hz played at half speed: stamps 66.7 ms apart arrive 133 ms apart.
    period_ns = 1_000_000_000 // 15
    samples = [
        Sample(seq=i + 1, timestamp_ns=i * period_ns, arrival_ns=2 * i * period_ns, payload_bytes=1)
        for i in range(30)
    ]
    stats = window_stats(samples)
    assert stats["rate_hz"] == pytest.approx(7.5)
    assert stats["stamp_rate_hz"] == pytest.approx(15.0)


def _write_bag(path: Path) -> list[DataObject]:
    frames = [DataObject(t, frame_payload(i), frame_metadata(t, i)) for i, t in enumerate((5, 9))]
    with BagWriter(path) as writer:
        writer.add_buffer("cam", "images", kind="frame", retention=Retention(max_count=7))
        writer.add_buffer("imu", "gyro", kind="generic", retention=Retention())
        writer.write("imu/gyro", DataObject(7, b"g", make_metadata("generic", 7)))
        for frame in frames:
            writer.write("cam/images", frame)
        # A frame whose payload does not match its layout gets no image message.
        writer.write("cam/images", DataObject(11, b"short", frame_metadata(11, 2)))
    return frames


def test_a_recording_reads_back_in_time_order_with_kinds_and_retention(tmp_path: Path) -> None:
    path = tmp_path / "a.mcap"
    frames = _write_bag(path)
    with open_bag(path) as bag:
        assert [(b.name, b.kind, b.count) for b in bag.buffers] == [
            ("cam/images", "frame", 3),
            ("imu/gyro", "generic", 1),
        ]
        assert bag.buffers[0].retention == Retention(max_count=7)
        order = [(b.name, e.timestamp_ns) for b, e in bag.elements()]
        assert order == [("cam/images", 5), ("imu/gyro", 7), ("cam/images", 9), ("cam/images", 11)]
        assert [e for b, e in bag.elements([bag.buffers[0]])][:2] == frames
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None and summary.statistics is not None
    counts = {
        summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()
    }
    assert counts == {"/cam/images": 3, "/cam/images/image": 2, "/imu/gyro": 1}


def test_bad_files_are_named_in_the_error(tmp_path: Path) -> None:
    with pytest.raises(BagError, match=r"cannot read .*missing\.mcap"):
        open_bag(tmp_path / "missing.mcap")
    text = tmp_path / "text.mcap"
    text.write_text("not a recording")
    with pytest.raises(BagError, match="is not an MCAP file"):
        open_bag(text)
    whole = tmp_path / "whole.mcap"
    _write_bag(whole)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole.read_bytes()[:200])
    # Cut inside its first chunk: nothing to recover, and the message says so.
    with pytest.raises(BagError, match="cut short before its first complete chunk"):
        open_bag(cut)
    with pytest.raises(BagError, match="exists"):
        BagWriter(whole)


def test_shifting_moves_timestamps_but_not_durations() -> None:
    element = DataObject(5 * SECOND, frame_payload(1), frame_metadata(5 * SECOND, 1))
    shifted = shift_element(element, "frame", 3 * SECOND)
    assert shifted.timestamp_ns == 8 * SECOND and shifted.payload == element.payload
    assert shifted.metadata == frame_metadata(8 * SECOND, 1)  # exposure_ns stays 2 ms
    validate_metadata(shifted.metadata, "frame")
    assert shift_element(element, "frame", 0) is element


@pytest.mark.parametrize(
    "text", ["\u00b2", "9" * 5000, "\u0663"], ids=["superscript", "5000 digits", "Arabic-Indic"]
)
def test_shifting_leaves_a_time_field_that_is_no_number_for_the_buffer_to_refuse(
    text: str,
) -> None:
    """A recording's field typed as a time holding a superscript two, 5,000 digits or an
    Arabic-Indic digit (each ``isdigit``): ``play --rebase`` ended in a ValueError
    traceback; now the field stays as recorded and the buffer refuses it (a counted skip)."""
    metadata = (
        '<metadata xmlns="urn:framegate:1" kind="decision" timestamp_ns="5">'
        f"<frame_timestamp_ns>{text}</frame_timestamp_ns></metadata>"
    )
    element = DataObject(5, b"", metadata.encode())
    shifted = shift_element(element, "decision", 3)
    assert shifted.timestamp_ns == 8
    assert f"<frame_timestamp_ns>{text}</frame_timestamp_ns>" in shifted.metadata.decode()
    with pytest.raises(SchemaError):
        validate_metadata(shifted.metadata, "decision")


def test_shifting_a_gyro_batch_moves_its_sample_times_with_its_key() -> None:
    # The mediator reads the samples' times from the payload: with --rebase/--loop they
    # stayed as recorded, minutes away from the frames, and every frame was gyro-missing.
    import numpy as np

    from services.lib.messages import gyro_metadata
    from services.lib.quality import GyroSamples

    t_ns = np.arange(5 * SECOND, 5 * SECOND + 10 * MS, MS, dtype=np.int64)
    rates = np.linspace(-1.0, 1.0, t_ns.size * 3).reshape(-1, 3)
    samples = GyroSamples(t_ns, rates)
    element = DataObject(int(t_ns[-1]), samples.to_bytes(), gyro_metadata(samples))
    shifted = shift_element(element, "gyro", 3 * SECOND)
    moved = GyroSamples.from_bytes(shifted.payload)
    assert shifted.timestamp_ns == element.timestamp_ns + 3 * SECOND
    assert moved.t_ns.tolist() == (t_ns + 3 * SECOND).tolist()
    assert moved.rates_rad_s.tobytes() == samples.rates_rad_s.tobytes()
    assert shifted.metadata == gyro_metadata(moved)
    validate_metadata(shifted.metadata, "gyro")
    # A payload that holds no whole record has no times to move; it is passed on as it is.
    garbled = DataObject(element.timestamp_ns, b"\x01\x02\x03", element.metadata)
    assert shift_element(garbled, "gyro", SECOND).payload == b"\x01\x02\x03"


def test_frame_layout_needs_a_raw_encoding_and_a_matching_payload() -> None:
    layout = frame_layout(frame_metadata(1, 1), WIDTH * HEIGHT)
    assert layout is not None and (layout.step_bytes, layout.size_bytes) == (WIDTH, WIDTH * HEIGHT)
    assert frame_layout(frame_metadata(1, 1), 3) is None
    assert frame_layout(make_metadata("generic", 1)) is None


def test_a_recording_named_without_its_suffix_is_the_mcap_file(tmp_path: Path) -> None:
    assert recording_output(tmp_path / "run") == tmp_path / "run.mcap"
    assert recording_output(tmp_path / "run.mcap") == tmp_path / "run.mcap"
    assert recording_output(tmp_path) == tmp_path  # a directory is refused by name later
    assert recording_input(tmp_path / "run") == tmp_path / "run"  # neither exists
    (tmp_path / "run.mcap").write_bytes(b"")
    assert recording_input(tmp_path / "run") == tmp_path / "run.mcap"
    (tmp_path / "run").write_bytes(b"")  # a file of the very name given wins
    assert recording_input(tmp_path / "run") == tmp_path / "run"


def test_info_of_a_recording_gives_its_window_beside_the_span(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A buffer's newest element at the start is recorded however old: the span of a 5 s
    recording began 13 min earlier, and info gave only that span."""
    from services.cli import main

    started = 10**18
    info_t = started - 600 * SECOND  # a camera description put 10 min before
    bag = tmp_path / "run.mcap"
    with BagWriter(bag) as writer:
        writer.add_buffer("cam", "info", kind="generic", retention=Retention())
        writer.write("cam/info", DataObject(info_t, b"d", make_metadata("generic", info_t)))
        writer.write("cam/info", DataObject(started + SECOND, b"d", make_metadata("generic", 1)))
        writer.add_metadata(
            "framegate.recording",
            {"host": "robot", "started_ns": str(started), "stopped_ns": str(started + 5 * SECOND)},
        )
    assert main(["info", str(bag)]) == 0
    out = capsys.readouterr().out
    assert (
        "Recorded:      2001-09-09T01:46:40.000000Z .. 2001-09-09T01:46:45.000000Z "
        "(5.0 s, on host robot)" in out
    )
    assert "(601.0 s; it begins 10 min 0 s before the recording: each buffer's newest" in out
    assert "Messages:      2 messages in 1 chunk\n" in out
    assert main(["info", str(tmp_path / "run"), "--json"]) == 0  # the suffix may be left out
    data = json.loads(capsys.readouterr().out)
    assert (data["recorded_start_ns"], data["recorded_stop_ns"]) == (started, started + 5 * SECOND)


@pytest.mark.parametrize("command", [["bench", "--quick", "small"], ["soak"], ["faults"]])
@pytest.mark.parametrize(
    ("where", "expected"),
    [
        ("no/report.json", r"argument --json: cannot write .*/no/report\.json: directory .*/no "
         r"does not exist"),
        (".", r"argument --json: .* is a directory; give a file, e.g. .*/report\.json"),
    ],
)  # fmt: skip
def test_json_report_file_of_a_long_run_is_checked_before_it_runs(
    command: list[str],
    where: str,
    expected: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """bench, soak and faults write --json FILE at their end: soak and faults ran for their
    whole duration, then failed ("No such file or directory"); bench checked first."""
    from services.cli import main

    assert main([*command, "--json", str(tmp_path / where)]) == 1
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and re.search(expected, err), err


def test_play_only_a_misspelt_buffer_gets_a_did_you_mean(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from services.cli import main

    bag = tmp_path / "run.mcap"
    with BagWriter(bag) as writer:
        writer.add_buffer("cam", "images", kind="generic", retention=Retention())
        writer.write("cam/images", DataObject(1, b"x", make_metadata("generic", 1)))
    assert main(["play", str(bag), "--only", "cam/imgaes"]) == 1
    err = capsys.readouterr().err
    assert "has no buffer 'cam/imgaes' (did you mean 'cam/images'?); it holds: cam/images" in err


class _StillFetching:
    """A recorder thread still fetching the tail when a second Ctrl-C comes."""

    def is_alive(self) -> bool:
        return True

    def join(self, timeout: float | None = None) -> None:
        raise KeyboardInterrupt  # the second Ctrl-C, while record waits for it


class _CtrlC(threading.Event):
    def wait(self, timeout: float | None = None) -> bool:
        raise KeyboardInterrupt  # the first Ctrl-C


def test_a_second_ctrl_c_cuts_records_wait_short_and_says_so() -> None:
    """It escaped ``record``: the file closed without its counts (`info FILE.mcap` had no
    Recorded or Recorder lines) and no summary was printed, not a word."""
    from services.cli.record import _wait

    recorders = [
        SimpleNamespace(
            thread=_StillFetching(),
            stop=_CtrlC(),
            queue=SimpleNamespace(error=None),
            stop_ns=None,
            deadline=None,
            offset_ns=0,
        )
        for _ in range(2)
    ]
    try:
        stopped_ns, cut = _wait(recorders, 1_000, 0.0, None)  # type: ignore[arg-type]
    except KeyboardInterrupt:
        pytest.fail("the second Ctrl-C escaped record's wait: no counts, no summary")
    assert cut and stopped_ns > 1_000
    assert recorders[0].stop.is_set()


def test_play_loop_keep_all_keeps_one_pass_not_every_pass() -> None:
    recorded = RecordedBuffer(
        "camera", "images", "frame", Retention(max_count=64), "camera/images", 1, count=77
    )
    kept = _retention(recorded, keep_all=True, loop=False)
    assert (kept.max_count, kept.max_bytes, kept.max_age_ns) == (None, None, None)
    # A loop never ends: every pass kept is memory without bound.
    looped = _retention(recorded, keep_all=True, loop=True)
    assert (looped.max_count, looped.max_bytes, looped.max_age_ns) == (77, None, None)
    unknown = replace(recorded, count=0)  # a damaged file without its statistics
    assert _retention(unknown, keep_all=True, loop=True) == recorded.retention


@pytest.mark.parametrize("encoding", ["bgr8", "rgb8", "bgra8", "rgba8"])
def test_query_save_writes_colour_frames_as_png_with_their_alpha(
    tmp_path: Path, encoding: str
) -> None:
    import cv2
    import numpy as np

    from services.lib.messages import frame_metadata_of
    from services.lib.quality import Exposure

    bgra = np.zeros((3, 4, 4), np.uint8)
    bgra[..., 0], bgra[..., 2], bgra[..., 3] = 200, 30, np.arange(12).reshape(3, 4)
    image = {
        "bgr8": bgra[..., :3],
        "rgb8": bgra[..., 2::-1],
        "bgra8": bgra,
        "rgba8": bgra[..., [2, 1, 0, 3]],
    }[encoding]
    metadata = frame_metadata_of(1, Exposure(5, 2), encoding, 4, 3, None)
    element = DataObject(5, np.ascontiguousarray(image).tobytes(), metadata)
    saved = query._save_all(tmp_path, [element], force=False)
    assert saved == {5: [str(tmp_path / "5.png"), str(tmp_path / "5.xml")]}
    read = cv2.imread(str(tmp_path / "5.png"), cv2.IMREAD_UNCHANGED)
    assert read.tolist() == (bgra if "a8" in encoding else bgra[..., :3]).tolist()


def test_query_save_writes_a_mono16_frame_as_a_16_bit_png(tmp_path: Path) -> None:
    import cv2
    import numpy as np

    from services.lib.messages import frame_metadata_of
    from services.lib.quality import Exposure

    samples = (np.arange(12, dtype=np.uint16) * 5000).reshape(3, 4)
    metadata = frame_metadata_of(1, Exposure(5, 2), "mono16", 4, 3, None)
    element = DataObject(5, samples.astype("<u2").tobytes(), metadata)
    query._save_all(tmp_path, [element], force=False)
    read = cv2.imread(str(tmp_path / "5.png"), cv2.IMREAD_UNCHANGED)
    assert read.dtype == np.uint16 and read.tolist() == samples.tolist()
