"""A producer's control inbox, full of small messages that each came in a batch of its own,
holds their bytes and not Zenoh's batches (real processes, real Zenoh).

A Zenoh sample of a few bytes is a slice of the batch it arrived in (up to 64 KiB) and keeps
all of it alive; a peer that sends every 20-byte message in its own batch (``express``) made
8192 held samples cost ~580 MB. The receiving process here fills a ``ControlInbox`` to its
capacity while a flooder keeps sending and a slow owner takes some now and then, and
reports its RSS growth; the bound asserted is a quarter of what pinned batches would cost,
far above what the copies cost.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from middleware._inbox import KEY_MAX_BYTES, ControlInbox
from tests.conftest import REPO, child_env, free_port, wait_until
from tests.helpers.raw_zenoh import open_session
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration

CAPACITY = 8192
MAX_BYTES = 256
BATCH_BYTES = 64 * 1024
# How many times the flood turns the inbox over: pinned batches pile up from the first (580
# MB after 16 turns here, 3 MB with copies; a full inbox of them is 512 MiB, 4x the bound).
TURNS = 4

_RECEIVER = """
import json, sys, time
from middleware._inbox import ControlInbox
from tests.helpers.raw_zenoh import open_session
endpoint, capacity, max_bytes = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
patience_s, TURNS = float(sys.argv[4]), int(sys.argv[5])
def rss():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
with open_session(endpoint, listen=True) as session:
    inbox = ControlInbox(capacity=capacity, max_bytes=max_bytes, signal=lambda: None)
    inbox.declare(session, "fg/@ack/**")
    print("ready", flush=True)
    before = most = rss()
    deadline = time.monotonic() + patience_s
    taken = 0
    enough = TURNS * capacity
    full_at = 0
    while (inbox.overflow < enough or taken < enough // 8) and time.monotonic() < deadline:
        time.sleep(0.05)
        # A slow owner: it takes some only once the inbox has overflowed since it last took,
        # so the inbox is full at every take however slow the flood (a busy machine's flooder
        # sent slower than any fixed pace took), and what it holds keeps changing.
        if inbox.overflow > full_at:
            full_at = inbox.overflow
            taken += len(inbox.take(capacity // 8))
        most = max(most, rss())
    print(json.dumps({"growth": most - before, "taken": taken, "overflow": inbox.overflow}))
    inbox.close()
"""

# Each message in a batch of its own (``express``: sent at once, not gathered).
_FLOODER = """
import sys
from tests.helpers.raw_zenoh import open_session
with open_session(sys.argv[1]) as session:
    pub = session.declare_publisher("fg/@ack/x/y/z", express=True)
    while True:
        pub.put(b"x" * 20)
"""


@pytest.mark.slow
@pytest.mark.timeout(660)
def test_a_full_control_inbox_holds_copies_not_zenoh_batches() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    receiver = subprocess.Popen(
        # Patience for the flood to go round TURNS times: a loaded machine's flooder (two busy
        # loops beside the suite) sent 52,000 in 120 s, under half of it.
        [
            sys.executable,
            "-c",
            _RECEIVER,
            endpoint,
            *map(str, (CAPACITY, MAX_BYTES, scaled(540), TURNS)),
        ],
        cwd=REPO,
        env=child_env(),
        stdout=subprocess.PIPE,
        text=True,
    )
    assert receiver.stdout is not None
    flooder = None
    try:
        assert receiver.stdout.readline().strip() == "ready"
        flooder = subprocess.Popen(
            [sys.executable, "-c", _FLOODER, endpoint], cwd=REPO, env=child_env()
        )
        out, _ = receiver.communicate(timeout=scaled(600))
    finally:
        for proc in (flooder, receiver):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
    report = json.loads(out.strip().splitlines()[-1])
    assert report["taken"] >= TURNS * CAPACITY / 8, report  # what was held kept changing
    assert report["overflow"] >= TURNS * CAPACITY, report
    assert report["growth"] < CAPACITY * BATCH_BYTES / 4, report


def test_a_control_message_with_a_key_longer_than_any_of_ours_is_counted_not_held(
    endpoint: str,
) -> None:
    with open_session(endpoint, listen=True) as session, open_session(endpoint) as peer:
        inbox = ControlInbox(capacity=CAPACITY, max_bytes=MAX_BYTES, signal=lambda: None)
        inbox.declare(session, "fg/@ack/**")
        long_key = "fg/@ack/" + "k" * KEY_MAX_BYTES
        # Until the link is up, puts may go nowhere: repeat both until each one counted.
        wait_until(
            lambda: (
                peer.put(long_key, b"x") is None
                and peer.put("fg/@ack/a/b/c", b"x") is None
                and inbox.oversize > 0
                and len(inbox) > 0
            ),
            30,
            "both messages received",
        )
        assert {m.key for m in inbox.take(CAPACITY)} == {"fg/@ack/a/b/c"}
        inbox.close()
