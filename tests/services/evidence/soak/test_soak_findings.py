"""What the soak found, kept as small reproductions.

A liveliness flap: when a subscriber's token disappears and comes back (a process stopped
or starved longer than the 1 s lease, or a cut link), the producer re-registers the
subscription with fresh counters. Under the producer's single epoch the subscriber dropped
the new sequence numbers as stale, never took or acked again, and the producer refused
for good (a soak on a loaded host stalled this way). Fixed by per-registration epochs.
"""

from __future__ import annotations

import os
import signal
from collections.abc import Callable

import pytest

from tests.conftest import NodeProcess, wait_until

pytestmark = pytest.mark.integration

MS = 1_000_000


def test_subscription_survives_a_liveliness_flap(
    node_process: Callable[..., NodeProcess], endpoint: str
) -> None:
    producer = node_process("cam", "--listen", endpoint)
    consumer = node_process(None, "--connect", endpoint)
    assert producer.call("offer", buffer="images")["ok"]
    assert consumer.call("subscribe", target="cam/images", queue=2)["ok"]
    assert producer.call("wait_subscribers", buffer="images", count=1, timeout=30)["registered"]
    for t in (1 * MS, 2 * MS, 3 * MS):
        # The credit of a taken element comes back with the consumer's (delayed) ack: the
        # third put may have to wait for it (a loaded machine's acks came after the put).
        assert producer.call("put", buffer="images", t=t, wait_s=30)["ok"]
        assert consumer.call("take", target="cam/images", timeout=30)["notification"]["t"] == t

    # Stopped longer than the lease: the producer sees the token go, then come back.
    os.kill(consumer.proc.pid, signal.SIGSTOP)
    wait_until(
        lambda: not producer.call("fill", buffer="images")["subscriptions"], 10, "token gone"
    )
    os.kill(consumer.proc.pid, signal.SIGCONT)
    wait_until(lambda: producer.call("fill", buffer="images")["subscriptions"], 10, "token back")

    assert producer.call("put", buffer="images", t=4 * MS)["ok"]
    taken = consumer.call("take", target="cam/images", timeout=30)
    assert taken["notification"] is not None and taken["notification"]["t"] == 4 * MS
