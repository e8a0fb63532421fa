"""What every benchmark worker role shares: the JSON-line conversation, pacing, profiling.

A role (``_raw``, ``_fg``) prints one JSON line ``{"ready": true, ...}`` with ``reply`` and then
answers JSON-line commands from stdin with ``serve``, one JSON line each, until
``{"op": "exit"}`` or end of input. With ``FRAMEGATE_BENCH_PROFILE=DIR`` in the environment
the workers' Python threads are profiled (see ``profiled``).
"""

from __future__ import annotations

import cProfile
import json
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

PROFILE_ENV = "FRAMEGATE_BENCH_PROFILE"

Handler = Callable[[dict[str, Any]], dict[str, Any]]


@contextmanager
def profiled(tag: str) -> Iterator[None]:
    """cProfile the calling thread into ``$FRAMEGATE_BENCH_PROFILE/<tag>-<pid>-<thread>.pstats``.

    Off unless that variable names a directory. cProfile sees Python threads only: time in
    callbacks that Zenoh runs on its own threads shows up in no profile.
    """
    directory = os.environ.get(PROFILE_ENV)
    if not directory:
        yield
        return
    profiler = cProfile.Profile()
    profiler.enable()
    try:
        yield
    finally:
        profiler.disable()
        name = f"{tag}-{os.getpid()}-{threading.current_thread().name}.pstats"
        profiler.dump_stats(str(Path(directory) / name))


def reply(**fields: Any) -> None:
    """One JSON line to the parent."""
    sys.stdout.write(json.dumps(fields) + "\n")
    sys.stdout.flush()


def serve(handlers: dict[str, Handler]) -> None:
    """Answer commands until ``exit`` or end of input; a failing command answers ``error``."""
    for line in sys.stdin:
        if not line.strip():
            continue
        command = json.loads(line)
        op = command.pop("op", None)
        if op == "exit":
            reply(ok=True)
            return
        handler = handlers.get(str(op))
        if handler is None:
            reply(error=f"unknown command {op!r}; this worker knows {sorted(handlers)}")
            continue
        try:
            result = handler(command)
        except Exception as exc:  # the parent decides; the worker keeps serving
            reply(error=f"{op}: {type(exc).__name__}: {exc}")
        else:
            reply(**result)


def serve_while_consuming(
    consumers: Sequence[Callable[[], None]], stop: threading.Event, handlers: dict[str, Handler]
) -> None:
    """Run each consumer on a daemon thread, say ready, serve ``handlers``; then set
    ``stop`` and give the consumers 2 s to end (one blocked in a take is left behind)."""
    threads = [threading.Thread(target=consume, daemon=True) for consume in consumers]
    for thread in threads:
        thread.start()
    reply(ready=True)
    try:
        serve(handlers)
    finally:
        stop.set()
        for thread in threads:
            thread.join(timeout=2.0)


def paced(seconds: float, interval_s: float) -> list[float]:
    """Tick times (monotonic seconds) every ``interval_s`` for ``seconds``, starting soon."""
    start = time.monotonic() + interval_s
    count = max(1, int(seconds / interval_s))
    return [start + i * interval_s for i in range(count)]


def sleep_until(moment: float) -> None:
    delay = moment - time.monotonic()
    if delay > 0:
        time.sleep(delay)


class Counter:
    """Messages and bytes received so far (written by one thread, read by another)."""

    def __init__(self) -> None:
        self.count = 0
        self.bytes = 0
        self.errors = 0

    def mark(self, _command: dict[str, Any]) -> dict[str, Any]:
        return {
            "t_ns": time.monotonic_ns(),
            "count": self.count,
            "bytes": self.bytes,
            "errors": self.errors,
        }


def round_trips(
    ask: Callable[[], object], seconds: float, interval_s: float, max_count: int
) -> list[float]:
    """Microseconds per ``ask()``: paced every ``interval_s``, or back to back when 0."""
    out: list[float] = []
    if interval_s > 0:
        for tick in paced(seconds, interval_s)[:max_count]:
            sleep_until(tick)
            start = time.perf_counter_ns()
            ask()
            out.append((time.perf_counter_ns() - start) / 1000)
        return out
    end = time.monotonic() + seconds
    while time.monotonic() < end and len(out) < max_count:
        start = time.perf_counter_ns()
        ask()
        out.append((time.perf_counter_ns() - start) / 1000)
    return out


class LatencyLog:
    """Latencies (us) per stream, appended by consuming threads and collected by command."""

    def __init__(self, streams: list[str]) -> None:
        self._cond = threading.Condition()
        self._latencies: dict[str, list[float]] = {name: [] for name in streams}

    def record(self, stream: str, latency_us: float) -> None:
        with self._cond:
            self._latencies[stream].append(latency_us)
            self._cond.notify_all()

    def collect(self, command: dict[str, Any]) -> dict[str, Any]:
        """``{stream, expect, wait_s}`` → the latencies so far, once ``expect`` have come."""
        stream, expect = str(command["stream"]), int(command["expect"])
        deadline = time.monotonic() + float(command.get("wait_s", 10.0))
        with self._cond:
            while len(self._latencies[stream]) < expect and time.monotonic() < deadline:
                self._cond.wait(0.05)
            out, self._latencies[stream] = self._latencies[stream], []
        return {"latencies_us": out}


class RssMeter:
    """A process's resident memory, split in two, sampled by the caller and kept at its
    maximum: ``shared`` is the shared memory mapped here (Linux ``RssShmem``: Zenoh's
    shared-memory pools, this process's own and every local peer's that sent it a large
    message; their pages belong to the pool's owner and are counted once per process that
    maps them), ``private`` is the rest (what this process itself allocated)."""

    def __init__(self) -> None:
        self.private, self.shared = self.read()
        self.start_private, self.start_shared = self.private, self.shared
        self.private_max, self.shared_max = self.private, self.shared
        self.start_total = self.total_max = self.private + self.shared

    @staticmethod
    def read() -> tuple[int, int]:
        """(private, shared) resident bytes now; shared is 0 where /proc is not there."""
        fields: dict[str, int] = {}
        try:
            with open("/proc/self/status", encoding="ascii") as status:
                for line in status:
                    key, _, value = line.partition(":")
                    if key in ("VmRSS", "RssShmem"):
                        fields[key] = int(value.split()[0]) * 1024
        except OSError:
            import psutil

            return psutil.Process().memory_info().rss, 0
        return fields["VmRSS"] - fields.get("RssShmem", 0), fields.get("RssShmem", 0)

    def sample(self) -> None:
        self.private, self.shared = self.read()
        self.private_max = max(self.private_max, self.private)
        self.shared_max = max(self.shared_max, self.shared)
        self.total_max = max(self.total_max, self.private + self.shared)
