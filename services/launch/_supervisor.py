"""Start service processes, prefix and colour their logs, restart crashes, stop cleanly.

Each service is its own OS process (``python -m services.cli run TYPE ...``). A process
that exits while it should run is restarted at once the first time, then with exponential
backoff (0.2 s doubling to 10 s) while it keeps dying young; one that ran 10 s is
restarted at once again. ``stop`` sends
SIGTERM, waits up to 1.5 s, then SIGKILLs.

A process that dies by a signal (an abort in native code, a kill by someone else) is said
so by name, and counted in ``signal_deaths``: a launcher reports it and exits non-zero. The
SIGKILL ``stop`` itself sends to a process that would not stop is not counted. A process
that exits with ``EXIT_NAME_TAKEN`` (another live instance offers its service name) is tried
again only every ``NAME_TAKEN_RETRY_S`` (10 s), said once: it cannot start while that one
lives, and restarting at once would storm the host; but the other instance may go (a camera
run by hand for a test, a peer answering in its name at the instant of a restart), and a
service given up for good stayed down for the rest of the launch after it had.

No orphans: every child gets ``FRAMEGATE_PARENT_PID`` and the read end of a pipe whose
write end only this process holds (``FRAMEGATE_PARENT_FD``). The child
(services/nodes/_runtime.exit_with_parent) asks Linux for SIGKILL when its parent dies and
watches the pipe, whose end-of-file means the same anywhere; so the services end with
their launcher however it ends, SIGKILL included. Linux sends that signal when the
*thread* that started the child ends: start, poll and run a Supervisor from a thread that
outlives it (the main thread).
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import IO

from middleware import EXIT_NAME_TAKEN

_COLOURS = ("36", "33", "35", "32", "34", "31", "96", "93")
_BACKOFF_START_S = 0.2
_BACKOFF_MAX_S = 10.0
# A process that ran this long is restarted at once when it dies; shorter lives back off.
HEALTHY_AFTER_S = 10.0
# How often a service whose name another instance held is tried again (see the module).
NAME_TAKEN_RETRY_S = 10.0
_POLL_S = 0.05
PARENT_PID_ENV = "FRAMEGATE_PARENT_PID"
PARENT_FD_ENV = "FRAMEGATE_PARENT_FD"
_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@dataclass(frozen=True, slots=True)
class ProcessSpec:
    """A process to keep running."""

    name: str
    argv: tuple[str, ...]
    restart: bool = True
    env: tuple[tuple[str, str], ...] = ()


@dataclass
class _Running:
    spec: ProcessSpec
    colour: str
    proc: subprocess.Popen[bytes] | None = None
    started_at: float = 0.0
    restarts: int = 0
    backoff_s: float = 0.0  # the first crash restarts at once
    next_start: float = 0.0
    exit_codes: list[int] = field(default_factory=list)
    pump: threading.Thread | None = None
    killed_by_us: bool = False
    exit_recorded: bool = False  # by stop(): a second stop() must not count it again
    up_at_stop: bool = False  # running when stop() came (its earlier deaths were restarted)
    name_taken_said: bool = False  # its name was taken: said once, retried quietly


def exit_text(code: int) -> str:
    """``exited with 3`` or ``died by signal SIGABRT (6)``."""
    if code >= 0:
        return f"exited with {code}"
    try:
        name = signal.Signals(-code).name
    except ValueError:
        name = "an unknown signal"
    return f"died by signal {name} ({-code})"


class Supervisor:
    """Keeps a set of processes running until ``stop``."""

    def __init__(
        self,
        specs: list[ProcessSpec],
        *,
        colour: bool | None = None,
        out: Callable[[str], None] | None = None,
        quiet: bool = False,
        name_taken_retry_s: float = NAME_TAKEN_RETRY_S,
    ) -> None:
        self._name_taken_retry_s = name_taken_retry_s
        use_colour = sys.stdout.isatty() if colour is None else colour
        self._running = [
            _Running(spec, _COLOURS[i % len(_COLOURS)] if use_colour else "")
            for i, spec in enumerate(specs)
        ]
        self._out = out or (lambda line: print(line, flush=True))
        self._quiet = quiet
        self._lock = threading.Lock()
        self._stopping = False
        self._width = max((len(s.name) for s in specs), default=4)
        # The children's lifeline: they hold the read end, only we hold the write end.
        self._lifeline_r, self._lifeline_w = os.pipe()

    def _emit(self, running: _Running, text: str) -> None:
        prefix = f"[{running.spec.name:<{self._width}}]"
        if running.colour:
            prefix = f"\033[{running.colour}m{prefix}\033[0m"
        with self._lock:
            self._out(f"{prefix} {text}")

    def _pump(self, running: _Running, stream: IO[bytes]) -> None:
        for raw in iter(stream.readline, b""):
            if not self._quiet:
                self._emit(running, raw.decode("utf-8", "replace").rstrip())
        stream.close()

    def _start(self, running: _Running) -> None:
        env = dict(os.environ)
        env.update(dict(running.spec.env))
        env.setdefault("PYTHONUNBUFFERED", "1")
        env[PARENT_PID_ENV] = str(os.getpid())
        env[PARENT_FD_ENV] = str(self._lifeline_r)
        # The child starts with SIGINT and SIGTERM blocked (a signal mask survives exec) and
        # unblocks them once its handler is in place (services.cli.main): a stop that comes
        # while it is still starting waits for that handler instead of killing it mid-import.
        blocked = signal.pthread_sigmask(signal.SIG_BLOCK, _STOP_SIGNALS)
        try:
            running.proc = subprocess.Popen(
                list(running.spec.argv),
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                env=env,
                pass_fds=(self._lifeline_r,),
                start_new_session=True,  # Ctrl-C reaches us; we decide how children stop
            )
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
        running.started_at = time.monotonic()
        assert running.proc.stdout is not None
        running.pump = threading.Thread(
            target=self._pump, args=(running, running.proc.stdout), daemon=True
        )
        running.pump.start()

    def start(self) -> None:
        """Start every process."""
        for running in self._running:
            self._start(running)

    def poll(self) -> None:
        """Restart what crashed (called periodically by ``run``)."""
        now = time.monotonic()
        for running in self._running:
            proc = running.proc
            if proc is not None:
                code = proc.poll()
                if code is None or self._stopping:
                    continue
                running.exit_codes.append(code)
                running.proc = None
                if not running.spec.restart:
                    running.next_start = float("inf")
                    self._emit(running, f"{exit_text(code)}; not restarting")
                    continue
                if code == EXIT_NAME_TAKEN:
                    # Another live instance holds the name (a second launcher, a copy of the
                    # deploy file, a peer): restarting at once would only storm the host and
                    # starve it; tried again slowly, it takes over once that one is gone.
                    running.next_start = now + self._name_taken_retry_s
                    if not running.name_taken_said:
                        running.name_taken_said = True
                        self._emit(
                            running,
                            "its service name is taken by another instance; trying again every "
                            f"{self._name_taken_retry_s:g} s until that one is gone",
                        )
                    continue
                running.name_taken_said = False
                if now - running.started_at > HEALTHY_AFTER_S:
                    running.backoff_s = 0.0
                running.next_start = now + running.backoff_s
                self._emit(running, f"{exit_text(code)}; restarting in {running.backoff_s:.1f} s")
                running.backoff_s = min(
                    _BACKOFF_MAX_S, max(_BACKOFF_START_S, running.backoff_s * 2)
                )
            if not self._stopping and now >= running.next_start:
                running.restarts += 1
                if not running.name_taken_said:  # its slow retries were said once
                    self._emit(running, f"restarting (restart {running.restarts})")
                self._start(running)

    def run(
        self,
        duration_s: float | None = None,
        on_tick: Callable[[], None] | None = None,
        *,
        stop: threading.Event | None = None,
    ) -> None:
        """Supervise until ``duration_s`` passes, ``stop`` is set or KeyboardInterrupt; then
        stop every process."""
        stop = stop or threading.Event()
        deadline = None if duration_s is None else time.monotonic() + duration_s
        try:
            while deadline is None or time.monotonic() < deadline:
                self.poll()
                if on_tick is not None:
                    on_tick()
                if stop.wait(_POLL_S):
                    break
        finally:
            self.stop()

    @property
    def stopping(self) -> bool:
        """True once ``stop`` began: what is said of the processes then is their end."""
        return self._stopping

    def pids(self) -> dict[str, int | None]:
        """Current pid of every process (None while waiting to restart)."""
        return {r.spec.name: (r.proc.pid if r.proc else None) for r in self._running}

    def name_taken(self) -> list[str]:
        """Processes that stopped because another live instance offers their service name."""
        return [
            r.spec.name
            for r in self._running
            if r.proc is None and r.exit_codes[-1:] == [EXIT_NAME_TAKEN]
        ]

    def restarts(self) -> dict[str, int]:
        return {r.spec.name: r.restarts for r in self._running}

    def uptimes(self) -> dict[str, float | None]:
        """Seconds each process has been running (None while waiting to restart)."""
        now = time.monotonic()
        return {r.spec.name: (now - r.started_at if r.proc else None) for r in self._running}

    def signal_deaths(self, *, recovered: bool = True) -> dict[str, list[str]]:
        """Each process that died by a signal (not the SIGKILL of ``stop``), and how;
        ``recovered=False``: not the deaths of a process that was restarted and running again
        when the stop came (each was said as it happened)."""
        out: dict[str, list[str]] = {}
        for running in self._running:
            codes = list(running.exit_codes)
            if not recovered and running.up_at_stop:
                codes = codes[-1:]  # only how it ended at the stop
            if running.killed_by_us and codes and codes[-1] == -signal.SIGKILL:
                codes.pop()
            deaths = [exit_text(c) for c in codes if c < 0]
            if deaths:
                out[running.spec.name] = deaths
        return out

    def failures(self, *, recovered: bool = True) -> list[str]:
        """One line per process a launcher must report (and then exit non-zero): each that
        died by a signal or by its own non-zero exit (``recovered=False``: only those left
        down at the stop, not a process restarted and running again), and each that could
        not start because its name is taken."""
        deaths = [
            f"{name} {', '.join(how)}"
            for name, how in self.signal_deaths(recovered=recovered).items()
        ]
        taken = [
            f"{name} did not start: another live instance offers its name"
            for name in self.name_taken()
        ]
        return deaths + taken + self._exits(recovered=recovered)

    def _exits(self, *, recovered: bool) -> list[str]:
        """Each process that ended by its own non-zero exit (not a signal, not a taken
        name): every one (``recovered``: a demo's figures are incomplete after any), or only
        those it left down at the stop (not restarted, or still waiting to restart)."""
        out: list[str] = []
        for running in self._running:
            codes = [c for c in running.exit_codes if c > 0 and c != EXIT_NAME_TAKEN]
            if recovered:
                if codes:
                    out.append(f"{running.spec.name} {', '.join(exit_text(c) for c in codes)}")
                continue
            code = running.exit_codes[-1] if running.exit_codes else 0
            if not running.up_at_stop and code > 0 and code != EXIT_NAME_TAKEN:
                out.append(f"{running.spec.name} {exit_text(code)} and was not running at the stop")
        return out

    def stop(self, timeout_s: float = 1.5) -> None:
        """SIGTERM every process, wait up to ``timeout_s``, then SIGKILL what is left.

        A service closes its Zenoh session well within the default; one that does not is
        killed, so that the whole launch ends within 2 s of one Ctrl-C.
        """
        self._stopping = True
        live = [r for r in self._running if r.proc is not None]
        # A process that died since the last poll still gets its exit recorded below.
        stopping = [r for r in live if r.proc is not None and r.proc.poll() is None]
        for running in stopping:
            running.up_at_stop = True
        for running in stopping:
            assert running.proc is not None
            with contextlib.suppress(ProcessLookupError):
                running.proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout_s
        for running in stopping:
            assert running.proc is not None
            try:
                running.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                running.killed_by_us = True
                running.proc.kill()
                running.proc.wait()
                if timeout_s > 0:  # (0: a second Ctrl-C asked for exactly this)
                    # Said, because its own last lines (its totals) will be missing.
                    self._emit(running, f"still running {timeout_s:g} s after SIGTERM: killed")
        for running in live:
            assert running.proc is not None
            code = running.proc.returncode
            if code is None or running.exit_recorded:
                continue
            running.exit_recorded = True
            running.exit_codes.append(code)
            if code == -signal.SIGTERM and any(r is running for r in stopping):
                # Our own SIGTERM, taken before the child set its handler (it was still
                # starting): a stop, not a death.
                running.exit_codes[-1] = 0
            elif code < 0 and not running.killed_by_us:
                self._emit(running, f"{exit_text(code)} while stopping")
        # A stopped child's last lines (its totals) are still in the pipe: read them out.
        for running in self._running:
            if running.pump is not None:
                running.pump.join(timeout=max(0.1, deadline - time.monotonic()))
        for fd in (self._lifeline_r, self._lifeline_w):
            with contextlib.suppress(OSError):
                os.close(fd)
