"""An answer cut short is an error, never the first part of a buffer read as all of it.

When the answering service's link drops in the middle of an answer (its lease lapsed: on a
loaded machine a process can go without CPU for over a second), Zenoh ends the query as if
every reply had come, with no error. Each answer therefore ends with the service's end mark,
and a query without it raises. Real processes: the service is stopped (SIGSTOP) after the
first reply came, while the rest of its answer cannot have left it yet. Two answers that
interleave are each judged by their own session's end mark (fed as replies, no processes).
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from middleware import NetworkConfig, Node, QueryError, make_metadata
from middleware._records import DataObject
from middleware._service import encode_answer_end
from middleware._wire import encode_element_attachment
from tests.conftest import NodeProcess
from tests.helpers.timing import answered, scaled

pytestmark = pytest.mark.integration

MS = 1_000_000
# Far more than the querier's reply channel (256) and the loopback socket buffers hold, so
# that most of the answer is still in the service when it stops.
COUNT = 600
SIZE = 64 * 1024


def test_an_answer_cut_short_by_a_lapsed_link_raises_instead_of_reading_as_the_buffer(
    node_process: Callable[..., NodeProcess], endpoint: str
) -> None:
    # Without shared memory every payload crosses the socket, which holds only a few of them.
    server = node_process("cam", "--listen", endpoint, "--no-shm")
    assert server.call("offer", buffer="images", retention={"max_count": COUNT})["ok"]
    for i in range(1, COUNT + 1):
        assert server.call("put", buffer="images", t=i * MS, payload_size=SIZE)["ok"]
    with Node(network=NetworkConfig(connect=(endpoint,), shared_memory=False)) as client:
        whole = answered(lambda: client.query("cam/images", timeout_s=scaled(30)), "cam/images")
        assert [e.timestamp_ns for e in whole] == [i * MS for i in range(1, COUNT + 1)]

        pending = client._start_get("cam/images", {}, scaled(60))
        stopped: list[bool] = []

        def stop_after_the_first(replies: Any) -> Iterator[Any]:
            it = iter(replies)
            first = next(it)
            os.kill(server.proc.pid, signal.SIGSTOP)
            stopped.append(True)
            yield first
            yield from it  # what came before the stop, then the end of the lapsed link

        try:
            with pytest.raises(QueryError, match="ended early") as raised:
                client._answer("cam/images", stop_after_the_first(pending))
            assert stopped
            # Some came, not all: read as the buffer, this would have been a shorter one.
            came = int(str(raised.value).split("(", 1)[1].split(" ", 1)[0])
            assert 1 <= came < COUNT, raised.value
        finally:
            os.kill(server.proc.pid, signal.SIGCONT)

    # Running again, the service answers whole and the end mark says so. Asked from a new
    # session: the one above can stay deaf to the service for good when it reconnected while
    # the service was still closing its side of the lapsed link (a Zenoh race: 6 of 222 runs,
    # 8 at once beside a busy loop; docs/limits.md), which is not what this test is about.
    with Node(network=NetworkConfig(connect=(endpoint,), shared_memory=False)) as client:
        again = answered(lambda: client.query("cam/images", timeout_s=scaled(10)), "cam/images")
        assert len(again) == COUNT


class _Bytes:
    def __init__(self, data: bytes) -> None:
        self._data = data

    def to_bytes(self) -> bytes:
        return self._data


class _Reply:
    """A Zenoh reply as ``Queries`` reads it: a sample, and the session that sent it."""

    def __init__(self, replier: str, payload: bytes, attachment: bytes) -> None:
        self.replier_id = replier
        self.ok = type("Sample", (), {"payload": _Bytes(payload), "attachment": _Bytes(attachment)})
        self.err = None


def _answer_of(replier: str, stamps: list[int]) -> list[_Reply]:
    replies = [
        _Reply(
            replier,
            b"p",
            encode_element_attachment(DataObject(t, b"p", make_metadata("generic", t))),
        )
        for t in stamps
    ]
    return [*replies, _Reply(replier, b"", encode_answer_end(len(stamps)))]


def test_two_answers_interleaved_are_each_complete_by_their_own_end_mark(endpoint: str) -> None:
    # Two sessions answer one query (a process's own buffer beside a peer's, a producer and
    # its restarted self): their replies interleave, and each end mark counts its own.
    a, b = _answer_of("a", [1, 2, 3]), _answer_of("b", [4, 5])
    interleaved = [a[0], b[0], a[1], b[1], b[2], a[2], a[3]]
    with Node(network=NetworkConfig(listen=(endpoint,))) as node:
        got = node._answer("x/y", interleaved)[0]
        assert sorted(e.timestamp_ns for e in got) == [1, 2, 3, 4, 5]
        # One of them cut short (its end mark never came) is still an error.
        with pytest.raises(QueryError, match="ended early"):
            node._answer("x/y", [a[0], b[0], a[1], b[1], b[2], a[2]])[0]
        # And a mark that disagrees with its own session's count.
        with pytest.raises(QueryError, match="ended early"):
            node._answer("x/y", [a[0], b[0], b[1], b[2], a[2], a[3]])[0]


def test_an_answer_cut_short_by_the_query_timeout_says_so_not_a_dropped_link(
    endpoint: str,
) -> None:
    # Zenoh ends the replies the same way when the query's timeout passes mid-answer (a long
    # range, a service without CPU on a busy machine) as when the link drops; only the first
    # ends them at or after the deadline. Said as a dropped link, the user asked again with
    # the same timeout and was cut short again (gyro/rates under load: 1,161 of ~11,000).
    a = _answer_of("a", [1, 2, 3])
    with Node(network=NetworkConfig(listen=(endpoint,))) as node:
        passed = time.monotonic()
        with pytest.raises(QueryError, match=r"ended early \(2 elements.*timeout \(5 s\)"):
            node._answer("x/y", a[:2], deadline=passed, timeout_s=5.0)
        # Cut short before the deadline: the link, as before.
        with pytest.raises(QueryError, match="link dropped"):
            node._answer("x/y", a[:2], deadline=time.monotonic() + 3600, timeout_s=3600.0)
        # A whole answer is whole however late it ends.
        got = node._answer("x/y", a, deadline=passed, timeout_s=5.0)[0]
        assert [e.timestamp_ns for e in got] == [1, 2, 3]
