"""The node's executor against real Zenoh sessions on loopback: handlers for subscriptions,
timers and deadlines run on its one thread; ``spin``; a handler that blocks on framegate
does not wait for the executor (which is itself)."""

from __future__ import annotations

import threading
import time

import pytest

from middleware import FlowControlRefused, FramegateError, Node, Notification, make_metadata
from tests.conftest import wait_until
from tests.helpers.timing import scaled


def _meta(t: int) -> bytes:
    return make_metadata("generic", t)


def test_a_handler_gets_every_notification_in_bounded_batches_on_the_executor(
    listen_net, connect_net
) -> None:
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        images = service.offer("images")
        sub = client.subscribe("cam/images", queue_size=32)
        seen: list[int] = []
        batches: list[int] = []
        threads: set[str] = set()

        def on_images(notes: list[Notification]) -> None:
            threads.add(threading.current_thread().name)
            batches.append(len(notes))
            seen.extend(n.timestamp_ns for n in notes)

        client.on(sub, on_images, max_batch=4)
        for t in range(1, 201):
            images.put(t, b"x", _meta(t), wait_s=10.0)
        wait_until(lambda: len(seen) == 200, 20.0, "every notification handled")
        assert seen == list(range(1, 201))
        assert max(batches) <= 4
        assert threads == {"fg-exec-client"}
        with pytest.raises(FramegateError, match="has a handler"):
            sub.take(timeout_s=0.1)


def test_timers_and_deadlines_run_on_the_executor_until_cancelled(listen_net) -> None:
    with Node("cam", listen_net) as node:
        ticks: list[int] = []
        once: list[str] = []
        timer = node.every(0.01, ticks.append)
        node.at(
            time.monotonic_ns() + 20_000_000,
            lambda _now: once.append(threading.current_thread().name),
        )
        cancelled = node.at(time.monotonic_ns() + 30_000_000, lambda _now: once.append("no"))
        cancelled.cancel()
        wait_until(lambda: len(ticks) >= 5 and once, 10.0, "ticks and the deadline")
        assert ticks == sorted(ticks)
        timer.cancel()
        time.sleep(0.1)  # a run already started may finish
        count = len(ticks)
        time.sleep(0.2)
        assert len(ticks) == count, "a cancelled timer runs no more"
        assert once == ["fg-exec-cam"]


def test_spin_returns_on_stop_and_raises_a_handler_error(listen_net) -> None:
    with Node("cam", listen_net) as node:
        stop = threading.Event()
        node.at(time.monotonic_ns() + 50_000_000, lambda _now: stop.set())
        node.spin(stop)  # returns: the deadline set it

    with Node("cam2", listen_net) as node:

        def broken(_now: int) -> None:
            raise ValueError("broken handler")

        node.at(time.monotonic_ns(), broken)
        with pytest.raises(ValueError, match="broken handler"):
            node.spin(threading.Event())


def test_a_handler_that_waits_to_put_is_not_waiting_for_itself(listen_net, connect_net) -> None:
    """A handler's put(wait_s) on a full queue waits for acks that the executor — its own
    thread — would feed: it feeds them inline instead, and gets its credit back."""
    with Node("relay", listen_net) as service, Node(network=connect_net) as client:
        out = service.offer("out")
        sub = client.subscribe("relay/out", queue_size=2)
        results: list[object] = []

        def produce(_now: int) -> None:
            try:
                for t in range(1, 7):
                    out.put(t, b"x", _meta(t), wait_s=10.0)
                results.append("stored")
            except FramegateError as exc:
                results.append(exc)

        service.at(time.monotonic_ns(), produce)
        taken = []
        while len(taken) < 6:
            note = sub.take(timeout_s=10.0)
            assert note is not None, f"stalled after {taken}"
            taken.append(note.timestamp_ns)
        wait_until(lambda: results, 10.0, "the handler's puts")
        assert results == ["stored"]

        # And a wait that runs out still ends within wait_s and a small slack.
        def refused(_now: int) -> None:
            start = time.monotonic()
            try:
                for t in range(7, 20):
                    out.put(t, b"x", _meta(t), wait_s=0.3)
            except FlowControlRefused:
                results.append(time.monotonic() - start)

        service.at(time.monotonic_ns(), refused)
        wait_until(lambda: len(results) == 2, 10.0, "the refusal")
        # Refused, not hung: within its wait_s, with the suite's slack for a slow machine.
        assert isinstance(results[1], float) and results[1] < scaled(3.0)


def test_a_handler_may_take_from_another_subscription(listen_net, connect_net) -> None:
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        a, b = service.offer("a"), service.offer("b")
        sub_a = client.subscribe("cam/a", queue_size=4)
        sub_b = client.subscribe("cam/b", queue_size=4)
        pairs: list[tuple[int, int]] = []

        def on_a(notes: list[Notification]) -> None:
            for note in notes:
                other = sub_b.take(timeout_s=10.0)
                assert other is not None
                pairs.append((note.timestamp_ns, other.timestamp_ns))

        client.on(sub_a, on_a, max_batch=1)
        for t in range(1, 4):
            a.put(t, b"x", _meta(t), wait_s=10.0)
        time.sleep(0.05)
        for t in range(1, 4):
            b.put(t, b"y", _meta(t), wait_s=10.0)
        wait_until(lambda: len(pairs) == 3, 20.0, "every pair")
        assert pairs == [(1, 1), (2, 2), (3, 3)]


def test_a_buffer_or_subscription_is_whole_when_the_executor_first_reads_its_deadline(
    listen_net, connect_net, monkeypatch
) -> None:
    """Regression: a producer joined the executor before its constructor had set every field,
    and an executor already running (for another buffer) read its deadline in between: the
    ``AttributeError`` was logged as "deadline of <Producer> failed" on a live service. Here
    ``add`` reads the deadline and runs it at once, as the running thread may."""
    from middleware._executor import Executor

    added: list[str] = []
    real_add = Executor.add

    def add_and_read_at_once(self: Executor, obj) -> None:
        real_add(self, obj)
        obj.next_deadline_ns()
        obj.on_deadline(time.monotonic_ns())
        added.append(type(obj).__name__)

    monkeypatch.setattr(Executor, "add", add_and_read_at_once)
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        images = service.offer("images")
        sub = client.subscribe("cam/images", queue_size=4)
        images.put(1, b"x", _meta(1), wait_s=10.0)
        assert sub.take(timeout_s=10.0) is not None
    assert added == ["Producer", "Subscription"]
