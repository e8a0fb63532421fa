"""A service answers its queries on one serving thread fed by a bounded inbox: a peer that
asks faster than the service answers costs bounded memory, its excess is counted, and an
honest query asked after the flood is answered."""

from __future__ import annotations

import subprocess
import sys
import threading

import pytest

from middleware import Node, make_metadata
from middleware._service import DATA_QUERIES, INFO_QUERIES, QUERY_BODY_MAX_BYTES, QueryInbox
from tests.conftest import REPO, child_env, wait_until
from tests.helpers.raw_zenoh import open_session
from tests.helpers.timing import answered, scaled


class _Query:
    """A stand-in for ``zenoh.Query``: the inbox only holds and drops them."""

    def __init__(self, n: int, payload: bytes | None = None, parameters: str = "") -> None:
        self.n = n
        self.payload = payload
        self.attachment = None
        self.parameters = parameters


def _offer_log(service: Node, count: int) -> None:
    """``cam/log`` with elements stamped 1..``count``."""
    log = service.offer("log")
    for t in range(1, count + 1):
        log.put(t, b"x" * 16, make_metadata("generic", t))


def _ask(inbox: QueryInbox, which: str, n: int) -> None:
    inbox.callback(which).callback(_Query(n))  # type: ignore[arg-type]


def test_the_inbox_holds_at_most_its_capacity_and_answers_both_kinds_in_turn() -> None:
    inbox = QueryInbox()
    for n in range(DATA_QUERIES + 10):
        _ask(inbox, "data", n)
    for n in range(INFO_QUERIES + 3):
        _ask(inbox, "info", n)
    assert inbox.dropped == 13  # the arrivals beyond each capacity
    taken = [inbox.take() for _ in range(DATA_QUERIES + INFO_QUERIES)]
    kinds = [which for which, _query in taken]  # type: ignore[misc]
    # In turn while both wait (a flood of one kind never holds up the other), then the rest.
    assert kinds == ["info", "data"] * INFO_QUERIES + ["data"] * (DATA_QUERIES - INFO_QUERIES)
    numbers = {which: [q.n for w, q in taken if w == which] for which in ("info", "data")}  # type: ignore[misc, attr-defined]
    # What was waiting is answered, oldest first; the excess that arrived later was not kept.
    assert numbers["info"] == list(range(INFO_QUERIES))
    assert numbers["data"] == list(range(DATA_QUERIES))


def test_a_query_carrying_more_than_a_query_needs_is_not_kept() -> None:
    # Issue 30: a waiting query holds what it carries; 4 MB payloads on queries sent faster
    # than a 16 MB answer went out grew a producer from 57 to 411 MB (101 MB now).
    inbox = QueryInbox()
    inbox.callback("data").callback(_Query(1, b"q" * (4 << 20)))  # type: ignore[arg-type]
    inbox.callback("info").callback(_Query(2, b"q" * (QUERY_BODY_MAX_BYTES + 1)))  # type: ignore[arg-type]
    inbox.callback("data").callback(_Query(3, b"q" * QUERY_BODY_MAX_BYTES))  # type: ignore[arg-type]
    # Selector parameters are held as well: a megabyte of them is as much as a payload.
    inbox.callback("data").callback(_Query(4, None, "_time=" + "9" * (1 << 20)))  # type: ignore[arg-type]
    assert inbox.dropped == 3
    taken = inbox.take()
    assert taken is not None and taken[1].n == 3  # type: ignore[attr-defined]
    assert not inbox._waiting["data"] and not inbox._waiting["info"]


@pytest.mark.integration
def test_a_query_with_a_large_payload_is_counted_and_not_answered(
    listen_net, connect_net, endpoint
) -> None:
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        _offer_log(service, 10)
        with open_session(endpoint) as rogue:
            wait_until(
                lambda: client.query("cam/log", timeout_s=scaled(10)) != [],
                scaled(30),
                "the service to answer an ordinary query",
            )
            replies = list(
                rogue.get("framegate/cam/log", payload=b"q" * (64 << 10), timeout=scaled(10))
            )
            assert [r for r in replies if r.ok is not None] == []
            assert client.service_info("cam").dropped_queries == 1
            long = "framegate/cam/log?_time=[0.." + "0" * (64 << 10) + "1]"
            replies = list(rogue.get(long, timeout=scaled(10)))
            assert [r for r in replies if r.ok is not None] == []
            assert client.service_info("cam").dropped_queries == 2
            got = client.query("cam/log", timeout_s=scaled(10))
            assert [e.timestamp_ns for e in got] == list(range(1, 11))


def test_take_sleeps_until_a_query_comes_and_close_ends_it() -> None:
    inbox = QueryInbox()
    got: list[object] = []
    reader = threading.Thread(target=lambda: got.append(inbox.take()))
    reader.start()
    _ask(inbox, "data", 7)
    reader.join(timeout=scaled(5))
    assert not reader.is_alive()
    assert got[0][0] == "data"  # type: ignore[index]
    closer = threading.Thread(target=lambda: got.append(inbox.take()))
    closer.start()
    inbox.close()
    closer.join(timeout=scaled(5))
    assert not closer.is_alive()
    assert got[1] is None
    _ask(inbox, "data", 8)  # after close: ignored, nothing held
    assert inbox.take() is None


@pytest.mark.integration
def test_a_query_flood_is_bounded_and_an_honest_query_is_answered_after_it(
    listen_net, connect_net, endpoint
) -> None:
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        _offer_log(service, 100)
        with open_session(endpoint) as rogue:
            inbox = service._endpoint._queries  # type: ignore[union-attr]
            held: list[int] = []
            pending = []
            # Thousands of range queries without waiting for any answer.
            for i in range(3000):
                pending.append(rogue.get("framegate/cam/log?_time=[0..200]", timeout=scaled(30)))
                if i % 100 == 0:
                    held.append(len(inbox._waiting["data"]))
            assert max(held) <= DATA_QUERIES

            def counted() -> bool:
                return client.service_info("cam").dropped_queries == inbox.dropped > 0

            # A flood this size outruns the serving thread: what it ended is reported.
            wait_until(counted, scaled(30), "the dropped queries in the service's @info")
            got = client.query("cam/log", time_range="[1..100]", timeout_s=scaled(30))
            assert [e.timestamp_ns for e in got] == list(range(1, 101))
            del pending
        threads = [t.name for t in threading.enumerate()]
        assert threads.count("fg-serve-cam") == 1
        assert not [n for n in threads if n.startswith(("fg-query", "fg-info"))]


# Info queries as fast as one process can ask, never reading an answer, until killed.
_INFO_FLOODER = """
import os, sys
from tests.helpers.raw_zenoh import open_session
os.nice(10)
with open_session(sys.argv[1]) as rogue:
    while True:
        rogue.get("framegate/@info/cam", timeout=10)
"""


@pytest.mark.integration
def test_an_info_flood_does_not_hold_up_data_queries(listen_net, connect_net, endpoint) -> None:
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        log = service.offer("log")
        for t in range(1, 21):
            log.put(t, b"x", make_metadata("generic", t))
        # Flooders in processes of their own, as a peer is: in this one they shared its
        # interpreter and Zenoh's threads with the service and the client, and in a worker
        # that had run the suite before, a query waited out 60 s (twice in CI). Niced: the
        # inbox's fairness is under test, not who wins the CPU on a busy machine (at load 19
        # two flooders at full speed kept the service's process from answering for 60 s);
        # they still overflow the info inbox (checked below).
        flooders = [
            subprocess.Popen(
                [sys.executable, "-c", _INFO_FLOODER, endpoint], cwd=REPO, env=child_env()
            )
            for _ in range(2)
        ]
        try:
            inbox = service._endpoint._queries  # type: ignore[union-attr]
            wait_until(lambda: inbox.dropped > 0, scaled(30), "the flood to fill the inbox")
            for _ in range(3):
                # Through answered(), as every look at another session: on a loaded machine the
                # flooded session can go past its lease for a moment, and nobody answers for
                # it until it reconnects ("no live service" in CI); a query starved by the
                # flood for good still fails.
                got = answered(
                    lambda: client.query("cam/log", time_range="[1..20]", timeout_s=scaled(30)),
                    "a data query during the info flood",
                    wait_s=60,  # the flooded service shares this worker's CPU: 20 s ran out once
                )
                assert [e.timestamp_ns for e in got] == list(range(1, 21))
        finally:
            for flooder in flooders:
                flooder.kill()
                flooder.wait()
