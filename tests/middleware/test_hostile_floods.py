"""Churn of a producer's subscription tokens from worker processes (the ``flood`` workers of
``framegate bench``, one process each), across real processes over Zenoh on loopback: token
churn loses no element uncounted. (The ack flood is test_ack_floods.py: files of their own,
as their tests are long and the suite's workers share files, ``--dist loadfile``.)"""

from __future__ import annotations

import threading
import time
from typing import Any

import pytest

from middleware import (
    FlowControlRefused,
    NetworkConfig,
    Node,
    make_metadata,
    now_ns,
)
from tests.helpers.flood_workers import flood_workers
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration


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
    count = 1000
    with (
        Node("cam", listen_net) as service,
        Node("consumer", NetworkConfig(connect=(endpoint,))) as consumer,
    ):
        images = service.offer("images")
        sub = consumer.subscribe("cam/images", queue_size=8, wait_s=scaled(10))
        stop = threading.Event()
        churn = {"kind": "churn", "mode": mode, "queue_size": 2, "batch": 8}
        with flood_workers(endpoint, churners, **churn) as floods:
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
