"""A service's query workers: bounded inboxes filled by Zenoh's callback, workers that sleep
until a query arrives (an idle service wakes for nothing), refusal when full."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import pytest

from middleware import NetworkConfig, Node, make_metadata, now_ns
from middleware._service import QueryInbox


class FakeQuery:
    """What the inbox uses of a Zenoh query: an error reply and finalisation."""

    def __init__(self) -> None:
        self.errors: list[bytes] = []
        self.finalized = 0

    def reply_err(self, payload: bytes) -> None:
        self.errors.append(payload)

    def drop(self) -> None:
        self.finalized += 1

    def __enter__(self) -> FakeQuery:
        return self

    def __exit__(self, *_exc: Any) -> None:
        self.finalized += 1


def test_full_inbox_refuses_with_an_error_and_counts() -> None:
    inbox = QueryInbox("cam", capacity=2)
    queries = [FakeQuery() for _ in range(5)]
    for query in queries:
        inbox._on_query(query)  # type: ignore[arg-type]
    assert inbox.refused == 3
    for refused in queries[2:]:
        assert refused.finalized == 1
        assert b"has 2 queries waiting" in refused.errors[0]
    taken: list[object] = [inbox.take(), inbox.take()]
    assert taken == queries[:2]
    assert queries[0].errors == [] and queries[1].errors == []


def test_close_ends_the_worker_and_finalizes_what_waits() -> None:
    inbox = QueryInbox("cam", capacity=4)
    waiting = FakeQuery()
    inbox._on_query(waiting)  # type: ignore[arg-type]
    inbox.close()
    assert waiting.finalized == 1
    assert inbox.take() is None
    late = FakeQuery()
    inbox._on_query(late)  # type: ignore[arg-type]
    assert inbox.refused == 0 and late.finalized == 1 and b"is closing" in late.errors[0]


def test_worker_sleeps_until_a_query_arrives() -> None:
    inbox = QueryInbox("cam", capacity=4)
    taken: list[object] = []
    worker = threading.Thread(target=lambda: taken.append(inbox.take()), daemon=True)
    worker.start()
    query = FakeQuery()
    inbox._on_query(query)  # type: ignore[arg-type]
    worker.join(timeout=10)
    assert taken == [query]


def _voluntary_switches(native_id: int) -> int:
    status = Path(f"/proc/self/task/{native_id}/status").read_text()
    return int(status.split("voluntary_ctxt_switches:")[1].split()[0])


@pytest.mark.integration
@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux /proc")
def test_idle_service_query_threads_do_not_wake(listen_net: NetworkConfig) -> None:
    """A waiting query worker sleeps: over 2 s it is switched in at most a few times (a
    blocking Zenoh channel ``recv`` polls ~10 times a second), and still answers."""
    with Node("idlesvc", listen_net) as node:
        producer = node.offer("b")
        t_ns = now_ns()
        producer.put(t_ns, b"x", make_metadata("generic", t_ns))
        workers = {
            t.name: t
            for t in threading.enumerate()
            if t.name in ("fg-query-idlesvc", "fg-info-idlesvc")
        }
        assert set(workers) == {"fg-query-idlesvc", "fg-info-idlesvc"}
        ids = {name: t.native_id or 0 for name, t in workers.items()}
        before = {name: _voluntary_switches(tid) for name, tid in ids.items()}
        time.sleep(2.0)
        woke = {name: _voluntary_switches(ids[name]) - n for name, n in before.items()}
        assert all(n <= 3 for n in woke.values()), woke
        assert [e.timestamp_ns for e in node.latest("idlesvc/b")] == [t_ns]
