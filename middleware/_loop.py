"""One loop per node: the thread that runs every timer of its producers and subscriptions.

Each timed object says when it next has work (``next_deadline_ns``, on the monotonic clock)
and does it in ``on_deadline``; the loop sleeps until the earliest deadline of all of them.
An object whose deadline moves earlier calls ``poke`` (it costs a lock and a wake-up only
when the loop sleeps past the new deadline). So a node runs one timer thread however many
buffers and subscriptions it holds, and none at all while nothing is due.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Protocol

log = logging.getLogger("framegate.middleware")

# The loop re-reads every deadline at least this often (a poke lost to a race costs this).
_MAX_SLEEP_NS = 1_000_000_000
# Waking this much later than planned means the process did not run (SIGSTOP, a debugger,
# a suspended VM): peers may have dropped it (see ``on_stall``).
STALL_NS = 1_000_000_000


class Timed(Protocol):
    def next_deadline_ns(self) -> int | None: ...

    def on_deadline(self, now_ns: int) -> None: ...


class NodeLoop:
    """The timer loop of one node (thread ``fg-loop-<node>``), started with the first
    object and stopped by ``close``."""

    def __init__(self, name: str, on_stall: Callable[[int], None] | None = None) -> None:
        self._name = name
        self._on_stall = on_stall
        self._cond = threading.Condition()
        self._objects: list[Timed] = []
        self._closed = False
        self._thread: threading.Thread | None = None
        # When the loop will look again (monotonic ns); read without the lock by ``poke``.
        self.wake_at_ns = 0
        self._dirty = False

    def add(self, obj: Timed) -> None:
        with self._cond:
            self._objects.append(obj)
            if self._thread is None and not self._closed:
                self._thread = threading.Thread(
                    target=self._run, daemon=True, name=f"fg-loop-{self._name}"
                )
                self._thread.start()
            self._cond.notify()

    def remove(self, obj: Timed) -> None:
        with self._cond:
            if obj in self._objects:
                self._objects.remove(obj)

    def poke(self, deadline_ns: int) -> None:
        """An object's deadline is now ``deadline_ns``: wake the loop if it sleeps past it
        (or is looking at the deadlines right now and may have read the old one)."""
        if deadline_ns < self.wake_at_ns or self.wake_at_ns == 0:
            with self._cond:
                self._dirty = True
                self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                if self._closed:
                    return
                self._dirty = False
                objects = list(self._objects)
            now = time.monotonic_ns()
            wake = now + _MAX_SLEEP_NS
            for obj in objects:
                try:
                    deadline = obj.next_deadline_ns()
                    if deadline is not None and deadline <= now:
                        obj.on_deadline(now)
                        deadline = obj.next_deadline_ns()
                except Exception:  # one object's failure must not stop the others' timers
                    log.exception("%s: timer of %r failed", self._name, obj)
                    continue
                if deadline is not None:
                    wake = min(wake, max(deadline, now + 100_000))
            with self._cond:
                if self._closed:
                    return
                timeout = (wake - time.monotonic_ns()) / 1e9
                if timeout > 0 and not self._dirty:
                    self.wake_at_ns = wake
                    self._cond.wait(timeout)
                self.wake_at_ns = 0
            late = time.monotonic_ns() - wake
            if late > STALL_NS and self._on_stall is not None:
                self._on_stall(late)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._objects.clear()
            self._cond.notify()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=6.0)  # a blocked put gives up after 5 s
