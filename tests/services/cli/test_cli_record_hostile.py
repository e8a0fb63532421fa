"""``record`` and ``query`` beside a peer that answers the buffer's data queries with an element
outside the range asked (any session may answer a query in the default profile)."""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import zenoh

from middleware import DataObject, NetworkConfig, Node, Producer, make_metadata
from middleware._service import encode_answer_end
from middleware._wire import encode_element_attachment
from tests.conftest import wait_until
from tests.helpers.raw_zenoh import open_session
from tests.helpers.timing import scaled
from tests.services.cli.conftest import Cli

pytestmark = pytest.mark.integration

HOUR_NS = 3600 * 1_000_000_000


@contextmanager
def _rogue_answering(endpoint: str, stamp: Callable[[], int]) -> Iterator[list[int]]:
    """A peer answering every data query of cam/a with one element stamped ``stamp()`` and
    a proper end mark; yields the count of queries it answered."""
    asked: list[int] = []

    def reply(query: zenoh.Query) -> None:
        with query:
            asked.append(1)
            stamp_ns = stamp()
            element = DataObject(stamp_ns, b"rogue", make_metadata("generic", stamp_ns))
            query.reply(query.key_expr, b"rogue", attachment=encode_element_attachment(element))
            query.reply(query.key_expr, b"", attachment=encode_answer_end(1))

    with open_session(endpoint) as rogue:
        queryable = rogue.declare_queryable("framegate/cam/a", zenoh.handlers.Callback(reply))
        try:
            yield asked
        finally:
            queryable.undeclare()


def _record_five(cli: Cli, producer: Producer, *argv: str) -> Any:
    """``record cam/a --count 5 --json ARGV`` while ``producer`` puts 5 elements stamped now,
    once it has subscribed; its JSON summary."""
    recorder = cli.start("record", "cam/a", "--count", "5", "--json", *argv)
    assert producer.wait_for_subscribers(1, timeout_s=scaled(60)), "record never subscribed"
    for _ in range(5):
        t = time.time_ns()
        producer.put(t, b"real", make_metadata("generic", t))
    out, err = recorder.communicate(timeout=scaled(120))
    assert recorder.returncode == 0, err
    return json.loads(out)


def test_record_beside_a_peer_answering_an_hour_ahead_records_the_real_elements(
    listen_net: NetworkConfig, endpoint: str, cli: Cli, tmp_path: Path
) -> None:
    """The peer's element, stamped an hour ahead, came back from the recorder's first query
    (it asks what lies before the start) although outside the range asked: it was recorded
    as the newest, and every real element after it looked recorded already (2 of ~100 in
    6.7 s, 0 evicted, 0 dropped)."""
    bag = tmp_path / "hostile.mcap"
    with Node("cam", listen_net) as node:
        producer = node.offer("a")  # before the peer answers in its name
        with _rogue_answering(endpoint, lambda: time.time_ns() + HOUR_NS):
            summary = _record_five(cli, producer, "-o", str(bag))
    assert [b["recorded"] for b in summary["buffers"]] == [5], summary


def test_query_shows_only_the_range_asked_beside_a_peer(
    listen_net: NetworkConfig, endpoint: str, cli: Cli
) -> None:
    with Node("cam", listen_net) as node:
        producer = node.offer("a")
        for t in (1000, 2000, 3000):
            producer.put(t, b"real", make_metadata("generic", t))
        with _rogue_answering(endpoint, lambda: 2**62) as asked:
            result = cli.run("query", "cam/a", "--from", "1500", "--to", "2500", "--json")
            wait_until(lambda: asked, scaled(10), "the peer to be asked")
    stamps = [e["timestamp_ns"] for e in result.json()["elements"]]
    assert stamps == [2000], stamps


def test_record_takes_only_its_producers_replies(
    listen_net: NetworkConfig, endpoint: str, cli: Cli, tmp_path: Path
) -> None:
    """The peer answers each query with an element stamped 5 s after it was asked: inside the
    window the recorder asks at its start, so the range alone does not tell it from the
    producer's. It became the newest recorded, and the real elements of the next 5 s were
    skipped as recorded already (102 of 200 in 10 s at 20 Hz, 0 evicted, 0 dropped)."""
    bag = tmp_path / "ahead.mcap"
    with Node("cam", listen_net) as node:
        producer = node.offer("a")
        with _rogue_answering(endpoint, lambda: time.time_ns() + 5 * 10**9):
            summary = _record_five(cli, producer, "-o", str(bag), "--duration", str(scaled(30)))
    assert [b["recorded"] for b in summary["buffers"]] == [5], summary


def test_query_shows_only_the_services_elements_beside_a_peer_answering_inside_the_range(
    listen_net: NetworkConfig, endpoint: str, cli: Cli
) -> None:
    """The peer's element lies inside the range asked, so the range alone cannot tell it from
    the service's: ``query`` reads the replies of the one session answering as the service
    (the peer's element was listed beside the real ones)."""
    with Node("cam", listen_net) as node:
        producer = node.offer("a")
        for t in (1000, 2000, 3000):
            producer.put(t, b"real", make_metadata("generic", t))
        with _rogue_answering(endpoint, lambda: 2500) as asked:
            ranged = cli.run("query", "cam/a", "--from", "1500", "--to", "3500", "--json")
            nearest = cli.run("query", "cam/a", "--at", "2600", "--json")
            wait_until(lambda: len(asked) >= 2, scaled(10), "the peer to be asked")
    assert [e["timestamp_ns"] for e in ranged.json()["elements"]] == [2000, 3000]
    assert [e["timestamp_ns"] for e in nearest.json()["elements"]] == [3000]
