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
from collections.abc import Callable, Iterator
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
