"""Pieces every command shares: connection flags, JSON output, signals, time formatting."""

from __future__ import annotations

import _thread
import argparse
import json
import signal
import sys
import threading
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from types import FrameType
from typing import Any

from middleware import (
    NetworkConfig,
    Notification,
    Subscription,
    add_network_arguments,
    network_from_args,
)


def command_parser(
    subparsers: Any, name: str, help_text: str, *, network: bool = True, json_flag: bool = False
) -> argparse.ArgumentParser:
    """A subcommand parser with the shared flags already added."""
    parser: argparse.ArgumentParser = subparsers.add_parser(
        name, help=help_text, description=help_text
    )
    if network:
        add_network_arguments(parser)
    if json_flag:
        parser.add_argument("--json", action="store_true", help="print machine-readable JSON")
    return parser


def network(args: argparse.Namespace, base: NetworkConfig | None = None) -> NetworkConfig:
    """defaults → deploy file (``base``) → environment → flags."""
    return network_from_args(args, base)


def print_json(data: Any) -> None:
    json.dump(data, sys.stdout, indent=2, default=str)
    sys.stdout.write("\n")
    sys.stdout.flush()


def stop_on_signals() -> threading.Event:
    """An event that the first SIGINT or SIGTERM sets; a second one interrupts at once.

    Long-running commands wait on the event (never on a bare sleep), so one Ctrl-C or
    ``kill`` ends them within a moment and their ``with Node(...)`` blocks close the Zenoh
    session cleanly. Call from the main thread.
    """
    stop = threading.Event()
    signalled = False

    def handler(_signum: int, _frame: FrameType | None) -> None:
        # Python runs this in the main thread between bytecodes, wherever that thread is:
        # also inside ``stop.wait()`` while it holds the event's own lock (in
        # ``Condition.wait``, before it lets go), where ``stop.set()`` here waits for that
        # lock for ever (seen: a router that one SIGTERM, in that instant, left running).
        # So the handler takes no lock: a thread of its own sets the event once the main
        # thread lets go (a bare ``_thread``: ``threading.Thread.start`` takes the module's
        # lock and waits on an event of its own). A second signal raises, as a Ctrl-C does.
        nonlocal signalled
        if signalled:
            raise KeyboardInterrupt
        signalled = True
        _thread.start_new_thread(stop.set, ())

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop


def exit_on_sigterm() -> None:
    """Turn SIGTERM into KeyboardInterrupt so ``with`` blocks close Zenoh sessions cleanly."""

    def handler(_signum: int, _frame: FrameType | None) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, handler)


def format_ns(timestamp_ns: int | None) -> str:
    """RFC 3339 with microseconds, UTC; '-' for None."""
    if timestamp_ns is None:
        return "-"
    moment = datetime.fromtimestamp(timestamp_ns / 1e9, tz=UTC)
    return moment.strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def format_bytes(count: int) -> str:
    value = float(count)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if value < 1024 or unit == "GiB":
            return f"{value:.0f} {unit}" if unit == "B" else f"{value:.1f} {unit}"
        value /= 1024
    return f"{value:.1f} GiB"


def notifications(sub: Subscription, duration_s: float | None) -> Iterator[Notification]:
    """``sub``'s notifications as they come, until ``duration_s`` has passed (None: until the
    caller stops); the streaming commands (``watch``, ``echo``) share this loop."""
    deadline = None if duration_s is None else time.monotonic() + duration_s
    while True:
        wait_s = 0.5
        if deadline is not None:
            wait_s = min(wait_s, deadline - time.monotonic())
            if wait_s <= 0:
                return
        note = sub.take(timeout_s=wait_s)
        if note is not None:
            yield note


def report_failures(failures: list[str]) -> int:
    """Print each of a supervisor's ``failures`` as ``error: ...`` on stderr; the exit code
    (1 if there was any)."""
    for line in failures:
        print(f"error: {line}", file=sys.stderr, flush=True)
    return 1 if failures else 0


def counted(count: int, noun: str) -> str:
    """``1 element``, ``2 elements``: a count with its noun (regular plurals only)."""
    return f"{count} {noun}" if count == 1 else f"{count} {noun}s"


def format_seconds(seconds: float) -> str:
    """``4.2 s``, ``13 min 14 s``, ``2 h 5 min``: a gap a reader takes in at once."""
    if seconds < 60:
        return f"{seconds:.1f} s"
    minutes, secs = divmod(round(seconds), 60)
    if minutes < 60:
        return f"{minutes} min {secs} s"
    return f"{minutes // 60} h {minutes % 60} min"


MCAP_SUFFIX = ".mcap"


def recording_output(path: Path) -> Path:
    """The file ``record -o PATH`` writes: ``PATH`` with ``.mcap`` added when it has not
    that suffix (``ros2 bag record -o run`` makes ``run/run_0.mcap``; Foxglove and
    ``info``/``play`` know a recording by its suffix). A directory stays as given, to be
    refused by name."""
    if path.suffix.lower() == MCAP_SUFFIX or path.is_dir():
        return path
    return path.with_name(path.name + MCAP_SUFFIX)


def recording_input(path: Path) -> Path:
    """The recording ``info``/``play`` PATH means: ``PATH.mcap`` when only that exists (the
    file ``record -o PATH`` wrote), else ``PATH``."""
    if not path.exists() and path.suffix.lower() != MCAP_SUFFIX:
        with_suffix = path.with_name(path.name + MCAP_SUFFIX)
        if with_suffix.is_file():
            return with_suffix
    return path


def write_report(path: Path, report: Any) -> None:
    """``--json FILE`` of ``bench``, ``soak`` and ``faults``: the report, indented, a value
    JSON has no form for as its text. A failure is one line (the run's table is printed)."""
    from services.lib.files import OutputError

    try:
        path.write_text(json.dumps(report, indent=2, default=str) + "\n")
    except OSError as exc:
        raise OutputError(f"cannot write --json {path}: {exc.strerror or exc}") from exc
