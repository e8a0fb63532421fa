"""The batch API over real Zenoh in one process: ``Producer.put_many`` (one notification for
many elements, the queue counted in elements) and ``Subscription.take_many`` (one ack)."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from contextlib import contextmanager

import msgpack
import pytest
import zenoh

from middleware import (
    DuplicateTimestampError,
    FlowControlRefused,
    NetworkConfig,
    Node,
    Producer,
    Subscription,
    make_metadata,
)
from middleware._wire import BatchHeader, decode_notification_header, encode_batch_header
from tests.conftest import wait_until
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration

SERVICE, BUFFER = "imu", "rates"


def _element(t: int) -> tuple[int, bytes, bytes]:
    return t, b"p%d" % t, make_metadata("generic", t)


def _batch(*timestamps: int) -> list[tuple[int, bytes, bytes]]:
    return [_element(t) for t in timestamps]


@contextmanager
def _pair(
    listen_net: NetworkConfig, connect_net: NetworkConfig, queue: int, push: int | None = None
) -> Iterator[tuple[Producer, Subscription, Node]]:
    with Node(SERVICE, listen_net) as server, Node(network=connect_net) as client:
        rates = server.offer(BUFFER)
        sub = client.subscribe(f"{SERVICE}/{BUFFER}", queue_size=queue, push_max_bytes=push)
        assert rates.wait_for_subscribers(1, timeout_s=scaled(30))
        yield rates, sub, client


def _queued(producer: Producer) -> int:
    return producer.subscriptions()[0].queued


def test_a_batch_is_refused_whole_when_the_queue_lacks_room_for_all_of_it(
    listen_net: NetworkConfig, connect_net: NetworkConfig
) -> None:
    with _pair(listen_net, connect_net, queue=4) as (rates, sub, _):
        rates.put_many(_batch(1, 2, 3))
        wait_until(lambda: sub.pending == 3, 30, "three notifications queued")
        with pytest.raises(FlowControlRefused, match="no room for a batch of 2"):
            rates.put_many(_batch(4, 5))
        assert len(rates.series) == 3, "a refused batch stores nothing"
        assert rates.info().refused == 2, "refusals are counted in elements"
        rates.put_many(_batch(4))
        assert _queued(rates) == 4
        with pytest.raises(FlowControlRefused, match="never fit: put batches of at most 4"):
            rates.put_many(_batch(*range(10, 15)), wait_s=5.0)  # refused at once, not waited
        wait_until(lambda: sub.pending == 4, 30, "the fourth notification")
        assert [n.timestamp_ns for n in sub.take_many(10, timeout_s=scaled(5))] == [1, 2, 3, 4]


def test_a_batch_with_timestamps_out_of_order_stores_nothing(
    listen_net: NetworkConfig, connect_net: NetworkConfig
) -> None:
    with _pair(listen_net, connect_net, queue=4) as (rates, _, _):
        rates.put(5, b"x", make_metadata("generic", 5))
        for bad in (_batch(6, 8, 7), _batch(6, 6), _batch(5, 6)):
            with pytest.raises(DuplicateTimestampError):
                rates.put_many(bad)
        assert len(rates.series) == 1 and _queued(rates) == 1


def test_take_many_takes_a_whole_batch_with_one_ack(
    listen_net: NetworkConfig, connect_net: NetworkConfig, endpoint: str
) -> None:
    acks: list[tuple[str, int]] = []
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    with (
        _pair(listen_net, connect_net, queue=8) as (rates, sub, _),
        zenoh.open(conf) as spy,
    ):
        spy_sub = spy.declare_subscriber(
            f"framegate/@ack/{SERVICE}/{BUFFER}/*",
            lambda s: acks.append(tuple(msgpack.unpackb(s.payload.to_bytes()).values())),
        )
        # Any reply at all (iterating ends when the get is done, replies or not).
        wait_until(
            lambda: any(True for _ in spy.liveliness().get(f"framegate/@sub/{SERVICE}/**")),
            30,
            "the mesh",
        )
        rates.put_many(_batch(*range(1, 7)))
        wait_until(lambda: sub.pending == 6, 30, "six notifications queued")
        notes = sub.take_many(10, timeout_s=scaled(5))
        assert [(n.timestamp_ns, n.seq) for n in notes] == [(t, t) for t in range(1, 7)]
        wait_until(lambda: _queued(rates) == 0, 30, "the producer seeing the batch taken")
        wait_until(lambda: acks, 30, "the spy seeing the ack")
        assert [seq for _, seq in acks] == [6], "one cumulative ack for six elements"
        spy_sub.undeclare()


def test_single_puts_and_batches_mix_in_one_stream(
    listen_net: NetworkConfig, connect_net: NetworkConfig
) -> None:
    with _pair(listen_net, connect_net, queue=8) as (rates, sub, _):
        rates.put(*_element(1))
        rates.put_many(_batch(2, 3, 4))
        rates.put(*_element(5))
        rates.put_many(_batch(6, 7))
        wait_until(lambda: sub.pending == 7, 30, "seven notifications queued")
        first = sub.take(timeout_s=scaled(5))
        rest = sub.take_many(3, timeout_s=scaled(5)) + sub.take_many(10, timeout_s=scaled(5))
        notes = [first, *rest]
        assert [(n.timestamp_ns, n.seq, n.missed) for n in notes if n] == [
            (t, t, 0) for t in range(1, 8)
        ]
        for note in notes:
            assert note is not None and note.element is not None, "small elements are pushed"
            assert note.element.payload == b"p%d" % note.timestamp_ns
            assert note.metadata == make_metadata("generic", note.timestamp_ns)


def test_a_batch_beyond_the_push_limit_is_fetched_element_by_element(
    listen_net: NetworkConfig, connect_net: NetworkConfig
) -> None:
    with _pair(listen_net, connect_net, queue=4, push=0) as (rates, sub, _):
        rates.put_many(_batch(1, 2, 3))
        notes = wait_until(lambda: sub.take_many(3, timeout_s=scaled(0.1)), 30, "the batch")
        notes += sub.take_many(3, timeout_s=scaled(1)) if len(notes) < 3 else []
        assert all(n.element is None for n in notes)
        assert [sub.fetch(n).payload for n in notes] == [b"p1", b"p2", b"p3"]


def test_a_flow_subscriber_taking_slowly_misses_no_element_of_many_batches(
    listen_net: NetworkConfig, connect_net: NetworkConfig
) -> None:
    with _pair(listen_net, connect_net, queue=4) as (rates, sub, _):
        batches = [_batch(*range(t, t + 3)) for t in range(1, 91, 3)]

        def produce() -> None:
            for batch in batches:
                rates.put_many(batch, wait_s=10.0)

        producer = threading.Thread(target=produce)
        producer.start()
        seen: list[tuple[int, int]] = []
        while len(seen) < 90:
            notes = sub.take_many(2, timeout_s=scaled(10))
            assert notes, f"stalled after {len(seen)} elements"
            seen += [(n.timestamp_ns, n.missed) for n in notes]
        producer.join(timeout=scaled(10))
        assert seen == [(t, 0) for t in range(1, 91)]
        assert rates.info().refused == 0


def test_queries_see_every_element_of_a_batch(
    listen_net: NetworkConfig, connect_net: NetworkConfig
) -> None:
    with _pair(listen_net, connect_net, queue=8) as (rates, _, client):
        rates.put_many(_batch(10, 20, 30, 40))
        rates.put(*_element(50))
        target = f"{SERVICE}/{BUFFER}"
        assert [e.timestamp_ns for e in client.query(target)] == [10, 20, 30, 40, 50]
        between = client.query(target, time_range="[20..40]")
        assert [(e.timestamp_ns, e.payload) for e in between] == [
            (20, b"p20"),
            (30, b"p30"),
            (40, b"p40"),
        ]
        assert [e.timestamp_ns for e in client.query(target, last=2)] == [40, 50]


def test_a_batch_header_round_trips_and_a_malformed_one_is_refused() -> None:
    raw = encode_batch_header("E.1", 3, [7, 8], [b"<m/>", None], [2, 0], acked=1, descriptor="k")
    head = decode_notification_header(raw)
    assert isinstance(head, BatchHeader)
    assert (head.seq, head.timestamps_ns, head.metadata, head.payload_sizes) == (
        3,
        (7, 8),
        (b"<m/>", None),
        (2, 0),
    )
    good = msgpack.unpackb(raw)
    for index, broken in (
        (2, []),
        (3, [b"<m/>"]),
        (2, [7, "8"]),
        (3, [b"", 5]),
        (4, [2]),
        (4, [2, -1]),
        (1, True),
    ):
        with pytest.raises(ValueError):
            decode_notification_header(
                bytes(msgpack.packb([*good[:index], broken, *good[index + 1 :]]))
            )


def test_a_subscriber_that_took_everything_and_went_away_frees_the_producer_at_once(
    listen_net: NetworkConfig, connect_net: NetworkConfig
) -> None:
    """A queue of 8 coalesces acks and holds back the ack of an emptied queue for a
    millisecond; a caller that then processes for a long time must not keep that credit
    (the subscription's flusher sends the ack, not the caller's next take)."""
    with _pair(listen_net, connect_net, queue=8) as (rates, sub, _):
        rates.put_many(_batch(1, 2, 3))
        wait_until(lambda: sub.pending == 3, 30, "three notifications queued")
        assert len(sub.take_many(3, timeout_s=scaled(5))) == 3
        # No further take: the caller is "processing".
        wait_until(lambda: _queued(rates) == 0, 30, "the delayed ack from the flusher")
        rates.put_many(_batch(*range(4, 12)), wait_s=0.0)  # the whole queue is free again
