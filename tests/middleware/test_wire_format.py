"""A client that uses only the zenoh package reads a buffer per docs/wire-format.md."""

from __future__ import annotations

import json
from collections.abc import Callable

import msgpack
import pytest
import zenoh

from tests.conftest import NodeProcess, wait_until
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration


def test_raw_zenoh_client_reads_a_time_range(
    node_process: Callable[..., NodeProcess], endpoint: str
) -> None:
    producer = node_process("cam", "--listen", endpoint)
    assert producer.call("offer", buffer="images")["ok"]
    for t in (100, 200, 300, 400):
        assert producer.call("put", buffer="images", t=t)["ok"]

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    with zenoh.open(conf) as session:

        def read() -> list[tuple[int, str, bytes]] | None:
            out = []
            for reply in session.get(
                "framegate/cam/images?_time=[200..400]",
                consolidation=zenoh.ConsolidationMode.NONE,
                timeout=scaled(2),
            ):
                if reply.ok is not None:
                    head = msgpack.unpackb(reply.ok.attachment.to_bytes())
                    if "end" in head:  # the last reply: how many elements came before it
                        assert reply.ok.payload.to_bytes() == b""
                        return out if head == {"end": len(out)} else None
                    out.append((head["t"], head["m"], reply.ok.payload.to_bytes()))
            return None  # no end mark: the answer was cut short

        elements = wait_until(read, 30, "a whole answer from the producer")
        assert [(t, p) for t, _, p in elements] == [(200, b"p200"), (300, b"p300"), (400, b"p400")]
        assert all(f'timestamp_ns="{t}"' in m for t, m, _ in elements)

        errors = [
            r.err.payload.to_string()
            for r in session.get("framegate/cam/images?last=zero", timeout=scaled(2))
            if r.err is not None
        ]
        assert errors == ["bad-query: last='zero' is not an integer"]


def test_every_ack_starts_with_the_byte_the_ack_filter_looks_for() -> None:
    from middleware._wire import ACK_FIRST_BYTE, AckFilter, encode_ack

    for epoch, seq in (("", 0), ("a1b2c3.7", 2**62), ("x" * 200, 1)):
        ack = encode_ack(epoch, seq)
        assert ack[:1] == ACK_FIRST_BYTE and not AckFilter.malformed(ack)
    assert AckFilter.malformed(b"\x00garbage") and AckFilter.malformed(b"")
