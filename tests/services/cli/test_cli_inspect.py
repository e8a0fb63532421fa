"""info, query, watch and hz as real subprocesses against a live service on loopback."""

from __future__ import annotations

import base64
import os
import re
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import pytest

from middleware import (
    FlowControlRefused,
    NetworkConfig,
    Node,
    Producer,
    SubscriptionMode,
    make_metadata,
)
from tests.conftest import free_port
from tests.helpers.background import in_background
from tests.helpers.timing import scaled
from tests.services.cli.conftest import (
    ABSENCE_TIMEOUT_S,
    HEIGHT,
    MS,
    WIDTH,
    Cli,
    frame_metadata,
    frame_payload,
    put_frame,
)

pytestmark = pytest.mark.integration

SECOND = 1_000_000_000


def test_info_and_query_report_what_the_buffer_holds(
    service: Node, endpoint: str, cli: Cli, tmp_path: Path
) -> None:
    images = service.offer("images", kind="frame")
    base = (time.time_ns() // SECOND - 60) * SECOND  # a minute ago, on a whole second
    with Node(network=NetworkConfig(connect=(endpoint,))) as client:
        client.subscribe("cam/images", queue_size=4, mode=SubscriptionMode.FLOW)
        assert images.wait_for_subscribers(1, timeout_s=scaled(10))
        for i in range(4):
            put_frame(images, base + i * 100 * MS, i)
        with pytest.raises(FlowControlRefused):  # nobody takes: the queue of 4 is full
            put_frame(images, base + 400 * MS, 4)
        info, in_range, nearest, recent = cli.run_many(
            [
                ("info", "cam/images", "--json"),
                ("query", "cam/images", "--from", str(base + 100 * MS), "--to",
                 str(base + 250 * MS), "--save", str(tmp_path / "saved"), "--json"),
                ("query", "cam/images", "--at", str(base + 260 * MS), "--json",
                 "--with-payload"),
                ("query", "cam/images", "--from", "-1h", "--last", "2", "--json"),
            ]
        )  # fmt: skip
    data = info.json()
    assert data["kind"] == "frame" and data["name"] == "cam/images"
    assert data["count"] == 4 and data["payload_bytes"] > 4 * WIDTH * HEIGHT
    assert (data["oldest_ns"], data["newest_ns"]) == (base, base + 300 * MS)
    assert (data["puts"], data["refused"], data["rejected"]) == (4, 1, 0)
    assert data["retention"]["max_count"] == 1000
    assert data["pid"] == os.getpid() and isinstance(data["clock_offset_ns"], int)
    [sub] = data["subscriptions"]
    assert (sub["mode"], sub["queue_size"]) == ("flow", 4)
    # 4 queued, unless a starved host let the 1 s lease lapse and the subscription re-register.
    assert sub["queued"] in (4, 0) and sub["fill"] == sub["queued"] / 4

    rows = in_range.json()["elements"]
    assert [r["timestamp_ns"] for r in rows] == [base + 100 * MS, base + 200 * MS]
    assert rows[0]["kind"] == "frame" and rows[0]["payload_bytes"] == WIDTH * HEIGHT
    assert rows[0]["fields"]["encoding"] == "mono8" and rows[0]["fields"]["frame_id"] == 1
    assert rows[0]["metadata"].encode() == frame_metadata(base + 100 * MS, 1)
    png, xml = (Path(p) for p in rows[0]["files"])
    assert png.suffix == ".png" and xml.read_bytes() == frame_metadata(base + 100 * MS, 1)
    pixels = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    assert pixels.shape == (HEIGHT, WIDTH) and pixels.tobytes() == frame_payload(1)

    [near] = nearest.json()["elements"]
    assert near["timestamp_ns"] == base + 300 * MS
    assert base64.b64decode(near["payload_base64"]) == frame_payload(3)
    assert [r["timestamp_ns"] for r in recent.json()["elements"]] == [
        base + 200 * MS,
        base + 300 * MS,
    ]
    # A range reaching past what the buffer holds says so (on stderr: the JSON stays clean).
    assert re.search(
        r"note: the range starts 5\d min \d+ s before cam/images's oldest element", recent.stderr
    ), recent.describe()
    assert "note:" not in in_range.stderr, in_range.describe()


@contextmanager
def _producing(producer: Producer, period_s: float, payload: bytes = b"") -> Iterator[None]:
    """Put elements stamped with the wall clock until the block ends; refusals are drops."""

    def loop(stop: threading.Event) -> None:
        i = 0
        while not stop.is_set():
            t = time.time_ns()
            try:
                producer.put(t, payload or b"%d" % i, make_metadata("generic", t))
            except FlowControlRefused:
                pass  # a camera drops the frame at the source
            i += 1
            stop.wait(period_s)

    with in_background(loop):
        yield


def test_only_a_flow_controlled_slow_watch_makes_the_producer_refuse(
    service: Node, cli: Cli
) -> None:
    events = service.offer("events")
    with _producing(events, period_s=0.01):
        observed = cli.run(
            "watch", "cam/events", "--queue", "1", "--delay", "0.2", "--count", "3", "--json"
        ).json_lines()
        assert cli.run("info", "cam/events", "--json").json()["refused"] == 0
        controlled = cli.run(
            "watch", "cam/events", "--queue", "1", "--delay", "0.2", "--count", "3",
            "--flow-control", "--json",
        ).json_lines()  # fmt: skip
        info = cli.run("info", "cam/events", "--json").json()
    notes = [e for e in observed if e["event"] == "notification"]
    assert len(notes) == 3 and all(n["inline"] for n in notes)
    assert [n["seq"] for n in notes] == sorted(n["seq"] for n in notes)
    summary = observed[-1]
    assert summary["event"] == "summary" and summary["mode"] == "observe"
    assert summary["missed"] > 0  # it could not keep up, and it said so
    assert controlled[-1]["mode"] == "flow" and controlled[-1]["missed"] == 0
    assert [n["seq"] for n in controlled[:-1]] == [1, 2, 3]  # a flow consumer misses nothing
    assert info["refused"] > 0


def test_hz_measures_rate_jitter_and_bandwidth(listen_net: NetworkConfig, cli: Cli) -> None:
    with Node("cam", listen_net) as node:
        # Not inline: hz must fetch each element to know its size.
        images = node.offer("images", inline_max_bytes=100)
        with _producing(images, period_s=0.02, payload=b"x" * 1000):
            lines = cli.run(
                "hz", "cam/images", "--duration", "2", "--interval", "0.5", "--json"
            ).json_lines()
    summary = lines[-1]
    assert summary["event"] == "summary"
    assert all(line["event"] == "report" for line in lines[:-1]) and len(lines) >= 2
    # 50 Hz nominal: never above it (allowing for jitter); below it as far as a loaded
    # machine starves the producer.
    assert 0 < summary["rate_hz"] < 60
    assert summary["window"] >= 5
    # min 0: on a loaded machine two elements can arrive in the same instant.
    assert 0 <= summary["min_s"] <= summary["mean_s"] <= summary["max_s"]
    assert summary["mean_s"] > 0
    assert summary["std_s"] >= 0
    assert summary["mean_bytes"] == 1000
    assert summary["bandwidth_bytes_s"] == pytest.approx(1000 * summary["rate_hz"])


def test_user_mistakes_give_one_line_errors(service: Node, cli: Cli, tmp_path: Path) -> None:
    service.offer("images", kind="frame")
    unreachable = f"tcp/127.0.0.1:{free_port()}"
    not_mcap = tmp_path / "notes.mcap"
    not_mcap.write_text("hello")
    cases = [
        (
            ("info", "cam/imgs", "--timeout", str(ABSENCE_TIMEOUT_S)),
            "no buffer 'imgs' (did you mean 'images'?)",
        ),
        (
            # Long enough to meet 'cam' on a loaded machine (for the did-you-mean); the
            # commands run at once, so it costs no more than the one above.
            ("query", "camra/images", "--timeout", str(ABSENCE_TIMEOUT_S)),
            "no live service named 'camra' (did you mean 'cam'?)",
        ),
        (("query", "cam/images", "--from", "yesterday"), "bad time 'yesterday' for --from"),
        (("watch", "cam/images/extra"), "bad buffer name 'cam/images/extra'"),
        (
            ("info", "cam/images", "--connect", unreachable, "--timeout", "1"),
            f"cannot reach {unreachable} (",
        ),
        (("play", str(not_mcap)), "is not an MCAP file"),
    ]
    results = cli.run_many([args for args, _ in cases])
    for (_args, message), result in zip(cases, results, strict=True):
        assert result.returncode == 1, result.describe()
        assert result.stderr.startswith("error: "), result.describe()
        assert len(result.stderr.strip().splitlines()) == 1, result.describe()
        assert message in result.stderr, result.describe()
        assert "Traceback" not in result.stderr


def test_hz_headline_is_the_arrival_rate_with_the_stamps_rate_named_beside_it(
    listen_net: NetworkConfig, cli: Cli
) -> None:
    # As `play --rate 0.5` does: stamps advance half as fast as the wall clock, so they
    # are twice as dense as the arrivals.
    with Node("cam", listen_net) as node:
        events = node.offer("events")

        def fast_stamps(stop: threading.Event) -> None:
            start = time.time_ns()
            while not stop.wait(0.02):
                t = start + (time.time_ns() - start) // 2
                events.put(t, b"x", make_metadata("generic", t))

        with in_background(fast_stamps):
            lines = cli.run("hz", "cam/events", "--duration", "3", "--json").json_lines()
            text = cli.run("hz", "cam/events", "--duration", "2").stdout
    summary = lines[-1]
    assert summary["stamp_rate_hz"] == pytest.approx(2 * summary["rate_hz"], rel=0.25), summary
    assert summary["receive_rate_hz"] == summary["rate_hz"]
    headline = [line for line in text.splitlines() if line.startswith("average rate:")][-1]
    arrivals, stamps = (float(x) for x in re.findall(r"([0-9.]+) Hz", headline))
    assert stamps == pytest.approx(2 * arrivals, rel=0.25), headline
    assert "(stamps: " in headline
