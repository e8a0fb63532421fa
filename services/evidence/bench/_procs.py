"""The parent side of worker processes: start, talk JSON lines, read CPU time, always stop.

Workers are separate OS processes (``python -m services.evidence.bench._worker``) on loopback, each
pair on its own free port with multicast scouting off. A worker that does not answer within
its deadline raises ``BenchError`` naming the role and the tail of its stderr.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import subprocess
import sys
import threading
import time
from collections import deque
from pathlib import Path
from types import TracebackType
from typing import Any

import psutil

from middleware import FramegateError

_REPO = Path(__file__).resolve().parents[2]


class BenchError(FramegateError):
    """A benchmark could not run: a worker failed, hung or answered nonsense."""


def free_endpoint() -> str:
    """``tcp/127.0.0.1:<port>`` with a port nobody listens on right now."""
    from services.launch import free_port  # not at import: workers import this module

    return f"tcp/127.0.0.1:{free_port()}"


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(_REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env["PYTHONUNBUFFERED"] = "1"
    return env


class Worker:
    """One worker process. Construct through ``WorkerGroup.start``."""

    def __init__(self, role: str, params: dict[str, Any]) -> None:
        self.role = role
        self._lines: queue.Queue[str | None] = queue.Queue()
        self._stderr: deque[str] = deque(maxlen=30)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "services.evidence.bench._worker", role, json.dumps(params)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=str(_REPO),  # ``-m`` puts the cwd first on sys.path: make it this checkout
            env=_env(),
        )
        self._ps = psutil.Process(self.proc.pid)
        self.ready: dict[str, Any] = {}
        threading.Thread(target=self._pump_stdout, daemon=True).start()
        threading.Thread(target=self._pump_stderr, daemon=True).start()

    def _pump_stdout(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if line.startswith("{"):
                self._lines.put(line)
            else:  # stray output from a library is kept for error messages
                self._stderr.append(line.rstrip())
        self._lines.put(None)

    def _pump_stderr(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self._stderr.append(line.rstrip())

    @property
    def pid(self) -> int:
        return self.proc.pid

    def _fail(self, what: str) -> BenchError:
        tail = " | ".join(list(self._stderr)[-8:]) or "(no output)"
        return BenchError(f"{self.role} worker (pid {self.pid}) {what}; its stderr: {tail}")

    def recv(self, timeout_s: float) -> dict[str, Any]:
        """The next answer; BenchError on timeout, exit or an ``error`` answer."""
        try:
            line = self._lines.get(timeout=timeout_s)
        except queue.Empty:
            raise self._fail(f"did not answer within {timeout_s:.0f} s") from None
        if line is None:
            raise self._fail(f"exited with code {self.proc.wait()}")
        answer: dict[str, Any] = json.loads(line)
        if "error" in answer:
            raise self._fail(f"failed: {answer['error']}")
        return answer

    def send(self, op: str, **fields: Any) -> None:
        assert self.proc.stdin is not None
        try:
            self.proc.stdin.write(json.dumps({"op": op, **fields}) + "\n")
            self.proc.stdin.flush()
        except OSError as exc:
            raise self._fail(f"cannot take command {op!r}: {exc}") from exc

    def call(self, op: str, timeout_s: float = 30.0, **fields: Any) -> dict[str, Any]:
        self.send(op, **fields)
        return self.recv(timeout_s)

    def cpu_s(self) -> float:
        """User + system CPU seconds this process has used so far (all threads)."""
        times = self._ps.cpu_times()
        return float(times.user + times.system)

    def wakeups(self) -> int:
        """Times this process's threads have slept and been woken so far (voluntary context
        switches, summed over its threads; Linux's /proc, 0 elsewhere). Each is a hand-off
        between threads or a wait for the network: what an element costs beyond its own
        work, counted the same on a loaded machine, where CPU time per wake-up is not."""
        total = 0
        for status in Path(f"/proc/{self.proc.pid}/task").glob("*/status"):
            with contextlib.suppress(OSError, ValueError):
                for line in status.read_text().splitlines():
                    if line.startswith("voluntary_ctxt_switches:"):
                        total += int(line.split()[1])
        return total

    def request_exit(self) -> None:
        """Ask the worker to exit (it closes its session first); no waiting."""
        if self.proc.poll() is None:
            with contextlib.suppress(BenchError):  # already gone: finish() reaps it
                self.send("exit")

    def finish(self, deadline: float) -> None:
        """Wait until ``deadline`` (monotonic) for the exit, then terminate, then kill:
        never leave a worker behind."""
        try:
            self.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            self.proc.terminate()  # the worker's SIGTERM handler still closes its session
            try:
                self.proc.wait(timeout=2.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        for stream in (self.proc.stdin, self.proc.stdout, self.proc.stderr):
            if stream is not None:
                stream.close()

    def close(self, grace_s: float = 5.0) -> None:
        """Ask politely, then terminate, then kill."""
        self.request_exit()
        self.finish(time.monotonic() + grace_s)


class WorkerGroup:
    """Workers started together and stopped together (use as a context manager)."""

    def __init__(self) -> None:
        self._workers: list[Worker] = []

    def start(self, role: str, params: dict[str, Any]) -> Worker:
        worker = Worker(role, params)
        self._workers.append(worker)
        return worker

    def wait_ready(self, timeout_s: float = 180.0) -> None:
        """Wait for every started worker's ready line (they start in parallel).

        Generous by default: on a shared 2-core machine under load, starting Python with
        Zenoh takes tens of seconds per process.
        """
        deadline = time.monotonic() + timeout_s
        for worker in self._workers:
            if not worker.ready:
                worker.ready = worker.recv(max(0.1, deadline - time.monotonic()))

    def close(self, grace_s: float = 5.0) -> None:
        """Ask every worker to exit at once, then wait for all within one ``grace_s``."""
        workers = list(reversed(self._workers))
        self._workers.clear()
        for worker in workers:
            worker.request_exit()
        deadline = time.monotonic() + grace_s
        for worker in workers:
            worker.finish(deadline)

    def __enter__(self) -> WorkerGroup:
        return self

    def __exit__(
        self,
        _type: type[BaseException] | None,
        _value: BaseException | None,
        _tb: TracebackType | None,
    ) -> None:
        # Interrupted (Ctrl-C, SIGTERM): the workers got the signal too or are told to
        # exit now; do not wait long for them.
        self.close(grace_s=1.0 if _type is KeyboardInterrupt else 5.0)
