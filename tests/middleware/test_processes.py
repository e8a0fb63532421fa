"""Producer and consumer in separate OS processes over real Zenoh on loopback."""

from __future__ import annotations

import base64
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import pytest

from middleware import (
    FlowControlRefused,
    NetworkConfig,
    Node,
    NotFoundError,
    Producer,
    QueryError,
    SubscriptionMode,
    make_metadata,
    tightest_flow,
)
from tests.conftest import NodeProcess, wait_until
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration

MS = 1_000_000


def _start_producer(
    node_process: Callable[..., NodeProcess], endpoint: str, count: int = 0
) -> NodeProcess:
    producer = node_process("cam", "--listen", endpoint)
    assert producer.call("offer", buffer="images")["ok"]
    for i in range(1, count + 1):
        assert producer.call("put", buffer="images", t=i * MS)["ok"]
    return producer


def test_queries_return_exactly_the_right_elements_in_order(
    node_process: Callable[..., NodeProcess], endpoint: str, connect_net: NetworkConfig
) -> None:
    _start_producer(node_process, endpoint, count=20)
    with Node(network=connect_net) as client:
        wait_until(lambda: "cam" in client.live_services(), 30, "the producer service")
        in_range = client.query("cam/images", time_range=f"[{5 * MS}..{9 * MS}]")
        assert [e.timestamp_ns for e in in_range] == [5 * MS, 6 * MS, 7 * MS, 8 * MS, 9 * MS]
        assert in_range[0].payload == b"p%d" % (5 * MS)
        assert b'timestamp_ns="5000000"' in in_range[0].metadata
        exclusive = client.query("cam/images", time_range=f"]{5 * MS}..{9 * MS}[")
        assert [e.timestamp_ns for e in exclusive] == [6 * MS, 7 * MS, 8 * MS]
        assert [e.timestamp_ns for e in client.latest("cam/images", 3)] == [
            18 * MS,
            19 * MS,
            20 * MS,
        ]
        assert client.nearest("cam/images", 7 * MS + 400_000).timestamp_ns == 7 * MS
        assert client.nearest("cam/images", 7 * MS + 600_000).timestamp_ns == 8 * MS
        assert client.get("cam/images", 12 * MS).payload == b"p%d" % (12 * MS)
        with pytest.raises(NotFoundError, match="no element with timestamp 12000001"):
            client.get("cam/images", 12 * MS + 1)
        # Relative ranges: everything is from 1970, so the last two seconds hold nothing.
        assert client.query("cam/images", time_range="[now(-2s)..]") == []
        last_in_range = client.query("cam/images", time_range=f"[..{10 * MS}]", last=2)
        assert [e.timestamp_ns for e in last_in_range] == [9 * MS, 10 * MS]


def _consumer(
    node_process: Callable[..., NodeProcess], endpoint: str, queue: int, mode: str = "flow"
) -> NodeProcess:
    consumer = node_process(None, "--connect", endpoint)
    assert consumer.call("subscribe", target="cam/images", queue=queue, mode=mode)["ok"]
    return consumer


@contextmanager
def _offered_with_consumer(
    node_process: Callable[..., NodeProcess],
    endpoint: str,
    listen_net: NetworkConfig,
    queue: int,
    mode: str = "flow",
) -> Iterator[tuple[Producer, NodeProcess]]:
    """cam/images offered here, subscribed by a consumer process, registered."""
    with Node("cam", listen_net) as node:
        images = node.offer("images")
        consumer = _consumer(node_process, endpoint, queue=queue, mode=mode)
        assert images.wait_for_subscribers(1, timeout_s=scaled(30))
        yield images, consumer


def _put(producer: Any, t: int) -> None:
    producer.put(t, b"x", make_metadata("generic", t))


def test_full_queue_refuses_put(
    node_process: Callable[..., NodeProcess], endpoint: str, listen_net: NetworkConfig
) -> None:
    with _offered_with_consumer(node_process, endpoint, listen_net, queue=2) as (
        images,
        _consumer_proc,
    ):
        _put(images, 1)
        assert [s.queued for s in images.subscriptions()] == [1]
        _put(images, 2)
        assert [s.queued for s in images.subscriptions()] == [2]
        with pytest.raises(FlowControlRefused, match="has 2/2 notifications queued"):
            _put(images, 3)
        # Refused means not stored.
        assert images.series.exact(3) is None
        assert images.info().refused == 1


def test_taking_a_notification_frees_one_slot(
    node_process: Callable[..., NodeProcess], endpoint: str, listen_net: NetworkConfig
) -> None:
    with _offered_with_consumer(node_process, endpoint, listen_net, queue=2) as (images, consumer):
        _put(images, 1)
        _put(images, 2)
        took = consumer.call("take", target="cam/images")
        assert took["notification"]["t"] == 1
        assert base64.b64decode(took["element"]["payload"]) == b"x"
        wait_until(lambda: [s.queued for s in images.subscriptions()] == [1], 30, "the ack")
        _put(images, 3)


def test_consumer_that_keeps_up_causes_no_refusal(
    node_process: Callable[..., NodeProcess], endpoint: str, listen_net: NetworkConfig
) -> None:
    with _offered_with_consumer(node_process, endpoint, listen_net, queue=1) as (images, consumer):
        for t in range(1, 31):
            # A lossless producer waits for credit; a consumer that keeps up grants it.
            images.put(t, b"x", make_metadata("generic", t), wait_s=5.0)
            took = consumer.call("take", target="cam/images")
            assert took["notification"]["t"] == t
        assert images.info().refused == 0


def test_observer_never_refuses_and_reports_missed(
    node_process: Callable[..., NodeProcess], endpoint: str, listen_net: NetworkConfig
) -> None:
    with _offered_with_consumer(node_process, endpoint, listen_net, queue=2, mode="observe") as (
        images,
        observer,
    ):
        for t in range(1, 11):
            _put(images, t)
        assert tightest_flow(images.subscriptions()) is None  # observers are not load
        assert images.info().refused == 0
        assert images.subscriptions()[0].queued == 2  # its queue holds 2; 8 were missed
        # Both read at once: each read drains what has arrived since the one before.
        wait_until(
            lambda: (
                (r := observer.call("stats", target="cam/images"))["pending"] == 2
                and r["missed_total"] == 8
            ),
            30,
            "the observer to receive all 10 notifications",
        )
        # Keep-last: the queue of 2 holds the newest two; 1..8 were pushed out, counted on
        # the first notification taken.
        first = observer.call("take", target="cam/images")["notification"]
        second = observer.call("take", target="cam/images")["notification"]
        assert [(first["t"], first["missed"]), (second["t"], second["missed"])] == [
            (9, 8),
            (10, 0),
        ]
        _put(images, 11)
        third = wait_until(
            lambda: observer.call("take", target="cam/images", timeout=0.2)["notification"],
            30,
            "notification 11",
        )
        assert (third["t"], third["missed"]) == (11, 0)


def test_killed_consumer_frees_a_waiting_put(
    node_process: Callable[..., NodeProcess], endpoint: str, listen_net: NetworkConfig
) -> None:
    with _offered_with_consumer(node_process, endpoint, listen_net, queue=1) as (images, consumer):
        _put(images, 1)
        with pytest.raises(FlowControlRefused):
            _put(images, 2)
        consumer.kill()
        started = time.monotonic()
        # A waiting put returns as soon as the dead subscriber's liveliness token goes (within
        # milliseconds, printed below; a put still refused at its deadline raises).
        images.put(2, b"x", make_metadata("generic", 2), wait_s=scaled(30))
        print(f"a killed consumer freed the producer after {time.monotonic() - started:.3f} s")
        assert images.subscriptions() == []


def test_bad_input_gets_an_error_and_the_service_keeps_answering(
    node_process: Callable[..., NodeProcess], endpoint: str, connect_net: NetworkConfig
) -> None:
    producer = _start_producer(node_process, endpoint, count=3)
    xxe = (
        '<?xml version="1.0"?><!DOCTYPE m [<!ENTITY x SYSTEM "file:///etc/passwd">]>'
        '<metadata xmlns="urn:framegate:1" kind="generic" timestamp_ns="4000000">&x;</metadata>'
    )
    laughs = (
        '<?xml version="1.0"?><!DOCTYPE l [<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;&a;">]>'
        '<metadata xmlns="urn:framegate:1" kind="generic" timestamp_ns="4000000">&b;</metadata>'
    )
    cases = [
        ({"metadata": xxe}, "SchemaError", "DTD or entity"),
        ({"metadata": laughs}, "SchemaError", "DTD or entity"),
        ({"metadata": make_metadata("frame", 4 * MS).decode()}, "SchemaError", "kind 'frame'"),
        ({"metadata": "<metadata"}, "SchemaError", "not well-formed"),
        ({"t": 3 * MS}, "DuplicateTimestampError", "duplicates the newest"),
    ]
    for extra, error, message in cases:
        reply = producer.call("put", buffer="images", **{"t": 4 * MS, **extra})
        assert not reply["ok"] and reply["error"] == error and message in reply["message"]
    with Node(network=connect_net) as client:
        wait_until(lambda: "cam" in client.live_services(), 30, "the producer service")
        for params, message in [
            ({"time_range": "[now(-2x)..]"}, "bad duration"),
            ({"time_range": "garbage"}, "bad time range"),
            ({"time_range": "[5..1]"}, "ends before it starts"),
        ]:
            with pytest.raises(QueryError, match=message):
                client.query("cam/images", **params)
        with pytest.raises(QueryError, match="unknown query parameter"):
            client._get("cam/images", {"bogus": "1"}, 5.0)
        with pytest.raises(QueryError, match="last='x' is not an integer"):
            client._get("cam/images", {"last": "x"}, 5.0)
        with pytest.raises(NotFoundError, match=r"no buffer 'imgs' \(did you mean 'images'\?\)"):
            client.query("cam/imgs")
        with pytest.raises(
            NotFoundError, match=r"no live service named 'camm' \(did you mean 'cam'"
        ):
            client.query("camm/images")
        # Nothing accepted was lost or changed, and the service still answers.
        elements = client.query("cam/images")
        assert [(e.timestamp_ns, e.payload) for e in elements] == [
            (t * MS, b"p%d" % (t * MS)) for t in (1, 2, 3)
        ]
    assert producer.call("put", buffer="images", t=4 * MS)["ok"]


def test_client_resubscribes_when_its_service_restarts(
    node_process: Callable[..., NodeProcess], endpoint: str, connect_net: NetworkConfig
) -> None:
    first = _start_producer(node_process, endpoint)
    with Node(network=connect_net) as client:
        wait_until(lambda: "cam" in client.live_services(), 30, "the producer service")
        sub = client.subscribe("cam/images", queue_size=2)
        assert first.call("put", buffer="images", t=1)["ok"]
        assert sub.take(timeout_s=scaled(30)).timestamp_ns == 1  # type: ignore[union-attr]
        first.kill()
        second = _start_producer(node_process, endpoint)
        assert second.call("wait_subscribers", buffer="images", count=1, timeout=30)["registered"]
        assert second.call("put", buffer="images", t=5)["ok"]
        note = sub.take(timeout_s=scaled(30))
        assert note is not None and note.timestamp_ns == 5
        assert sub.fetch(note).payload == b"p5"


def test_local_default_needs_no_configuration(monkeypatch: pytest.MonkeyPatch) -> None:
    from tests.conftest import free_port

    monkeypatch.setenv("FRAMEGATE_LOCAL_PORT", str(free_port()))
    net = NetworkConfig().with_env()
    assert net.uses_local_default
    with Node("cam", net) as first, Node("det", net) as second, Node(network=net) as third:
        first.offer("images")
        second.offer("detections")
        wait_until(
            lambda: third.live_services() == ["cam", "det"], 30, "both services via the rendezvous"
        )
        sub = third.subscribe("cam/images", queue_size=1, mode=SubscriptionMode.OBSERVE)
        assert sub.subscription_id


def test_payloads_are_pushed_up_to_the_subscription_limit(
    node_process: Callable[..., NodeProcess], endpoint: str, connect_net: NetworkConfig
) -> None:
    from middleware import PUSH_ALL

    producer = _start_producer(node_process, endpoint)
    big = bytes(range(256)) * 4096  # 1 MiB: over the producer's 64 KiB default
    with Node(network=connect_net) as client:
        wait_until(lambda: "cam" in client.live_services(), 30, "the producer service")
        pushed = client.subscribe("cam/images", queue_size=4, push_max_bytes=PUSH_ALL)
        fetched = client.subscribe("cam/images", queue_size=4)
        for t, payload in ((1, b"small"), (2, big)):
            reply = producer.call(
                "put", buffer="images", t=t, payload=base64.b64encode(payload).decode()
            )
            assert reply["ok"], reply
        small_pushed, big_pushed = (
            pushed.take(timeout_s=scaled(5)),
            pushed.take(timeout_s=scaled(5)),
        )
        small_fetched, big_fetched = (
            fetched.take(timeout_s=scaled(5)),
            fetched.take(timeout_s=scaled(5)),
        )
        assert small_pushed and big_pushed and small_fetched and big_fetched
        assert big_pushed.element is not None and big_pushed.element.payload == big
        assert small_fetched.element is not None  # small ones ride along by default
        assert big_fetched.element is None  # large ones are fetched on demand
        assert fetched.fetch(big_fetched).payload == big
