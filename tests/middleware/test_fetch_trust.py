"""A subscription fetches its elements from its producer only: any session may answer a
query, so a peer's reply to a fetch (garbage, or an element stamped alike) is not read."""

from __future__ import annotations

from collections.abc import Callable

import pytest
import zenoh

from middleware import DataObject, NetworkConfig, Node, make_metadata, now_ns
from middleware._wire import Keys, encode_element_attachment
from tests.conftest import free_port
from tests.helpers.raw_zenoh import open_session
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
        open_session(f"tcp/127.0.0.1:{port}") as rogue,
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
                got.append(sub.fetch(note, timeout_s=scaled(5)).payload)
            assert got == [bytes([i]) * SIZE for i in range(3)]
        finally:
            queryable.undeclare()
