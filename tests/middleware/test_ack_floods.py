"""An ack flood on a producer's control keys from ``flood`` worker processes (the workers of
``framegate bench``), across real processes over Zenoh on loopback: it neither stalls
``put`` nor grows memory. (Apart from test_hostile_floods.py: both files are long, and the
suite's workers share files.)"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.conftest import NodeProcess
from tests.helpers.flood_workers import flood_workers
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


@pytest.mark.parametrize(
    ("processes", "size"), [(4, 16), (2, 1 << 20)], ids=["16 B x 4", "1 MiB x 2"]
)
def test_an_ack_flood_neither_stalls_put_nor_grows_memory(
    node_process: Callable[..., NodeProcess], endpoint: str, processes: int, size: int
) -> None:
    """Garbage on the producer's ack keys from several processes: a put that waits for
    credit returns within its ``wait_s`` plus slack, elements keep flowing to a consumer
    that takes, and the producer's memory stays bounded."""
    producer = node_process("cam", "--listen", endpoint)
    assert producer.call("offer", buffer="images")["ok"]
    consumer = node_process(None, "--connect", endpoint)
    consumer.call("subscribe", target="cam/images", queue=1)
    assert producer.call("wait_subscribers", buffer="images", count=1, timeout=scaled(30))[
        "registered"
    ]
    rss_before = _rss_mb(producer.proc.pid)
    # Deadlines a 10x slower machine meets: at load 36 the producer went unscheduled past
    # its lease once (peers dropped it and it re-registered), and a 10 s take came back empty.
    patience = scaled(30)
    with flood_workers(endpoint, processes, kind="acks", size=size):
        time.sleep(1.0)  # the flood under way
        # The consumer takes each: credit comes back through the flood. An element stored
        # while the flood starved a process past its lease (the registration lapsed) is not
        # notified; the next one taken counts it missed. Every element arrives or is counted.
        t = last = 0
        while t < 20 or last < t:
            t += 1
            assert t <= 30, f"only {last} of {t - 1} elements notified"
            assert producer.call("put", buffer="images", t=t, wait_s=patience)["ok"]
            took = consumer.call("take", target="cam/images", timeout=patience)
            note = took.get("notification")
            if note is not None:
                assert note["t"] == t == last + 1 + note["missed"], f"after {last}: {took}"
                last = t
        # Fills the queue of 1 (once the last take's ack came through the flood).
        assert producer.call("put", buffer="images", t=100, wait_s=patience)["ok"]
        started = time.monotonic()
        refused = producer.call("put", buffer="images", t=101, wait_s=1)
        waited = time.monotonic() - started
        rss_during = _rss_mb(producer.proc.pid)
    assert refused["error"] == "FlowControlRefused", refused
    assert waited < 1 + scaled(10), f"put(wait_s=1) took {waited:.1f} s under the flood"
    # The inboxes hold at most their capacity of acks no larger than an ack can be.
    assert rss_during - rss_before < 400, f"RSS grew {rss_during - rss_before:.0f} MB"
