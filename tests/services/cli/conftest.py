"""Running ``python -m services.cli`` as real subprocesses, and a live service to point it at."""

from __future__ import annotations

import json
import queue
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import pytest

from middleware import NetworkConfig, Node, Producer
from services.lib.messages import frame_metadata_of
from services.lib.quality import Exposure
from tests.conftest import REPO, child_env
from tests.helpers.timing import scaled

WIDTH, HEIGHT = 8, 6
MS = 1_000_000
# Generous: a CLI process imports every command module, which takes seconds on a loaded host.
TIMEOUT_S = 180.0
# How long a command may wait to discover the service (3 s by default) on a loaded host: a
# deadline, scaled as every other; only a command whose service is missing waits it out.
# 20 s was too short with two CPU hogs beside the suite (hz found no 'cam' in 35 s).
DISCOVERY_TIMEOUT_S = scaled(60.0)
# The --timeout of a command looking for what the test knows is missing (a misspelt buffer of
# a live service, a service in another namespace): such a command waits all of it, so
# DISCOVERY_TIMEOUT_S there cost a minute a command. It must still meet the live service
# first (for its did-you-mean or its other namespace): the command's clock starts once its
# session is open, and meeting a service on loopback takes well under a second.
ABSENCE_TIMEOUT_S = scaled(15.0)


def frame_metadata(t: int, frame_id: int) -> bytes:
    """A mono8 frame exposed 2 ms from ``t``, with no camera model (the product's
    ``frame_metadata_of``, the one place that writes frame metadata)."""
    return frame_metadata_of(frame_id, Exposure(t, 2 * MS), "mono8", WIDTH, HEIGHT, None)


def frame_payload(frame_id: int) -> bytes:
    return bytes((frame_id * 7 + i) % 256 for i in range(WIDTH * HEIGHT))


def put_frame(producer: Producer, t: int, frame_id: int) -> None:
    producer.put(t, frame_payload(frame_id), frame_metadata(t, frame_id))


@dataclass
class Result:
    args: list[str]
    returncode: int
    stdout: str
    stderr: str

    def json(self) -> Any:
        assert self.returncode == 0, self.describe()
        return json.loads(self.stdout)

    def json_lines(self) -> list[dict[str, Any]]:
        assert self.returncode == 0, self.describe()
        return [json.loads(line) for line in self.stdout.splitlines() if line.strip()]

    def describe(self) -> str:
        return f"{self.args} -> {self.returncode}\nstdout: {self.stdout}\nstderr: {self.stderr}"


def _command(args: list[str]) -> list[str]:
    return [sys.executable, "-m", "services.cli", *args]


# A command that saw no live service at all, while the test keeps one live, ran while that
# service's session had lost its lease (a starved test process: 9.9 s without CPU at load 33
# on 2 cores): it is run again, at most this many times.
_NOTHING_LIVE = "live services: none"
_NOTHING_LIVE_RETRIES = 2


class Cli:
    """Runs CLI commands against one endpoint (``--connect`` is added unless given)."""

    def __init__(self, endpoint: str) -> None:
        self.endpoint = endpoint
        self._procs: list[subprocess.Popen[str]] = []

    def _args(self, args: tuple[str, ...]) -> list[str]:
        out = list(args)
        if "--connect" not in out and "--listen" not in out:
            out += ["--connect", self.endpoint]
        if out[0] != "play" and "--timeout" not in out:
            out += ["--timeout", str(DISCOVERY_TIMEOUT_S)]
        return out

    def run(self, *args: str, timeout_s: float = TIMEOUT_S) -> Result:
        return self.run_many([args], timeout_s=timeout_s)[0]

    def run_many(
        self, commands: list[tuple[str, ...]], timeout_s: float = TIMEOUT_S
    ) -> list[Result]:
        """Run several commands at once (each is a slow-starting Python process)."""
        procs = [
            (self._args(c), self.start(*c, stdin=subprocess.DEVNULL, connect=True))
            for c in commands
        ]
        results = []
        for args, proc in procs:
            out, err = proc.communicate(timeout=scaled(timeout_s))
            result = Result(args, proc.returncode, out, err)
            for _ in range(_NOTHING_LIVE_RETRIES):
                if not result.stderr.rstrip().endswith(_NOTHING_LIVE):
                    break
                again = self.start(*args, stdin=subprocess.DEVNULL, connect=False)
                out, err = again.communicate(timeout=scaled(timeout_s))
                result = Result(args, again.returncode, out, err)
            results.append(result)
        return results

    def start(self, *args: str, stdin: Any = subprocess.DEVNULL, connect: bool = True) -> Any:
        """A long-running command (watch, record, play); stopped at teardown."""
        command = _command(self._args(args) if connect else list(args))
        proc = subprocess.Popen(
            command,
            stdin=stdin,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=REPO,
            env=child_env(),
        )
        self._procs.append(proc)
        return proc

    def close(self) -> None:
        for proc in self._procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


class LineReader:
    """Reads a process's stdout lines with a deadline (readline alone would block forever)."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self._lines: queue.Queue[str | None] = queue.Queue()
        self.seen: list[str] = []
        self._proc = proc
        assert proc.stdout is not None
        stream = proc.stdout

        def pump() -> None:
            for line in stream:
                self._lines.put(line)
            self._lines.put(None)

        threading.Thread(target=pump, daemon=True).start()

    def json_until(self, predicate: Callable[[dict[str, Any]], bool], timeout_s: float) -> Any:
        deadline = time.monotonic() + scaled(timeout_s)
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise AssertionError(f"timed out; output so far: {self.seen}")
            try:
                line = self._lines.get(timeout=remaining)
            except queue.Empty:
                continue
            if line is None:
                raise AssertionError(f"process ended; {self._ending()}; output: {self.seen}")
            self.seen.append(line)
            if line.strip():
                event = json.loads(line)
                if predicate(event):
                    return event

    def _ending(self) -> str:
        """How the process ended: exit code and what it said on stderr (why it ended)."""
        try:
            code = self._proc.wait(timeout=scaled(10))
        except subprocess.TimeoutExpired:
            return "stdout closed, process still running"
        err = self._proc.stderr.read() if self._proc.stderr is not None else ""
        return f"exit {code}, stderr: {err.strip()!r}"


@pytest.fixture
def cli(endpoint: str) -> Iterator[Cli]:
    runner = Cli(endpoint)
    yield runner
    runner.close()


@pytest.fixture
def service(listen_net: NetworkConfig) -> Iterator[Node]:
    """A live service named ``cam`` listening on the test's endpoint."""
    with Node("cam", listen_net) as node:
        yield node
