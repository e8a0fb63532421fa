"""``hz`` once its producer stops: as ``ros2 topic hz`` says "no new messages", a report
after an interval in which nothing arrived says so instead of repeating the window's rate
(it printed "average rate: 5.004 Hz" every second after the camera had died)."""

from __future__ import annotations

import threading
import time

import pytest

from middleware import NetworkConfig, Node
from services.cli.hz import _print_report, window_stats
from tests.helpers.background import in_background
from tests.services.cli.conftest import Cli, LineReader, put_frame

pytestmark = pytest.mark.integration


def test_hz_says_no_new_elements_once_the_producer_stops(
    listen_net: NetworkConfig, cli: Cli
) -> None:
    with Node("cam", listen_net) as node:
        images = node.offer("images", kind="frame")
        hz = LineReader(cli.start("hz", "cam/images", "--interval", "0.5", "--json"))
        putting = threading.Event()
        putting.set()

        def loop(stop: threading.Event) -> None:
            frame_id = 0
            while not stop.wait(0.05) and putting.is_set():
                put_frame(images, time.time_ns(), frame_id)
                frame_id += 1

        with in_background(loop):
            hz.json_until(lambda e: e["event"] == "report" and (e["rate_hz"] or 0) > 0, 60)
            putting.clear()
            # The report that covers an interval after the last put.
            idle = hz.json_until(lambda e: e.get("new_elements") == 0, 60)
    assert idle["event"] == "report" and idle["window"] >= 2, idle


def test_an_idle_report_prints_one_line_naming_the_last_arrival(
    capsys: pytest.CaptureFixture[str],
) -> None:
    stats = window_stats([])
    _print_report(stats, 0, idle_s=2.5)
    assert capsys.readouterr().out == "no new elements (the last arrived 2.5 s ago)\n"
