"""The loop's gate against the node's images, with no Zenoh: ``ConsumerLoop`` driven with
stand-in subscriptions and a clock of the test's, so that the registration race of its two
subscriptions is played exactly."""

from __future__ import annotations

import threading
import types
from typing import Any

import pytest

from services.evidence.bench._ros2_node import _header_cdr
from services.nodes.ros2 import _consumer_loop
from services.nodes.ros2._config import Mapping, Ros2Config
from services.nodes.ros2._consumer import MAX_RESULT_TYPES
from services.nodes.ros2._consumer_loop import ConsumerLoop
from services.nodes.ros2._rmw import EntityKind, NodeIdentity, Qos


class _Sub:
    """A subscription's local queue of notifications (keys only)."""

    def __init__(self, keys: list[int]) -> None:
        self.notes = [self.note(k) for k in keys]

    @staticmethod
    def note(key: int) -> Any:
        return types.SimpleNamespace(timestamp_ns=key, missed=0, service="m", buffer="images")

    @property
    def pending(self) -> int:
        return len(self.notes)

    def take(self, timeout_s: float = 0) -> Any:
        return self.notes.pop(0) if self.notes else None

    def take_many(self, count: int, timeout_s: float = 0) -> list[Any]:
        taken, self.notes = self.notes[:count], self.notes[count:]
        return taken

    def fetch(self, note: Any) -> Any:
        return types.SimpleNamespace(timestamp_ns=note.timestamp_ns)

    def close(self) -> None:
        pass


class _Link:
    """The ROS 2 side's subscriptions as the loop declares them, in order, with what the
    data subscriber delivers to (``on_result``)."""

    def __init__(self, calls: list[str] | None = None) -> None:
        self.calls = calls if calls is not None else []
        self.on_result: Any = None
        self.tokens: list[str] = []

    def listen_any_type(self, topic: str, on_sample: Any) -> None:
        self.calls.append(f"listen {topic}")
        self.on_result = on_sample

    def subscription_token(self, topic: str, ros_type: str, *a: Any) -> None:
        self.tokens.append(ros_type)


def _loop(feed: _Sub, gate: _Sub, queue: int, link: Any = None) -> tuple[ConsumerLoop, list[str]]:
    """A loop of ``--consumer-queue queue`` on the stand-in subscriptions (the feed first, as
    the loop subscribes), and the skip reasons it counts."""
    subscriptions = iter([feed, gate])
    calls = link.calls if isinstance(link, _Link) else []

    def subscribe(*a: Any, **k: Any) -> _Sub:
        calls.append("framegate subscribe")
        return next(subscriptions)

    node = types.SimpleNamespace(
        offer=lambda *a, **k: types.SimpleNamespace(put=lambda *a: None),
        subscribe=subscribe,
    )
    link = link if link is not None else _Link()
    skipped: list[str] = []
    config = Ros2Config(
        image_out=(Mapping("m/images", "/in"),),
        consumer_done="/out",
        consumer_queue=queue,
        consumer_timeout_ms=1000,
    )
    loop = ConsumerLoop(
        node,  # type: ignore[arg-type]
        link,
        types.SimpleNamespace(publish=lambda cdr: None),  # type: ignore[arg-type]
        config.image_out[0],
        lambda element: b"image",
        config,
        types.SimpleNamespace(count=lambda producer, reason, detail: skipped.append(reason)),
    )
    return loop, skipped


def _test_clock(monkeypatch: pytest.MonkeyPatch) -> Any:
    """The loop's clock, set by the test (``clock.now_ns``)."""
    clock = types.SimpleNamespace(now_ns=0)
    fake_time = types.SimpleNamespace(monotonic_ns=lambda: clock.now_ns, time_ns=lambda: 0)
    monkeypatch.setattr(_consumer_loop, "time", fake_time)
    return clock


def test_an_image_the_gate_never_counted_leaves_no_lasting_deficit(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    clock = _test_clock(monkeypatch)
    # The gate registered after image 1000 was put: the feed has it, the gate does not.
    feed, gate = _Sub([1000, 2000]), _Sub([2000])
    loop, skipped = _loop(feed, gate, 2)

    def image(key: int) -> None:  # the mediator puts it: both subscriptions are notified
        if key not in (n.timestamp_ns for n in feed.notes):
            feed.notes.append(_Sub.note(key))
            gate.notes.append(_Sub.note(key))
        loop._publish(feed.take())

    def answer(key: int, at_ms: int) -> None:  # the node's result for image ``key``
        clock.now_ns = at_ms * 1_000_000
        loop._answers.put((_header_cdr(key, "camera", 0), None))
        loop._turn()

    image(1000)
    image(2000)
    # The node answers every image 400 ms after the one before, and gets the next at once:
    # it always holds two, and the gate must count two.
    for i, key in enumerate(range(1000, 8000, 1000)):
        answer(key, 400 * i)
        image(key + 2000)
    assert len(loop._ledger) == 2
    assert gate.pending == 2, "the mediator sees the node one image less busy than it is"
    assert skipped == ["ungated-image"]


class _Flood:
    """A result queue a hostile peer never lets run dry (forged stamps, no image of ours)."""

    def __init__(self) -> None:
        self.given = 0

    def get(self, timeout: float = 0) -> Any:
        return self.get_nowait()

    def get_nowait(self) -> Any:
        self.given += 1
        if self.given > 100_000:
            raise RuntimeError("the resolver's turn never ended under a flood of results")
        return _header_cdr(1, "forged", 0), None


def test_a_flood_of_results_does_not_keep_the_resolver_from_expiring_slots(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    clock = _test_clock(monkeypatch)
    feed, gate = _Sub([1000]), _Sub([1000])
    loop, skipped = _loop(feed, gate, 1)
    loop._publish(feed.take())
    flood = _Flood()
    loop._answers = flood  # type: ignore[assignment]
    clock.now_ns = 2_000_000_000  # the node never answered: its slot is due to be freed
    loop._turn()
    assert len(loop._ledger) == 0 and gate.pending == 0, "the slot was not freed"
    assert "consumer-timeout" in skipped
    assert flood.given < 1000, "one turn took the whole flood"


def test_the_nodes_results_are_heard_before_any_image_can_reach_it() -> None:
    # The result subscription was declared only once the graph watch had named the result
    # type: a node answering its first image before that lost the answer (consumer-timeout).
    link = _Link()
    feed, gate = _Sub([1000]), _Sub([1000])
    loop, skipped = _loop(feed, gate, 1, link)
    assert link.calls[0] == "listen /out", link.calls  # before the loop's subscriptions
    loop._publish(feed.take())
    link.on_result(bytes(_header_cdr(1000, "camera", 0)), None)  # no token seen yet
    loop._turn()
    assert len(loop._ledger) == 0 and gate.pending == 0 and skipped == []
    assert link.tokens == []  # the graph shows the subscription once the type is known


def test_tokens_of_made_up_types_declared_first_do_not_shut_out_the_nodes_results() -> None:
    feed, gate = _Sub([]), _Sub([])
    real = "vision_msgs/msg/Detection2DArray"
    link = _Link()
    loop, _ = _loop(feed, gate, 1, link)
    identity = NodeIdentity(0, "a1b2", "peer")
    # A hostile peer declares (and may withdraw at once) publishers of made-up types.
    for i in range(2 * MAX_RESULT_TYPES):
        kind = EntityKind.PUBLISHER
        loop.on_token(
            identity.endpoint_token(i, kind, "/out", f"x_msgs/msg/T{i}", "RIHS01_00", Qos())
        )
    loop.on_token(
        identity.endpoint_token(99, EntityKind.PUBLISHER, "/out", real, "RIHS01_11", Qos())
    )
    stop = threading.Event()
    loop._turn = stop.set  # type: ignore[method-assign]
    loop.run_resolver(stop)
    # Heard whatever the tokens: the data subscriber takes every type on the topic.
    assert link.calls == ["listen /out", "framegate subscribe", "framegate subscribe"]
    assert len(link.tokens) == 1


def test_a_queued_result_keeps_only_its_header_however_large_it_came() -> None:
    feed, gate = _Sub([1000]), _Sub([1000])
    loop, _ = _loop(feed, gate, 1)
    loop._publish(feed.take())
    # A peer's results of 64 MiB each: a full queue of them held 4 GiB.
    bulk = bytes(64 << 20)
    loop._on_result(bytes(_header_cdr(1000, "camera", 0)) + bulk, bulk)
    raw, attachment = loop._answers.queue[0]
    assert len(raw) <= 8192 and (attachment is None or len(attachment) <= 8192)
    loop._turn()  # what was kept still answers the image
    assert len(loop._ledger) == 0 and gate.pending == 0


def test_a_result_stamped_by_the_node_itself_says_the_header_must_be_copied() -> None:
    # A node stamping its results with now() had every image time out; the one warning said
    # only "result stamped ... ns (camera)", not what names an image or what to change.
    feed, gate = _Sub([1_000_000]), _Sub([1_000_000])
    loop, _ = _loop(feed, gate, 1)
    said: list[tuple[str, str]] = []
    loop._skips = types.SimpleNamespace(
        count=lambda p, reason, detail: said.append((reason, detail))
    )
    loop._publish(feed.take())
    loop._answers.put((_header_cdr(1_004_000, "camera", 0), None))
    loop._turn()
    [(reason, detail)] = said
    assert reason == "unmatched-result"
    assert "names no image sent to /in (nearest waiting: 1000000 ns)" in detail
    assert "copy its image's header.stamp" in detail
    assert len(loop._ledger) == 1  # its image still waits for its own result
