"""One executor per node, as rclpy's: the one thread that waits, and what it runs.

Zenoh's threads only append to bounded per-object inboxes (``_inbox``) and ``signal`` the
object here; the executor thread (``fg-exec-<node>``) is the only waiter. Each turn it

1. takes the objects that were signalled, in the order they were, and lets each handle a
   *bounded* batch of its input (``run_ready(budget)``); one that has more left is signalled
   again, behind the others, so a flooded inbox cannot starve the rest (round robin);
2. runs every timer (``Node.every``) and one-shot deadline (``Node.at``) that is due;
3. runs every object whose own deadline is due (``Timed``: resends, delayed acks).

It then sleeps until the next signal or the earliest deadline of all of them. Handlers
registered by services (``Node.on`` / ``every`` / ``at``) run here, on this one thread.

A handler running here that blocks on framegate (``Subscription.take``, ``Producer.put``
with ``wait_s``, waiting for a registration) does not wait for the executor, which is
itself: it processes its own object's input inline, in the same bounded batches, and waits
on this executor's condition for that object's next signal (``wait_for``). Other objects'
input waits in their bounded inboxes until the handler returns.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Protocol

log = logging.getLogger("framegate.middleware")

# Input items an object handles per turn before the next ready object gets its turn.
BUDGET = 64
# The executor re-reads every object's deadline at least this often (a deadline moved
# earlier without ``poke`` costs at most this).
_MAX_SLEEP_NS = 1_000_000_000
# Waking this much later than planned means the process did not run (SIGSTOP, a debugger,
# a suspended VM): peers may have dropped it (see ``on_stall``).
STALL_NS = 1_000_000_000
# A periodic timer that fell this many periods behind skips the missed runs (no burst).
_MAX_CATCH_UP = 1


def remaining_s(deadline: float) -> float:
    """Seconds left until ``deadline`` (``time.monotonic``), never negative."""
    return max(0.0, deadline - time.monotonic())


class Source(Protocol):
    """An object with an inbox: ``scheduled`` is the executor's (guarded by its lock)."""

    scheduled: bool

    def run_ready(self, budget: int) -> bool:
        """Handle at most ``budget`` input items; True if more are waiting."""
        ...


class Timed(Protocol):
    def next_deadline_ns(self) -> int | None: ...

    def on_deadline(self, now_ns: int) -> None: ...


class Timer:
    """A handle on a timer or deadline registered with ``Node.every`` / ``Node.at``."""

    def __init__(
        self, executor: Executor, fn: Callable[[int], object], at_ns: int, period_ns: int
    ) -> None:
        self._executor = executor
        self.fn = fn
        self.at_ns = at_ns
        self.period_ns = period_ns  # 0: one-shot
        self.cancelled = False

    def cancel(self) -> None:
        """Stop it; a run already started finishes. Safe from any thread, and repeatable."""
        self.cancelled = True


class Wake:
    """How new input on one object reaches whoever needs it now, at the cost of one wake-up.

    The executor when it owns the object's input (a ``Node.on`` handler: ``executor_owned``)
    or a handler on it waits for the object (``Executor.wait_for``), or a batch or more waits;
    else the callers
    blocked in the object's condition (``take``, a waiting ``put``), which then feed the
    input themselves; else nobody: the input waits in its bounded inbox for the next caller
    that looks (a ``put``, ``info``, ``take``, or the executor at the object's deadline).
    ``threads`` and ``handler_waiting`` are changed under the condition's lock, and set *before*
    the waiter's last look at the inbox, so an append that the look missed sees them.
    """

    def __init__(
        self,
        source: Source,
        cond: threading.Condition,
        executor: Executor,
        backlog: Callable[[], int],
    ) -> None:
        self._source = source
        self._cond = cond
        self._executor = executor
        self._backlog = backlog
        self.executor_owned = False
        self.threads = 0  # callers blocked in the condition
        self.handler_waiting = False  # a handler on the executor waits for this object

    def signal(self) -> None:
        """(Zenoh's thread, after appending to the inbox) A backlog of a batch or more is
        the executor's to work off in any case (a flood must not wait for the next caller:
        it would push honest input out of the bounded inbox meanwhile)."""
        if self.executor_owned or self.handler_waiting or self._backlog() >= BUDGET:
            if not self._source.scheduled:
                self._executor.signal(self._source)
        elif self.threads:
            with self._cond:
                self._cond.notify_all()

    def wait(self, ready: Callable[[], bool], timeout_s: float) -> bool:
        """(holding the condition's lock) True if ``ready()`` (which feeds the inbox and
        looks) is; else wait up to ``timeout_s`` for news and return False (look again)."""
        executor = self._executor
        on_executor = executor.on_thread
        if on_executor:
            self.handler_waiting = True
        else:
            self.threads += 1
        try:
            if ready():
                return True
            if on_executor:
                self._cond.release()
                try:
                    executor.wait_for(self._source, timeout_s)
                finally:
                    self._cond.acquire()
            else:
                self._cond.wait(timeout_s)
            return False
        finally:
            if on_executor:
                self.handler_waiting = False
            else:
                self.threads -= 1

    def left_over(self, waiting: int) -> None:
        """(after a handler waited inline) Input it claimed but left is the executor's."""
        if waiting and self._executor.on_thread:
            self._executor.signal(self._source)


class Executor:
    """The executor of one node, started on first use and stopped by ``close``.

    ``_cond`` guards the ready queue, every source's ``scheduled`` flag, the timer heap, the
    timed objects and ``_sleeping``. Nothing runs under it but bookkeeping: objects handle
    their input and handlers run with it released.
    """

    def __init__(self, name: str, on_stall: Callable[[int], None] | None = None) -> None:
        self.name = name
        self._on_stall = on_stall
        self._cond = threading.Condition()
        self._ready: deque[Source] = deque()
        self._timers: list[tuple[int, int, Timer]] = []
        self._seq = itertools.count()
        self._timed: list[Timed] = []
        self._closed = False
        self._sleeping = False
        self._wake_at_ns = 0
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None  # the first handler failure, for ``spin``

    # -- any thread ----------------------------------------------------------------------------
    def signal(self, source: Source) -> None:
        """``source`` has input (called by Zenoh's threads after appending to its inbox)."""
        with self._cond:
            if source.scheduled:
                return
            source.scheduled = True
            self._ready.append(source)
            self._cond.notify_all()  # the executor, or a handler waiting in ``wait_for``

    def add(self, obj: Timed) -> None:
        with self._cond:
            self._timed.append(obj)
            self._start()
            self._cond.notify_all()

    def remove(self, obj: Timed) -> None:
        with self._cond:
            if obj in self._timed:
                self._timed.remove(obj)

    def poke(self, deadline_ns: int) -> None:
        """An object's deadline is now ``deadline_ns``: wake the executor unless it sleeps
        and wakes in time anyway. (Not sleeping, it may be reading the deadlines under its
        lock right now: the lock then waits for its sleep, and the notify ends that sleep.)"""
        if self._sleeping and deadline_ns >= self._wake_at_ns:
            return
        with self._cond:
            self._cond.notify_all()

    def schedule(self, fn: Callable[[int], object], at_ns: int, period_ns: int = 0) -> Timer:
        timer = Timer(self, fn, at_ns, period_ns)
        with self._cond:
            heapq.heappush(self._timers, (at_ns, next(self._seq), timer))
            self._start()
            self._cond.notify_all()
        return timer

    @property
    def on_thread(self) -> bool:
        """Whether the caller is the executor thread (a handler)."""
        return self._thread is threading.current_thread()

    def wait_for(self, source: Source, timeout_s: float) -> None:
        """(the executor thread, inside a handler) Wait up to ``timeout_s`` for ``source``
        to be signalled; its input is then the caller's to handle inline."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            # Claimed: the caller handles this source's input itself from here on.
            if source.scheduled:
                source.scheduled = False
                if source in self._ready:
                    self._ready.remove(source)
                return
            while not source.scheduled and not self._closed:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return
                self._cond.wait(remaining)
            if source.scheduled:
                source.scheduled = False
                if source in self._ready:
                    self._ready.remove(source)

    # -- the executor thread ---------------------------------------------------------------------
    def _start(self) -> None:
        """(under _cond)"""
        if self._thread is None and not self._closed:
            self._thread = threading.Thread(
                target=self._run, daemon=True, name=f"fg-exec-{self.name}"
            )
            self._thread.start()

    def _run(self) -> None:
        planned = 0
        while True:
            with self._cond:
                if self._closed:
                    return
                if not self._ready:
                    wake = self._next_wake_ns()
                    timeout = (wake - time.monotonic_ns()) / 1e9
                    if timeout > 0:
                        self._wake_at_ns = wake
                        self._sleeping = True
                        self._cond.wait(timeout)
                        self._sleeping = False
                        planned = wake
                if self._closed:
                    return
                ready = list(self._ready)
                self._ready.clear()
                for source in ready:
                    source.scheduled = False
            now = time.monotonic_ns()
            if planned and now - planned > STALL_NS and self._on_stall is not None:
                self._on_stall(now - planned)
            planned = 0
            for source in ready:
                try:
                    more = source.run_ready(BUDGET)
                except Exception as exc:
                    self._failed(exc, f"input of {source!r}")
                    more = False
                if more:
                    self.signal(source)
            self._run_timers()
            self._run_timed()

    def _next_wake_ns(self) -> int:
        """(under _cond) The earliest deadline of every timer and timed object."""
        now = time.monotonic_ns()
        wake = now + _MAX_SLEEP_NS
        if self._timers:
            wake = min(wake, self._timers[0][0])
        for obj in self._timed:
            try:
                deadline = obj.next_deadline_ns()
            except Exception:
                log.exception("%s: deadline of %r failed", self.name, obj)
                continue
            if deadline is not None:
                wake = min(wake, deadline)
        return wake

    def _run_timers(self) -> None:
        now = time.monotonic_ns()
        while True:
            with self._cond:
                if not self._timers or self._timers[0][0] > now or self._closed:
                    return
                _, _, timer = heapq.heappop(self._timers)
                if timer.cancelled:
                    continue
                if timer.period_ns:
                    nxt = timer.at_ns + timer.period_ns
                    if nxt <= now - _MAX_CATCH_UP * timer.period_ns:
                        nxt = now + timer.period_ns  # fell behind: skip, never burst
                    timer.at_ns = nxt
                    heapq.heappush(self._timers, (nxt, next(self._seq), timer))
            try:
                timer.fn(now)
            except Exception as exc:
                self._failed(exc, f"timer {timer.fn!r}")

    def _run_timed(self) -> None:
        with self._cond:
            objects = list(self._timed)
        now = time.monotonic_ns()
        for obj in objects:
            try:
                deadline = obj.next_deadline_ns()
                if deadline is not None and deadline <= now:
                    obj.on_deadline(now)
            except Exception:  # one object's failure must not stop the others' timers
                log.exception("%s: timer of %r failed", self.name, obj)

    def _failed(self, exc: Exception, what: str) -> None:
        log.error("%s: %s failed: %s", self.name, what, exc, exc_info=exc)
        if self.error is None:
            self.error = exc

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._timed.clear()
            self._timers.clear()
            self._ready.clear()
            self._cond.notify_all()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=6.0)  # a handler's blocked put gives up after its wait
