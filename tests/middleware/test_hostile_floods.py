"""Floods and churn of a producer's control keys from worker processes (the ``flood``
workers of ``framegate bench``, one process each), across real processes over Zenoh on
loopback: token churn loses no element uncounted, an ack flood neither stalls ``put`` nor
grows memory. (A file of its own: its tests are long, and the suite's workers share files.)"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from middleware import (
    FlowControlRefused,
    NetworkConfig,
    Node,
    make_metadata,
    now_ns,
)
from tests.conftest import REPO, NodeProcess, child_env
from tests.helpers.timing import scaled

pytestmark = [pytest.mark.integration, pytest.mark.slow]


class _Flood:
    """A ``flood`` worker of ``framegate bench`` (services/evidence/bench/_floods.py)."""

    def __init__(self, endpoint: str, **params: Any) -> None:
        params = {"connect": endpoint, "namespace": "framegate", **params}
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "services.evidence.bench._worker", "flood", json.dumps(params)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            cwd=REPO,
            env=child_env(),
        )
        assert self.proc.stdout is not None
        assert json.loads(self.proc.stdout.readline()).get("ready")

    def stop(self) -> int:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(json.dumps({"op": "stop"}) + "\n")
        self.proc.stdin.flush()
        count = int(json.loads(self.proc.stdout.readline())["count"])
        self.proc.stdin.close()
        self.proc.wait(timeout=scaled(10))
        return count

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


@contextmanager
def _floods(endpoint: str, count: int, **params: Any) -> Iterator[list[_Flood]]:
    floods: list[_Flood] = []
    try:
        for _ in range(count):
            floods.append(_Flood(endpoint, service="cam", buffer="images", **params))
        yield floods
    finally:
        for flood in floods:
            flood.kill()


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def _sequence_checked(sub: Any, expected: int, stall_s: float) -> tuple[int, int, int]:
    """Take until element ``expected`` or a later one: each element's payload is its
    number; every one must arrive or be counted in the next one's ``missed``. (received,
    missed, the last number). Fails when no element arrives for ``stall_s``: how fast they
    come is the bench's (at load 40 the 1,000 took over 3 minutes, arriving all along)."""
    last, received, missed = 0, 0, 0
    deadline = time.monotonic() + stall_s
    while last < expected:
        assert time.monotonic() < deadline, f"stalled at element {last} of {expected}"
        for note in sub.take_many(64, timeout_s=1.0):
            number = int(sub.fetch(note).payload)
            assert number == last + 1 + note.missed, (
                f"element {number} after {last} with missed={note.missed}: lost uncounted"
            )
            last, received, missed = number, received + 1, missed + note.missed
            deadline = time.monotonic() + stall_s
    return received, missed, last


def _produce(images: Any, stop: threading.Event) -> None:
    """Put elements 1, 2, ... (payload = the number), each waiting for credit, until
    ``stop``: past the count a test checks, so that elements stored while the consumer's
    registration lapsed (a starved process) are counted by a later one's ``missed``, as the
    protocol counts them, even at the end."""
    number = 1
    while not stop.is_set():
        t = now_ns()
        try:
            images.put(t, str(number).encode(), make_metadata("generic", t), wait_s=1.0)
            number += 1
        except FlowControlRefused:
            continue  # a churned token held the queue: the same element again


@pytest.mark.parametrize(("mode", "churners"), [("flow", 1), ("observe", 2)])
def test_token_churn_loses_no_element_uncounted(
    listen_net: NetworkConfig, endpoint: str, mode: str, churners: int
) -> None:
    """Tokens declared and withdrawn as fast as 1-2 processes can, beside a legitimate
    flow subscriber that checks every element's number: each one arrives or is counted in
    ``missed``, and the producer goes on. (A churned flow token that never takes holds the
    producer while it lives, by the paper's rule: that costs rate, never an element.)"""
    count = 200  # each under hundreds of churned registrations: a gap shows at any count
    with (
        Node("cam", listen_net) as service,
        Node("consumer", NetworkConfig(connect=(endpoint,))) as consumer,
    ):
        images = service.offer("images")
        sub = consumer.subscribe("cam/images", queue_size=8, wait_s=scaled(10))
        stop = threading.Event()
        churn = {"kind": "churn", "mode": mode, "queue_size": 2, "batch": 8}
        with _floods(endpoint, churners, **churn) as floods:
            producer = threading.Thread(target=_produce, args=(images, stop), daemon=True)
            producer.start()
            try:
                received, missed, last = _sequence_checked(sub, count, scaled(60))
            finally:
                stop.set()
                producer.join(timeout=scaled(10))
            churned = sum(flood.stop() for flood in floods)
        assert received + missed == last >= count and churned > 0
        assert sub.missed_total >= missed  # and any the producer stored after ``last``


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
    with _floods(endpoint, processes, kind="acks", size=size):
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
