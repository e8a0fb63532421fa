"""The viewer's configuration, targets and status bookkeeping (no sockets)."""

from __future__ import annotations

import re
import threading

import pytest

from middleware import ConfigError, FramegateError
from services.tools.bag import derived_topics
from services.tools.view import (
    Counters,
    ViewConfig,
    foxglove_layout,
    installed_layout,
    parse_target,
)
from tests.conftest import REPO


def test_loopback_is_private_and_anything_else_is_exposed() -> None:
    assert not ViewConfig().exposed
    assert not ViewConfig(host="localhost").exposed
    assert not ViewConfig(host="::1").exposed
    assert ViewConfig(host="0.0.0.0").exposed
    assert ViewConfig(host="192.168.1.5").exposed


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"port": 70000}, "--port 70000"),
        ({"jpeg_quality": 0}, "--jpeg 0: JPEG quality must be 1..100"),
        ({"queue": 0}, "--queue 0"),
        # Above the observe limit no producer registers it: refused at once, not retried.
        ({"queue": 99_999_999}, r"--queue 99999999: must be 1\.\.1048576 \(the observe limit\)"),
        ({"backlog": 0}, "--backlog 0"),
        ({"duration_s": -1.0}, "--duration -1.0"),
    ],
)
def test_bad_options_are_named(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        ViewConfig(**kwargs)  # type: ignore[arg-type]


def test_jpeg_quality_switches_frames_to_compressed_images() -> None:
    assert ViewConfig().images == "raw"
    assert ViewConfig(jpeg_quality=70).images == "jpeg"


def test_frames_keep_a_short_queue_and_small_elements_a_long_one() -> None:
    assert ViewConfig(queue=2).queue_for("frame") == 2
    assert ViewConfig(queue=2).queue_for("gyro") == 32
    assert ViewConfig(queue=64).queue_for("decision") == 64


def test_targets_are_a_buffer_or_a_whole_service() -> None:
    assert parse_target("camera/images") == ("camera", "images")
    assert parse_target("/detector") == ("detector", None)
    with pytest.raises(FramegateError, match="camera/images/x"):
        parse_target("camera/images/x")


def test_status_rates_are_over_the_time_since_the_last_snapshot() -> None:
    counters = Counters()
    counters.snapshot("ws://x", 10.0)
    counters.count("/camera/images/image", 30)
    counters.count("/gyro/rates/rates", 200)
    status = counters.snapshot("ws://x", 12.0)
    assert status.rates_hz == {"/camera/images/image": 15.0, "/gyro/rates/rates": 100.0}
    assert counters.snapshot("ws://x", 13.0).rates_hz["/camera/images/image"] == 0.0
    assert status.published == 230


def test_clients_count_while_they_subscribe_to_something() -> None:
    counters = Counters()
    counters.subscribed(1, 10)
    counters.subscribed(1, 11)
    counters.subscribed(2, 10)
    assert counters.snapshot("u", 1.0).clients == 2
    counters.unsubscribed(1, 10)
    assert counters.snapshot("u", 2.0).clients == 2
    counters.unsubscribed(1, 11)
    assert counters.snapshot("u", 3.0).clients == 1


def test_status_line_says_what_was_missed_and_which_client_is_slow() -> None:
    counters = Counters()
    counters.snapshot("ws://127.0.0.1:8765", 0.0)
    counters.subscribed(1, 10)
    counters.count("/camera/images/image", 15)
    counters.set_missed("camera/images", 3)
    counters.add_lost("gyro/rates")
    counters.slow_client("127.0.0.1:5000")
    status = counters.snapshot("ws://127.0.0.1:8765", 1.0)
    line = status.line()
    assert line.startswith("clients 1 | sent: 1 channels 15.0 msg/s, images 15.0/s")
    assert "missed 3 lost 1" in line
    assert line.endswith("| slow: 127.0.0.1:5000 (1x)")
    assert status.json()["slow_clients"] == {"127.0.0.1:5000": 1}
    counters.client_gone("127.0.0.1:5000")
    assert "slow" not in counters.snapshot("u", 2.0).line()


def test_status_line_fits_100_columns_with_many_channels_and_slow_clients() -> None:
    counters = Counters()
    counters.snapshot("ws://127.0.0.1:8765", 0.0)
    for service in ("camera", "gyro", "mediator", "detector", "uncontrolled"):
        for topic in ("image", "metadata", "annotations", "verdict", "rates"):
            counters.count(f"/{service}/{service}/{topic}", 15)
    for port in range(5000, 5010):
        counters.slow_client(f"127.0.0.1:{port}")
        counters.subscribed(port, 1)
    line = counters.snapshot("ws://127.0.0.1:8765", 1.0).line()
    assert len(line) <= 100, line
    assert line.startswith("clients 10 | sent: 25 channels 375.0 msg/s, images 75.0/s")


def test_status_line_without_a_client_says_it_waits_for_one() -> None:
    # It said "clients 0 | no data yet | missed 730", as if data were due and being lost.
    counters = Counters()
    counters.snapshot("ws://127.0.0.1:8765", 0.0)
    assert counters.snapshot("u", 1.0).line() == (
        "clients 0 | waiting for a Foxglove client | missed 0 lost 0"
    )
    counters.subscribed(1, 10)
    assert counters.snapshot("u", 2.0).line().startswith("clients 1 | nothing sent yet |")


class _Sub:
    missed_total = 0


class _Server:
    watched = False

    def wanted(self, topics: object) -> set[str]:
        return {"/camera/images/image"} if self.watched else set()


def test_notifications_passed_over_count_as_missed_only_while_a_client_watches() -> None:
    from services.tools.view._stream import BufferStream

    counters, sub, server = Counters(), _Sub(), _Server()
    stream = object.__new__(BufferStream)
    stream.name = "camera/images"
    stream.__dict__.update(
        _sub=sub,
        _server=server,
        _counters=counters,
        _missed_seen=0,
        _missed=0,
        _deriver=type("D", (), {"topics": ()})(),
    )
    sub.missed_total = 730  # nobody watching: passed over, missed by no one
    stream._count_missed()
    assert counters.snapshot("u", 1.0).missed == 0
    server.watched, sub.missed_total = True, 733
    stream._count_missed()
    assert counters.snapshot("u", 2.0).missed == 3


def test_the_layout_files_are_the_generated_layout_and_names_only_produced_topics() -> None:
    for committed in (REPO / "deploy" / "foxglove-layout.json", installed_layout()):
        assert committed.read_text() == foxglove_layout(), (
            f"regenerate: python -m services.tools.view._layout > {committed}"
        )
    produced = {
        t.topic
        for service, buffer, kind in [
            ("camera", "images", "frame"),
            ("mediator", "decisions", "decision"),
            ("detector", "detections", "detections"),
            ("gyro", "rates", "gyro"),
        ]
        for t in derived_topics(service, buffer, kind, images="raw")
    }
    named = set(re.findall(r'"(/[a-z]+/[a-z]+/[a-z]+)', foxglove_layout()))
    assert named and named <= produced, named - produced


class _Ended:
    """A stream whose thread ended with an error (the view loop only looks at these)."""

    def __init__(self, alive: bool) -> None:
        import threading

        self.thread = threading.Thread(target=lambda: None)
        if not alive:
            self.thread.start()
            self.thread.join()
        else:
            self.thread.is_alive = lambda: True  # type: ignore[method-assign]
        self.error = None if alive else FramegateError("fetch failed")
        self.closed = False

    def close(self) -> None:
        self.closed = True


def test_a_stream_that_died_is_said_and_started_again(caplog: pytest.LogCaptureFixture) -> None:
    from services.tools.view._view import _drop_dead

    dead, live = _Ended(alive=False), _Ended(alive=True)
    streams = {"camera/images": dead, "gyro/rates": live}
    _drop_dead(streams)  # type: ignore[arg-type]
    assert list(streams) == ["gyro/rates"] and dead.closed and not live.closed
    assert "streaming camera/images stopped" in caplog.text and "fetch failed" in caplog.text


class _NothingLive:
    def services(self, timeout_s: float = 0.0) -> list[object]:
        return []


def test_a_stop_while_waiting_for_named_buffers_is_a_stop_not_an_error() -> None:
    """`framegate view camera/images` before the camera is up ignored Ctrl-C and SIGTERM for
    the whole --timeout, then exited 1 with `error: no live service named 'camera'`."""
    from services.tools.view import check_targets

    stop = threading.Event()
    stop.set()  # Ctrl-C, while the view waits for camera/images
    assert not check_targets(_NothingLive(), ("camera/images",), 3600.0, stop)  # type: ignore[arg-type]
