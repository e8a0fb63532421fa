"""Regression tests for the flow-control defects of issue 14, over real Zenoh in one process.

A producer ``Node`` listens on a loopback port, a client ``Node`` connects to it, and a raw
Zenoh session (what any peer in the default trusted profile can open) forges messages on
the wire keys of docs/wire-format.md. Each test names the defect it pins down.
"""

from __future__ import annotations

import re
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import msgpack
import pytest
import zenoh

from middleware import (
    ClosedError,
    ConfigError,
    FlowControlRefused,
    NetworkConfig,
    Node,
    Producer,
    Subscription,
    make_metadata,
    tightest_flow,
)
from middleware._buffer import TimeSeries
from middleware._records import DataObject, Retention
from tests.conftest import wait_until
from tests.helpers.raw_zenoh import open_session
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration

SERVICE, BUFFER = "cam", "images"
FORGED_T = 999_999


def _put(producer: Producer, t: int, wait_s: float = 0.0) -> None:
    producer.put(t, b"p%d" % t, make_metadata("generic", t), wait_s=wait_s)


def _forged_header(epoch: str, seq: int, t: int = FORGED_T) -> bytes:
    # docs/wire-format.md's array of 7: epoch, seq, timestamp_ns, metadata, pushed, acked,
    # descriptor.
    body = [epoch, seq, t, make_metadata("generic", t), True, None, None]
    return bytes(msgpack.packb(body, use_bin_type=True))


@contextmanager
def _pair(
    listen_net: NetworkConfig, connect_net: NetworkConfig, queue: int
) -> Iterator[tuple[Producer, Subscription, Node]]:
    """cam/images offered by one node, a flow subscription of ``queue`` from another."""
    with Node(SERVICE, listen_net) as server, Node(network=connect_net) as client:
        images = server.offer(BUFFER)
        sub = client.subscribe(f"{SERVICE}/{BUFFER}", queue_size=queue)
        assert images.wait_for_subscribers(1, timeout_s=scaled(30))
        yield images, sub, client


def _drain(sub: Subscription, timeout_s: float = 1.0) -> list[int]:
    """Take notifications until none arrives for ``timeout_s``; their timestamps."""
    seen = []
    while (note := sub.take(timeout_s=scaled(timeout_s))) is not None:
        seen.append(note.timestamp_ns)
    return seen


class _SpyEpoch:
    """Learns the epoch of a subscription's notifications, as any peer can."""

    def __init__(self, session: zenoh.Session, sub_id: str) -> None:
        self.epochs: list[str] = []
        self.seen = threading.Event()
        self._sub = session.declare_subscriber(
            f"framegate/@notify/{SERVICE}/{BUFFER}/{sub_id}", self._on
        )

    def _on(self, sample: zenoh.Sample) -> None:
        assert sample.attachment is not None
        self.epochs.append(msgpack.unpackb(sample.attachment.to_bytes())[0])
        self.seen.set()

    def close(self) -> None:
        self._sub.undeclare()


def test_foreign_epoch_notification_does_not_block_a_full_producer(
    endpoint: str, listen_net: NetworkConfig, connect_net: NetworkConfig
) -> None:
    with _pair(listen_net, connect_net, queue=2) as (images, sub, _client):
        _put(images, 1)
        _put(images, 2)
        wait_until(lambda: sub.pending == 2, 30, "both notifications")
        with open_session(endpoint) as rogue:
            rogue.put(
                f"framegate/@notify/{SERVICE}/{BUFFER}/{sub.subscription_id}",
                b"forged",
                attachment=_forged_header("foreign", 1),
            )
            taken = _drain(sub)
        # Nothing the producer stored is lost, and once taken the producer is free again.
        assert [t for t in taken if t != FORGED_T] == [1, 2]
        _put(images, 3, wait_s=5.0)
        note = sub.take(timeout_s=scaled(30))
        assert note is not None and note.timestamp_ns == 3
        assert sub.missed_total == 0


def test_forged_future_seq_neither_drops_real_notifications_nor_reports_missed(
    endpoint: str, listen_net: NetworkConfig, connect_net: NetworkConfig
) -> None:
    with _pair(listen_net, connect_net, queue=2) as (images, sub, _client):
        with open_session(endpoint) as rogue:
            spy = _SpyEpoch(rogue, sub.subscription_id)
            wait_until(lambda: _put(images, 1) is None, 30, "the first put")
            assert spy.seen.wait(scaled(30))
            first = sub.take(timeout_s=scaled(30))
            assert first is not None and first.timestamp_ns == 1
            rogue.put(
                f"framegate/@notify/{SERVICE}/{BUFFER}/{sub.subscription_id}",
                b"forged",
                attachment=_forged_header(spy.epochs[0], 1000),
            )
            spy.close()
        for t in (2, 3, 4):
            _put(images, t, wait_s=5.0)
            note = sub.take(timeout_s=scaled(30))
            assert note is not None and note.timestamp_ns == t, note
            assert note.missed == 0
        assert sub.missed_total == 0
        assert sub.pending == 0


def test_colliding_observe_token_cannot_remove_a_flow_subscription(
    endpoint: str, listen_net: NetworkConfig, connect_net: NetworkConfig
) -> None:
    with _pair(listen_net, connect_net, queue=2) as (images, sub, _client):
        sub_id = sub.subscription_id
        with open_session(endpoint) as rogue:
            token = rogue.liveliness().declare_token(
                f"framegate/@sub/{SERVICE}/{BUFFER}/{sub_id}/observe/1/-1"
            )
            wait_until(lambda: len(images.subscriptions()) == 2, 30, "the rogue's token")
            token.undeclare()
            wait_until(lambda: len(images.subscriptions()) == 1, 30, "the rogue's token to go")
        [left] = images.subscriptions()
        assert left.subscription_id == sub_id and left.mode.value == "flow"
        _put(images, 1)
        load = tightest_flow(images.subscriptions())
        assert load is not None and load.fill == pytest.approx(0.5)  # the load is still counted
        note = sub.take(timeout_s=scaled(30))
        assert note is not None and note.timestamp_ns == 1


def test_colliding_observe_token_does_not_feed_the_flow_subscriber(
    endpoint: str, listen_net: NetworkConfig, connect_net: NetworkConfig
) -> None:
    with _pair(listen_net, connect_net, queue=4) as (images, sub, _client):
        with open_session(endpoint) as rogue:
            token = rogue.liveliness().declare_token(
                f"framegate/@sub/{SERVICE}/{BUFFER}/{sub.subscription_id}/observe/1/-1"
            )
            wait_until(lambda: len(images.subscriptions()) == 2, 30, "the rogue's token")
            for t in (1, 2):
                _put(images, t)
            # Each element reaches the real subscriber once, not once per registration.
            assert _drain(sub) == [1, 2]
            token.undeclare()


class _FlakyPublisher:
    def __init__(self, inner: Any, owner: _FlakySession) -> None:
        self._inner = inner
        self._owner = owner

    def put(self, *args: Any, **kwargs: Any) -> Any:
        owner = self._owner
        if owner.producer is not None:
            # The lock Zenoh's callbacks take must be free while a put may block.
            free: list[bool] = []
            probe = threading.Thread(
                target=lambda: free.append(owner.producer._cond.acquire(blocking=False))  # type: ignore[union-attr]
            )
            probe.start()
            probe.join()
            if free[0]:
                owner.producer._cond.release()  # type: ignore[union-attr]
            owner.lock_free_during_put.append(free[0])
        if owner.failures > 0:
            owner.failures -= 1
            raise zenoh.ZError("injected send failure")
        return self._inner.put(*args, **kwargs)

    def undeclare(self) -> None:
        self._owner.undeclared += 1
        self._inner.undeclare()


class _FlakySession:
    """Wraps a session: counts publishers and can make their puts fail."""

    def __init__(self, inner: zenoh.Session) -> None:
        self._inner = inner
        self.failures = 0
        self.declared = 0
        self.undeclared = 0
        self.producer: Producer | None = None
        self.lock_free_during_put: list[bool] = []

    def declare_publisher(self, *args: Any, **kwargs: Any) -> _FlakyPublisher:
        self.declared += 1
        return _FlakyPublisher(self._inner.declare_publisher(*args, **kwargs), self)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)


def test_failed_notification_send_does_not_lose_the_credit(
    listen_net: NetworkConfig, connect_net: NetworkConfig
) -> None:
    with _pair(listen_net, connect_net, queue=1) as (images, sub, _client):
        flaky = _FlakySession(images._session)
        images._session = flaky  # type: ignore[assignment]
        flaky.failures = 1
        _put(images, 1)  # stored; its notification fails to leave
        note = sub.take(timeout_s=scaled(30))
        assert note is not None and note.timestamp_ns == 1
        _put(images, 2, wait_s=5.0)
        note = sub.take(timeout_s=scaled(30))
        assert note is not None and note.timestamp_ns == 2


def test_notification_send_does_not_hold_the_callback_lock(
    listen_net: NetworkConfig, connect_net: NetworkConfig
) -> None:
    with _pair(listen_net, connect_net, queue=4) as (images, sub, _client):
        flaky = _FlakySession(images._session)
        flaky.producer = images
        images._session = flaky  # type: ignore[assignment]
        _put(images, 1)
        assert flaky.lock_free_during_put == [True]
        assert sub.take(timeout_s=scaled(30)) is not None


def test_token_flaps_do_not_leak_publishers(
    endpoint: str, listen_net: NetworkConfig, connect_net: NetworkConfig
) -> None:
    with Node(SERVICE, listen_net) as server, open_session(endpoint) as rogue:
        images = server.offer(BUFFER)
        flaky = _FlakySession(images._session)
        images._session = flaky  # type: ignore[assignment]
        for t in range(1, 4):
            token = rogue.liveliness().declare_token(
                f"framegate/@sub/{SERVICE}/{BUFFER}/flap{t}/observe/4/-1"
            )
            wait_until(lambda: len(images.subscriptions()) == 1, 30, "the flapping token")
            _put(images, t)
            token.undeclare()
            wait_until(lambda: not images.subscriptions(), 30, "the token to go")
        _put(images, 10)  # with nobody registered
        wait_until(
            lambda: flaky.undeclared == flaky.declared == 3, 30, "every publisher undeclared"
        )


def test_closed_subscriptions_leave_the_node(
    listen_net: NetworkConfig, connect_net: NetworkConfig
) -> None:
    with Node(SERVICE, listen_net) as server, Node(network=connect_net) as client:
        server.offer(BUFFER)
        for _ in range(3):
            client.subscribe(f"{SERVICE}/{BUFFER}", queue_size=1, wait_s=0).close()
        assert client._subscriptions == []


def test_a_closed_subscription_reads_and_takes_nothing_without_raising(
    listen_net: NetworkConfig, connect_net: NetworkConfig
) -> None:
    # A taker waiting for notifications is released by the close.
    with _pair(listen_net, connect_net, 4) as (images, sub, _client):
        taken: list[object] = []
        taker = threading.Thread(target=lambda: taken.append(sub.take(timeout_s=scaled(5))))
        taker.start()
        wait_until(lambda: sub._wake.threads, 30, "the taker to wait")
        sub.close()
        taker.join(timeout=scaled(2))
        assert not taker.is_alive() and taken == [None]
        assert (sub.pending, sub.garbage, sub.missed_total) == (0, 0, 0)
        assert (
            sub.take(timeout_s=scaled(0.1)) is None
            and sub.take_many(3, timeout_s=scaled(0.1)) == []
        )
        images.close()
        assert images.subscriptions() == []


def test_second_process_offering_a_live_name_is_refused(
    listen_net: NetworkConfig, connect_net: NetworkConfig
) -> None:
    with Node(SERVICE, listen_net) as first:
        first.offer(BUFFER)
        with Node(SERVICE, connect_net) as second:
            with pytest.raises(ConfigError, match=r"already offered by pid \d+ on host \S+"):
                second.offer(BUFFER)
    with Node(SERVICE, listen_net) as first, Node(SERVICE, connect_net) as third:
        first.offer("other")
        first.close()  # the old instance is gone: a restart takes over
        wait_until(lambda: SERVICE not in third.live_services(), 30, "the first to go")
        third.offer(BUFFER)


class _RecordingLock:
    """A lock that records each acquisition."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.acquired = 0

    def __enter__(self) -> bool:
        self._lock.acquire()
        self.acquired += 1
        return True

    def __exit__(self, *_exc: Any) -> None:
        self._lock.release()

    def acquire(self, blocking: bool = True, timeout: float = -1) -> bool:
        got = self._lock.acquire(blocking, timeout)
        self.acquired += got
        return got

    def release(self) -> None:
        self._lock.release()


def test_time_series_reads_take_its_lock() -> None:
    series = TimeSeries(Retention())
    series.append(DataObject(1, b"x", b"m"))
    recorder = _RecordingLock()
    series._lock = recorder  # type: ignore[assignment]
    for read in (
        len,
        lambda s: s.total_bytes,
        lambda s: s.check_extend((DataObject(2, b"x", b"m"),)),
    ):
        before = recorder.acquired
        read(series)
        assert recorder.acquired > before, read


def test_put_refusal_names_the_full_subscription(
    listen_net: NetworkConfig, connect_net: NetworkConfig
) -> None:
    with _pair(listen_net, connect_net, queue=1) as (images, sub, _client):
        _put(images, 1)
        with pytest.raises(FlowControlRefused, match=re.escape(sub.subscription_id)):
            _put(images, 2)


def test_a_put_on_a_closed_buffer_is_a_closed_error(listen_net: NetworkConfig) -> None:
    """What a service's timer meets between a stop and its end: its own kind of error, so
    the service can tell a stop from a failure (and stay quiet about it)."""
    with Node("cam", listen_net) as service:
        images = service.offer("images")
        images.close()
        with pytest.raises(ClosedError, match="is closed"):
            images.put(1, b"x", make_metadata("generic", 1))
        with pytest.raises(ClosedError):
            images.put_many([(2, b"x", make_metadata("generic", 2))])


def test_producer_epoch_is_the_greeting_producer_and_a_new_instance_changes_it(
    endpoint: str,
) -> None:
    """What a stage that follows rewinds relies on: only a new producer instance (here one
    that took the name after the first closed) changes it."""
    server_net = NetworkConfig(connect=(endpoint,))  # each instance joins the client's port
    with Node(network=NetworkConfig(listen=(endpoint,))) as client:
        with Node(SERVICE, server_net) as first:
            images = first.offer(BUFFER)
            sub = client.subscribe(f"{SERVICE}/{BUFFER}", queue_size=4, await_service=True)
            assert images.wait_for_subscribers(1, timeout_s=scaled(10))
            wait_until(lambda: sub.producer_epoch == images.epoch, scaled(10), "the greeting")
        with Node(SERVICE, server_net) as second:
            again = second.offer(BUFFER)
            wait_until(lambda: sub.producer_epoch == again.epoch, scaled(30), "a new greeting")
            assert again.epoch != images.epoch
        sub.close()
