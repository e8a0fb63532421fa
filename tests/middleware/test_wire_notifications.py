"""The compact notification header: round trips, and garbage is refused as ValueError only."""

from __future__ import annotations

from typing import Any

import msgpack
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from middleware import NetworkConfig, Node, make_metadata
from middleware._wire import (
    BatchHeader,
    Header,
    decode_notification_header,
    encode_batch_header,
    encode_notification_header,
)
from tests.conftest import wait_until
from tests.helpers.raw_zenoh import open_session
from tests.helpers.timing import scaled

META = make_metadata("generic", 7)


def _array(*items: Any) -> bytes:
    return bytes(msgpack.packb(list(items), use_bin_type=True))


def test_a_single_header_round_trips() -> None:
    raw = encode_notification_header(
        "E.1", 3, 7, META, pushed=True, acked=2, descriptor="k", base=40
    )
    assert decode_notification_header(raw) == Header("E.1", 3, 7, META, True, 2, "k", 40)
    bare = encode_notification_header("E.1", 3, 7, None, pushed=False)
    assert decode_notification_header(bare) == Header("E.1", 3, 7, None, False, None, None, None)
    # The array of 7 of earlier versions (no base) is still read.
    old = _array("E.1", 3, 7, META, True, 2, "k")
    assert decode_notification_header(old) == Header("E.1", 3, 7, META, True, 2, "k", None)


def test_an_unpushed_batch_header_has_no_payload_sizes() -> None:
    raw = encode_batch_header("E.1", 5, [7, 8], [None, META], None)
    assert decode_notification_header(raw) == BatchHeader(
        "E.1", 5, (7, 8), (None, META), None, None, None, None
    )


@pytest.mark.parametrize(
    ("raw", "why"),
    [
        (b"", "empty"),
        (b"\xc1", "msgpack's never-used byte"),
        (_array("E.1", 1, 7, META, True, None, None) + b"\x00", "trailing bytes"),
        (bytes(msgpack.packb({"e": "E.1", "s": 1, "t": 7, "p": True})), "the old map"),
        (_array("E.1", 1, 7, META, True, None), "6 items"),
        (_array("E.1", 1, 7, META, True, None, None, None, None), "9 items"),
        (_array("E.1", 1, 7, META, True, None, None, -1), "a negative base"),
        (_array("E.1", 1, 7, META, True, None, None, True), "base a bool"),
        (_array(b"E.1", 1, 7, META, True, None, None), "epoch as bin"),
        (_array("E.1", True, 7, META, True, None, None), "seq a bool"),
        (_array("E.1", 1.0, 7, META, True, None, None), "seq a float"),
        (_array("E.1", 1, False, META, True, None, None), "timestamp a bool"),
        (_array("E.1", 1, "7", META, True, None, None), "timestamp a str"),
        (_array("E.1", 1, 7, "<m/>", True, None, None), "metadata as str"),
        (_array("E.1", 1, 7, META, 1, None, None), "pushed an int"),
        (_array("E.1", 1, 7, META, True, True, None), "acked a bool"),
        (_array("E.1", 1, 7, META, True, None, 5), "descriptor an int"),
        (_array("E.1", 1, [], [], None, None, None), "an empty batch"),
        (_array("E.1", 1, [7], [META], [-1], None, None), "a negative payload size"),
        (_array("E.1", 1, [7], [META, None], None, None, None), "n + 1 metadata"),
        (_array("E.1", 1, [7], [META], 5, None, None), "sizes not an array"),
        (_array("E.1", 1, [7], META, None, None, None), "metadata not an array"),
        # Seqs are int64: an observer's ack of 2^64 could not be encoded.
        (_array("E.1", 2**63, 7, META, True, None, None), "seq beyond 2^63-1"),
        (_array("E.1", 2**64 - 1, [7, 8], [None, None], None, None, None), "batch past 2^64"),
        (_array("E.1", 2**63 - 1, [7, 8], [None, None], None, None, None), "batch past 2^63"),
        (_array("E.1", 1, 7, META, True, None, None, 2**63), "base beyond 2^63-1"),
        (bytes(msgpack.packb(("hello", "flow/2/-1", "E.1", 2**63))), "hello base too large"),
    ],
)
def test_a_malformed_header_is_a_value_error(raw: bytes, why: str) -> None:
    with pytest.raises(ValueError):
        decode_notification_header(raw)


_scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**63), 2**64 - 1),
    st.floats(allow_nan=False),
    st.text(max_size=8),
    st.binary(max_size=8),
)
_values = st.recursive(_scalars, lambda inner: st.lists(inner, max_size=4), max_leaves=12)


def _well_typed(head: Header | BatchHeader) -> bool:
    def is_int(x: object) -> bool:
        return type(x) is int

    common = (
        type(head.epoch) is str
        and is_int(head.seq)
        and (head.acked is None or is_int(head.acked))
        and (head.descriptor is None or type(head.descriptor) is str)
        and (head.base is None or (is_int(head.base) and 0 <= head.base < 2**63))
    )
    if isinstance(head, Header):
        return (
            common
            and head.seq < 2**63
            and is_int(head.timestamp_ns)
            and type(head.pushed) is bool
            and (head.metadata is None or type(head.metadata) is bytes)
        )
    n = len(head.timestamps_ns)
    return (
        common
        and head.seq + n - 1 < 2**63
        and n >= 1
        and all(map(is_int, head.timestamps_ns))
        and len(head.metadata) == n
        and all(m is None or type(m) is bytes for m in head.metadata)
        and (
            head.payload_sizes is None
            or (len(head.payload_sizes) == n and all(is_int(s) for s in head.payload_sizes))
        )
    )


@settings(deadline=None)  # no wall-clock bound per example
@given(st.one_of(st.binary(max_size=64), st.lists(_values, min_size=6, max_size=9).map(_array)))
def test_any_input_decodes_to_a_well_typed_header_or_a_value_error(raw: bytes) -> None:
    try:
        head = decode_notification_header(raw)
    except ValueError:
        return
    assert _well_typed(head), head


@pytest.mark.integration
def test_a_subscription_counts_malformed_compact_headers_as_garbage(
    endpoint: str, listen_net: NetworkConfig
) -> None:
    garbage = [
        (b"x", None),
        (b"x", bytes(msgpack.packb({"e": "E.1", "s": 1, "t": 7, "p": True, "m": META}))),
        (b"x", _array("E.1", True, 7, META, True, None, None)),
        (b"x", _array("E.1", 1, 7, META, True, None)),
        (b"xyz", _array("E.1", 1, [7, 8], [META, META], [1, 1], None, None)),  # 3 != 1 + 1
    ]
    with Node(network=listen_net) as client:
        sub = client.subscribe("cam/images", queue_size=2, wait_s=0, await_service=True)
        key = f"framegate/@notify/cam/images/{sub.subscription_id}"

        def valid(seq: int) -> bytes:
            return _array("E.1", seq, seq, META, True, None, None)

        with open_session(endpoint) as rogue:
            # Until Zenoh has matched the subscriber, puts go nowhere: repeat the first one.
            wait_until(lambda: rogue.put(key, b"p1", attachment=valid(1)) or sub.pending, 30, "1")
            for payload, attachment in garbage:
                rogue.put(key, payload, attachment=attachment)
            rogue.put(key, b"p2", attachment=valid(2))  # one link: it arrives after the rest
            notes = [sub.take(timeout_s=scaled(5)), sub.take(timeout_s=scaled(5))]
        assert [(n.timestamp_ns, n.element.payload) for n in notes if n and n.element] == [
            (1, b"p1"),
            (2, b"p2"),
        ]
        assert sub.garbage == len(garbage)
        assert (sub.counters.out_of_order, sub.counters.foreign) == (0, 0)
