"""What every service process shares: logging, a common start time, pacing, shutdown."""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import logging
import os
import queue
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, Protocol, TypeVar

from middleware import ConfigError, FramegateError, NetworkConfig, Node, now_ns

START_AT_ENV = "FRAMEGATE_START_AT_NS"
# Set by the launch supervisor (services/launch/_supervisor.py) for each child it starts.
PARENT_PID_ENV = "FRAMEGATE_PARENT_PID"
PARENT_FD_ENV = "FRAMEGATE_PARENT_FD"
_PR_SET_PDEATHSIG = 1
T = TypeVar("T")
S = TypeVar("S")
# After the parent is gone, how long the service may take to stop by itself.
_ORPHAN_GRACE_S = 1.5


def setup_logging(name: str, level: int = logging.INFO) -> logging.Logger:
    """Plain one-line logs on stderr; the launcher prefixes them with the service name."""
    logging.basicConfig(level=level, format="%(levelname)s %(message)s", force=True)
    return logging.getLogger(f"framegate.{name}")


def start_at_ns(flag_value: int | None) -> int:
    """Wall-clock ns at which replayed time zero happens.

    Camera and gyro replays started by one launch share it (the launcher sets
    FRAMEGATE_START_AT_NS), so their streams stay aligned although they are separate
    processes. Without either, start now.
    """
    if flag_value is not None:
        return flag_value
    raw = os.environ.get(START_AT_ENV)
    if raw:
        try:
            return int(raw)
        except ValueError as exc:
            raise ConfigError(f"{START_AT_ENV} must be integer ns, got {raw!r}") from exc
    return now_ns()


def _wall_minus_monotonic_ns() -> int:
    """The process clock minus the monotonic clock, read as one pair (a thread switch
    between the two readings would make it off by milliseconds)."""
    best = None
    for _ in range(5):
        before = time.monotonic_ns()
        wall = now_ns()
        after = time.monotonic_ns()
        if best is None or after - before < best[0]:
            best = (after - before, wall - (before + after) // 2)
        if after - before < 50_000:
            break
    assert best is not None
    return best[1]


# A change of (process clock - monotonic) smaller than this is reading noise and ignored.
_OFFSET_NOISE_NS = 500_000


class Timeline:
    """Where a replayed source's relative times happen, and how they are stamped.

    Paced by the monotonic clock, stamped by the process clock (``middleware.now_ns``):
    the start instant is converted once, so a step of the system clock changes the stamps
    (a forward step moves them forward at once; a backward one is absorbed by the process
    clock) but never when the next frame or sample is due. Camera and gyro processes on
    one host share the monotonic clock, so their streams stay aligned across a step; a
    source paced by the wall clock instead stalls for the size of a backward step and
    skips everything for the size of a forward one. Stamps strictly increase.
    """

    def __init__(self, start_wall_ns: int) -> None:
        self._offset_ns = _wall_minus_monotonic_ns()
        self._start_mono_ns = start_wall_ns - self._offset_ns
        self._last_ns = 0

    def _base_ns(self) -> int:
        offset = _wall_minus_monotonic_ns()
        if abs(offset - self._offset_ns) > _OFFSET_NOISE_NS:
            self._offset_ns = offset
        return self._start_mono_ns + self._offset_ns

    def stamp_ns(self, rel_ns: int) -> int:
        """The process-clock time of relative time ``rel_ns`` (as the clock reads now)."""
        return self.stamps_ns([rel_ns])[0]

    def stamps_ns(self, rel_ns: list[int]) -> list[int]:
        """``stamp_ns`` of increasing times with one reading of the clocks (a batch); each
        after every stamp given before."""
        base = self._base_ns()
        base = max(base, self._last_ns + 1 - rel_ns[0])
        out = [base + t for t in rel_ns]
        self._last_ns = out[-1]
        return out

    def late_ns(self, rel_ns: int) -> int:
        """How long ago relative time ``rel_ns`` came (negative: still to come)."""
        return time.monotonic_ns() - (self._start_mono_ns + rel_ns)


class Monotonic:
    """Strictly increasing int ns keys from the process clock (for decision records)."""

    def __init__(self) -> None:
        self._last = 0
        self._lock = threading.Lock()

    def next(self) -> int:
        with self._lock:
            self._last = max(self._last + 1, now_ns())
            return self._last


class CallThread:
    """One long-lived thread that runs calls one at a time while the caller waits:
    ``call(work, stop)`` is ``work()``, or None once ``stop`` is set while it runs.

    For slow steps a stop must not wait for (a vision handler inside OpenCV): after a stop
    the call is given ``_WORKER_GRACE_S`` to finish; one still running then is abandoned,
    and the process exits without finalising the interpreter (``_exit_past_workers``): a
    thread that is inside native code (OpenCV) when the interpreter finalises is ended by
    ``pthread_exit``, which unwinds through C++ frames into ``std::terminate`` and aborts
    the process (exit 134 on an ordinary Ctrl-C).

    Every call runs on the same thread, so what one call leaves in per-thread state (a
    thread-local cache, PyTorch's grad mode, a model or connection bound to the thread that
    made it, when an earlier call made it) is there for the next: a new thread per call
    lost it each time.

    Threads: ``name``, a daemon, for the life of the object; ``work`` must not touch Zenoh.
    """

    def __init__(self, name: str) -> None:
        self._calls: queue.SimpleQueue[Callable[[], None] | None] = queue.SimpleQueue()
        self._abandoned = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        with _workers_lock:
            _workers.add(self._thread)
        self._thread.start()

    def _run(self) -> None:
        while (call := self._calls.get()) is not None:
            call()

    def call(self, work: Callable[[], T], stop: threading.Event) -> T | None:
        """``work()`` on this thread (what it raises is raised here), or None once ``stop``
        is set while it runs (then it is abandoned after ``_WORKER_GRACE_S``)."""
        result: list[T] = []
        failure: list[BaseException] = []
        done = threading.Event()

        def target() -> None:
            try:
                result.append(work())
            except BaseException as exc:  # handed back to the caller's thread
                failure.append(exc)
            finally:
                done.set()

        self._calls.put(target)
        while not done.wait(0.05):
            if stop.is_set():
                if not done.wait(_WORKER_GRACE_S):
                    self._abandoned = True
                return None
        if failure:
            raise failure[0]
        return result[0]

    def close(self) -> None:
        """End the thread once its call returns; a call abandoned after a stop is not
        waited for again (its grace is spent), and keeps the process from finalising."""
        self._calls.put(None)
        self._thread.join(0 if self._abandoned else _WORKER_GRACE_S)
        if not self._thread.is_alive():
            with _workers_lock:
                _workers.discard(self._thread)


@dataclass(frozen=True, slots=True)
class Outcome(Generic[T]):
    """What a ``Worker`` step came to: its value, or what it raised."""

    value: T | None = None
    error: BaseException | None = None


_Step = tuple[Callable[[], Any], Callable[["Outcome[Any]"], object]]


class Worker:
    """One long-lived thread for a service's slow steps (a simulator's render, a dataset's
    read): ``submit(work, then)`` runs ``work()`` there and hands its ``Outcome`` to
    ``then`` on the node's executor, so the executor never waits for a step (the
    subscribers' acks and the deadlines go on meanwhile) and no thread is made per step.
    Steps run one at a time, in order. A step still inside native code when the service
    stops is abandoned (``close``): the process then ends without finalising the
    interpreter (``_exit_past_workers``).

    Threads: the worker runs only ``work`` (which must not touch Zenoh) and hands the
    outcome over with ``Node.at``; ``then`` runs on the executor."""

    def __init__(self, name: str, node: Node) -> None:
        self._node = node
        self._steps: queue.SimpleQueue[_Step | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        with _workers_lock:
            _workers.add(self._thread)
        self._thread.start()

    def submit(self, work: Callable[[], T], then: Callable[[Outcome[T]], object]) -> None:
        self._steps.put((work, then))

    def _run(self) -> None:
        while (step := self._steps.get()) is not None:
            work, then = step
            try:
                outcome: Outcome[Any] = Outcome(work())
            except BaseException as exc:  # handed to ``then``, on the executor
                outcome = Outcome(error=exc)
            with contextlib.suppress(FramegateError):  # the node closed meanwhile: a stop
                self._node.at(time.monotonic_ns(), _handing(then, outcome))

    def close(self) -> None:
        """Stop after the current step; one still running after ``_WORKER_GRACE_S`` is
        abandoned (see the class doc)."""
        self._steps.put(None)
        self._thread.join(_WORKER_GRACE_S)
        if not self._thread.is_alive():
            with _workers_lock:
                _workers.discard(self._thread)


def _handing(then: Callable[[Outcome[T]], object], outcome: Outcome[T]) -> Callable[[int], object]:
    """A deadline handler that hands ``outcome`` to ``then``."""
    return lambda _now_ns: then(outcome)


# How long a stopped service waits for a worker in native code before abandoning it.
_WORKER_GRACE_S = 0.5
_workers: set[threading.Thread] = set()
_workers_lock = threading.Lock()


def _exit_past_workers() -> None:
    """At exit: if a worker is still inside native code, end the process here.

    Runs as the last ``atexit`` hook, after the service has returned and closed its
    session, before the interpreter finalises. The code is 0 (a worker is only abandoned
    after a requested stop), or 1 after an uncaught exception.
    """
    with _workers_lock:
        alive = [t for t in _workers if t.is_alive()]
    if not alive:
        return
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(1 if getattr(sys, "last_value", None) is not None else 0)


# Registered at import, so it runs after every hook registered later (atexit is LIFO).
atexit.register(_exit_past_workers)


class Pump(Protocol):
    """What a source service runs on its node: a deadline handler that puts what is due and
    sets the next deadline itself, the summary logged when the service ends, and its close
    (a worker to stop)."""

    def on_time(self, now: int) -> None: ...

    def summary(self) -> str: ...

    def close(self) -> None: ...


def run_source(
    name: str,
    network: NetworkConfig,
    stop: threading.Event,
    open_source: Callable[[], S],
    pump: Callable[[Node, S, logging.Logger], Pump],
) -> int:
    """A source service's life (camera, gyro): open the source, then the node; ``pump``
    offers the buffers and returns the pump, which runs on the node's executor from now
    until ``stop`` is set (or Ctrl-C); its summary is logged last. Exit code 0.

    The source opens before the node because opening may take seconds (a simulator's first
    frame, a device): a stop meanwhile starts nothing, and no peer sees a service whose
    buffers stay empty.
    """
    log = setup_logging(name)
    try:
        source = open_source()
    except FramegateError:
        if stop.is_set():  # a stop while the source was opening (a render: RenderStopped)
            return 0
        raise
    if stop.is_set():  # interrupted while the source was opening
        return 0
    with Node(name, network) as node:
        running = pump(node, source, log)
        node.at(time.monotonic_ns(), running.on_time)
        try:
            with contextlib.suppress(KeyboardInterrupt):
                node.spin(stop)
        finally:
            running.close()
        log.info("%s", running.summary())
    return 0


def exit_with_parent(stop: threading.Event) -> None:
    """End this process with the supervisor that started it, however the supervisor ends.

    On Linux the kernel kills this process (SIGKILL) when the parent dies. Not SIGTERM: a
    service busy in C code that holds the GIL (an FFT, OpenCV) runs no Python handler until it
    returns, which measured over 5 s on a loaded machine; and with the parent gone there is
    nothing left to stop gracefully for (peers see the liveliness token vanish at once).
    A supervisor that stops normally stops its children first, so this is only the abnormal
    path. Everywhere, a thread also waits for end-of-file on the pipe whose write end only
    the parent holds, then sets ``stop`` and, if the service has not ended
    ``_ORPHAN_GRACE_S`` later, exits hard. A process started by hand (no
    ``FRAMEGATE_PARENT_PID``) is left alone.

    Threads: one daemon thread blocked on the pipe; it only sets ``stop`` or exits.
    """
    parent = os.environ.pop(PARENT_PID_ENV, None)
    fd_text = os.environ.pop(PARENT_FD_ENV, None)
    if parent is None:
        return
    if sys.platform == "linux":
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    # The parent may have died before the request above took effect.
    if os.getppid() != int(parent):
        stop.set()
    if fd_text is None:
        return
    fd = int(fd_text)

    def watch() -> None:
        with contextlib.suppress(OSError):
            while os.read(fd, 1):
                pass
        # The hard exit must not wait on anything: ``stop.set()`` takes the event's lock,
        # which a stuck main thread could hold, so it is asked for on a thread of its own.
        threading.Thread(target=stop.set, name="orphan-stop", daemon=True).start()
        time.sleep(_ORPHAN_GRACE_S)
        os._exit(1)

    threading.Thread(target=watch, name="parent-watchdog", daemon=True).start()
