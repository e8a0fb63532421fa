"""A subscription fetches its elements from its producer only: any session may answer a
query, so a peer's reply to a fetch (garbage, or an element stamped alike) is not read."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable

import pytest
import zenoh

from middleware import DataObject, NetworkConfig, Node, make_metadata, now_ns
from middleware._wire import Keys, encode_element_attachment
from tests.conftest import REPO, child_env, free_port
from tests.helpers.raw_zenoh import answering, flooding_session
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration

# Above the producer's inline limit (64 KiB by default): notified without it, then fetched.
SIZE = 200_000


def _garbage(query: zenoh.Query) -> None:
    with query:  # no end mark: read, it made the producer's whole answer "ended early"
        query.reply(query.key_expr, b"\xff" * 64, attachment=b"\x00garbage")


def _same_stamp(query: zenoh.Query) -> None:
    with query:  # an element stamped as asked, with the peer's payload
        stamp = int(str(query.selector.parameters.get("ts")))
        forged = DataObject(stamp, b"forged", make_metadata("generic", stamp))
        query.reply(query.key_expr, forged.payload, attachment=encode_element_attachment(forged))


@pytest.mark.parametrize("answer", [_garbage, _same_stamp], ids=["garbage", "same-stamp"])
def test_a_fetch_reads_only_the_producer_s_answer(
    answer: Callable[[zenoh.Query], None],
) -> None:
    port = free_port()
    net = NetworkConfig(local_port=port)
    with (
        Node("cam", net) as cam,
        Node("cons", net) as cons,
        flooding_session(f"tcp/127.0.0.1:{port}") as rogue,
    ):
        images = cam.offer("images", kind="generic")
        sub = cons.subscribe("cam/images", queue_size=4, wait_s=scaled(10))
        queryable = rogue.declare_queryable(
            Keys("framegate").data("cam", "images"), zenoh.handlers.Callback(answer)
        )
        try:
            got: list[bytes] = []
            for i in range(3):
                stamp = now_ns() + i
                payload = bytes([i]) * SIZE
                images.put(stamp, payload, make_metadata("generic", stamp))
                (note,) = sub.take_many(1, timeout_s=scaled(10))
                assert note.element is None  # fetched, not pushed
                got.append(sub.fetch(note, timeout_s=scaled(30)).payload)
            assert got == [bytes([i]) * SIZE for i in range(3)]
        finally:
            queryable.undeclare()


# A consumer process: subscribes to cam/images (its elements are above the inline limit:
# fetched), says so, then fetches ``N`` elements with ``timeout_s`` each and prints how long
# each fetch took and whether it got the producer's payload.
_CONSUMER = """
import sys, time
from middleware import NetworkConfig, Node
port, count, size = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[4])
timeout_s = float(sys.argv[3])
with Node("cons", NetworkConfig(local_port=port)) as node:
    sub = node.subscribe("cam/images", queue_size=4, wait_s=timeout_s, await_service=True)
    print("subscribed", flush=True)
    # One take each: take_many returns what is queued once one is (the second may be on
    # its way), and this consumer must fetch both.
    notes = [sub.take(timeout_s=timeout_s) for _ in range(count)]
    for note in notes:
        began = time.monotonic()
        element = sub.fetch(note, timeout_s=timeout_s)
        same = element.payload == bytes([note.timestamp_ns % 251]) * size
        print(time.monotonic() - began, same, flush=True)
"""


def test_a_peer_holding_fetches_open_does_not_hold_them_up() -> None:
    """A peer's queryable on the producer's data key that takes each query and never ends
    it: a fetch waited for every queryable to end its query, so each took its whole timeout
    (5 s by default; with a peer that also took the large-push slots, a real mediator fell
    from 15 decisions/s to 0-2 and the camera stored 1.6 of its 15 frames/s). The producer's
    answer is the only one a fetch reads: it ends when that answer has."""
    port = free_port()
    timeout_s = scaled(60)
    held: list[zenoh.Query] = []
    with (
        Node("cam", NetworkConfig(local_port=port)) as cam,
        flooding_session(f"tcp/127.0.0.1:{port}") as rogue,
    ):
        images = cam.offer("images", kind="generic")
        queryable = rogue.declare_queryable(
            Keys("framegate").data("cam", "images"), zenoh.handlers.Callback(held.append)
        )
        consumer = subprocess.Popen(
            [sys.executable, "-c", _CONSUMER, str(port), "2", str(timeout_s), str(SIZE)],
            cwd=REPO,
            env=child_env(),
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            assert consumer.stdout is not None
            assert consumer.stdout.readline().strip() == "subscribed"
            assert images.wait_for_subscribers(1, timeout_s=timeout_s)
            for i in range(2):
                stamp = now_ns() // 251 * 251 + i
                images.put(stamp, bytes([stamp % 251]) * SIZE, make_metadata("generic", stamp))
            out, _ = consumer.communicate(timeout=scaled(120))
            reached = len(held)
        finally:
            consumer.kill()
            queryable.undeclare()
            held.clear()
    assert reached, "the rogue's queryable never saw a fetch: the test proves nothing"
    fetches = [line.split() for line in out.splitlines()]
    assert [ok for _s, ok in fetches] == ["True", "True"], out
    # Before: each took timeout_s exactly. A hang detector, not a speed bound.
    assert all(float(s) < timeout_s / 2 for s, _ok in fetches), out


# A process with a producer and a consumer that fetches ahead and is slow: fetches one
# element (so it fetches ahead from then on), then 3 times: 7 elements put, their
# notifications taken and held 2 s (the fetches started ahead meanwhile), then fetched.
# Prints how many were fetched ahead and its peak RSS (kB).
_AHEAD = """
import resource, sys, time
from middleware import NetworkConfig, Node, make_metadata, now_ns
port, size = int(sys.argv[1]), int(sys.argv[2])
net = NetworkConfig(local_port=port)
with Node("cam", net) as cam, Node("cons", net) as cons:
    images = cam.offer("images", kind="generic")
    sub = cons.subscribe("cam/images", queue_size=32, wait_s=60)
    print("subscribed", flush=True)
    sys.stdin.readline()  # the peer is up
    def put():
        stamp = now_ns()
        images.put(stamp, b"y" * size, make_metadata("generic", stamp), wait_s=60)
    put()
    sub.fetch(sub.take(timeout_s=60), timeout_s=60)
    for _ in range(3):
        for _ in range(7):
            put()
        notes = sub.take_many(7, timeout_s=60)
        time.sleep(2)
        for note in notes:
            sub.fetch(note, timeout_s=60)
    print(sub.fetched_ahead, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, flush=True)
"""
FLOOD_REPLIES, FLOOD_BYTES = 40, 16 << 20


def test_fetches_started_ahead_hold_no_peer_s_replies() -> None:
    """A peer answering every fetch with 40 replies of 16 MiB: the fetches a slow consumer
    started ahead held every reply whole in Zenoh's channel until fetched, 460-542 MB (93 MB
    without the peer); now only the producer's replies are kept, the rest dropped as they
    come (142 MB, what Zenoh's receive buffers take)."""
    port = free_port()
    blob = zenoh.ZBytes(b"x" * FLOOD_BYTES)
    asked: list[str] = []

    def replies(key: str) -> list[tuple[str, zenoh.ZBytes]]:
        asked.append(key)
        return [(key, blob)] * FLOOD_REPLIES

    victim = subprocess.Popen(
        [sys.executable, "-c", _AHEAD, str(port), str(SIZE)],
        cwd=REPO,
        env=child_env(),
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert victim.stdout is not None and victim.stdin is not None
        assert victim.stdout.readline().strip() == "subscribed"
        with (
            flooding_session(f"tcp/127.0.0.1:{port}") as rogue,
            answering(rogue, Keys("framegate").data("cam", "images"), replies),
        ):
            victim.stdin.write("go\n")
            victim.stdin.flush()
            out, _ = victim.communicate(timeout=scaled(120))
    finally:
        victim.kill()
    assert asked, "the rogue never saw a fetch: the test proves nothing"
    ahead, peak = (int(word) for word in out.split())
    assert ahead > 0, out  # the consumer did fetch ahead
    peak_mb = peak / 1024
    # Alone: 460-542 MB before, 142 MB now. What Zenoh's receive buffers hold in flight
    # grows as the process gets less CPU (a loaded clean-clone suite peaked at 608 MB), so
    # the bound is only the class: never the floods of two fetches ahead held whole (each
    # fetch started ahead held its whole flood before); the figure is measured, not asserted.
    assert peak_mb < 2 * FLOOD_REPLIES * FLOOD_BYTES / 2**20, f"peak RSS {peak_mb:.0f} MB"
