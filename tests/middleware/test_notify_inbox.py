"""A subscription's notification inbox: its byte bound pushes out the oldest without
calling them dropped (honest pushed frames fill it too)."""

from __future__ import annotations

from types import SimpleNamespace

from middleware._inbox import Inbox


def test_samples_pushed_out_for_bytes_are_not_counted_dropped() -> None:
    """32 honest frames of 3 MiB pushed to a flow-controlled PUSH_ALL subscriber filled
    the 64 MiB bound: 11 pushed out (resent later) were counted ``dropped``, which the
    vision runner, the mediator, the ros2 bridge and record report as a peer's garbage."""
    inbox = Inbox(capacity=64, max_bytes=1 << 30, signal=lambda: None, max_held_bytes=100)
    for _ in range(5):
        inbox._on_sample(SimpleNamespace(payload=b"x" * 40, attachment=b"y" * 10))  # type: ignore[arg-type]
    assert len(inbox) == 2 and inbox.held_bytes == 100
    assert (inbox.squeezed, inbox.dropped) == (3, 0)
    assert len(inbox.take(8)) == 2 and inbox.held_bytes == 0
