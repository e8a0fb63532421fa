"""The vision handler's thread (``services.nodes._runtime.CallThread``): every call on one
thread of its own, what a call raises raised to the caller, and a stop that waits for a
busy call only its grace. A vision handler used to run on a new thread per frame: what a
call left in per-thread state (a thread-local cache, PyTorch's grad mode, a SQLite
connection its class made) was gone at the next frame."""

from __future__ import annotations

import threading
import time

import pytest

from services.nodes._runtime import CallThread
from tests.helpers.timing import scaled


def test_every_call_runs_on_one_thread_that_is_not_the_caller_s() -> None:
    thread = CallThread("test-calls")
    stop = threading.Event()
    local = threading.local()

    def count() -> tuple[threading.Thread, int]:
        local.calls = getattr(local, "calls", 0) + 1
        return threading.current_thread(), local.calls

    try:
        outcomes = [thread.call(count, stop) for _ in range(5)]
    finally:
        thread.close()
    assert [o[1] for o in outcomes if o is not None] == [1, 2, 3, 4, 5]
    (ran_on,) = {o[0] for o in outcomes if o is not None}
    assert ran_on is not threading.current_thread() and ran_on.name == "test-calls"
    assert not ran_on.is_alive()  # closed


def test_what_a_call_raises_is_raised_to_the_caller_and_the_thread_goes_on() -> None:
    thread = CallThread("test-calls")
    stop = threading.Event()

    def fail() -> int:
        raise ValueError("bad frame")

    try:
        with pytest.raises(ValueError, match="bad frame"):
            thread.call(fail, stop)
        assert thread.call(lambda: 7, stop) == 7
    finally:
        thread.close()


def test_a_stop_ends_the_wait_for_a_busy_call_after_its_grace() -> None:
    thread = CallThread("test-calls")
    stop = threading.Event()
    release = threading.Event()
    threading.Timer(0.2, stop.set).start()
    started = time.monotonic()
    assert thread.call(lambda: release.wait(scaled(60)), stop) is None
    waited = time.monotonic() - started
    closing = time.monotonic()
    thread.close()  # its grace is spent: the abandoned call is not waited for again
    closed = time.monotonic() - closing
    release.set()
    assert waited < scaled(10), waited
    assert closed < 0.25, closed
