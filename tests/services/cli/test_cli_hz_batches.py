"""``hz`` and ``info`` against a producer that puts in batches (``put_many``), as an IMU
driver does: the rate is of elements, as ``ros2 topic hz`` counts messages, whatever the
batch size. Real hz/info processes over real Zenoh; the reference rate is the producer's
own, measured over the same run, so a slow machine changes both sides alike."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import pytest

from middleware import NetworkConfig, Node, Producer, Retention, make_metadata
from tests.conftest import wait_until
from tests.helpers.background import in_background
from tests.services.cli.conftest import Cli

pytestmark = pytest.mark.integration

BATCH = 64  # at and above the sizes that read 0 Hz (info) and ~1.5x (hz) before
PERIOD_S = 0.05


@contextmanager
def _batching(producer: Producer, log: list[tuple[int, int]]) -> Iterator[None]:
    """Put ``BATCH`` elements every ``PERIOD_S`` until the block ends; ``log`` gets
    ``(monotonic ns, elements)`` per batch stored."""

    def loop(stop: threading.Event) -> None:
        t = time.time_ns()
        # On a schedule, not a sleep after each put: the rate stays steady when the
        # machine is loaded (late puts catch up), so any stretch of the run has about it.
        due = time.monotonic()
        while not stop.wait(max(0.0, due - time.monotonic())):
            due += PERIOD_S
            batch = [
                (t + i * 1000, b"r", make_metadata("generic", t + i * 1000)) for i in range(BATCH)
            ]
            producer.put_many(batch)
            log.append((time.monotonic_ns(), BATCH))
            t += BATCH * 1000

    with in_background(loop):
        yield


def _rate_between(log: list[tuple[int, int]], start_ns: int, end_ns: int) -> float:
    """The producer's own rate over its batches in [start_ns, end_ns]: elements after
    the first batch over the span from it to the last."""
    within = [(t, n) for t, n in log if start_ns <= t <= end_ns]
    assert len(within) >= 3, f"too few batches in the interval: {within}"
    span_s = (within[-1][0] - within[0][0]) / 1e9
    return sum(n for _t, n in within[1:]) / span_s


def test_hz_and_info_count_the_elements_of_batches(listen_net: NetworkConfig, cli: Cli) -> None:
    log: list[tuple[int, int]] = []
    with Node("imu", listen_net) as node:
        rates = node.offer("rates", retention=Retention(max_count=100_000))
        with _batching(rates, log):
            wait_until(lambda: len(log) >= 5, 30, "the first batches")
            started = time.monotonic_ns()
            hz, info = cli.run_many(
                [
                    ("hz", "imu/rates", "--duration", "4", "--interval", "1", "--json"),
                    ("info", "imu/rates", "--json"),
                ]
            )
            ended = time.monotonic_ns()
    produced = _rate_between(log, started, ended)
    summary = hz.json_lines()[-1]
    assert summary["event"] == "summary"
    assert summary["rate_hz"] == pytest.approx(produced, rel=0.25), (summary, produced)
    # The put rate of info: over the producer's last puts, not per element (a window of 64
    # per-element times that one batch fills read 0 Hz).
    put_rate = info.json()["rate_hz"]
    assert put_rate == pytest.approx(_rate_between(log, 0, ended), rel=0.25), put_rate
