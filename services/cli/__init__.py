"""The ``framegate`` command line: a thin shell over the library.

Each command lives in its own module here and exposes ``register(subparsers)``, which adds
its parser and sets ``func`` to a function ``(args) -> int``. Commands catch only
``FramegateError``, print ``error: ...`` on stderr and return a non-zero exit code.

Start-up is part of the interface: ``framegate --help`` imports no command module (the
summaries below are enough to list them) and ``framegate CMD`` imports only CMD's module,
so ``ls`` does not pay for OpenCV, NumPy or the Foxglove bridge.

Signals are part of it too: ``main`` turns SIGINT and SIGTERM into KeyboardInterrupt
before it imports the command's module, so a Ctrl-C or ``kill`` at any instant of a
command's life (the imports, the parsing, the opening of a Zenoh session) ends it with
exit code 0 and no traceback. That instant starts once Python has loaded its site
packages (the first few tens of milliseconds of the process; before that, Python itself
answers a Ctrl-C, as it does for any program), and the handler is set before anything else
is imported (through ``_signal``). Commands that run until stopped replace that handler with
their own (``_common.stop_on_signals``). A process started with the two signals blocked
(as ``launch`` starts its services, so that a stop during their start-up waits for this
handler) gets them delivered once the handler is in place.
"""

from __future__ import annotations

# ``_signal``, not ``signal``: importing ``signal`` builds its enums first, which took up
# to half a second on a loaded machine, and a Ctrl-C then ended in a traceback.
import _signal
import os
import sys


def _stopped_while_importing(_signum: int, _frame: object) -> None:
    # No session, file or child exists yet: nothing to close, nothing to report. Not a
    # raise: Python ignores an exception raised inside some callbacks (the import system's
    # module-lock weakref callback), and the command would then start as if never stopped
    # (seen: a router signalled while importing kept running).
    os._exit(0)


# Run as the ``framegate`` command (the console script, or ``python -m services.cli``, whose
# argv[0] is "-m" while this package loads): a stop during this module's own imports exits 0
# without a traceback; ``main`` installs the real handler. Imported by anything else (tests,
# a user's script), the importer's handlers are left alone.
if sys.argv and (sys.argv[0] == "-m" or sys.argv[0].endswith("framegate")):
    for _signum in (_signal.SIGINT, _signal.SIGTERM):
        _signal.signal(_signum, _stopped_while_importing)

import argparse
import contextlib
import importlib
import signal
from collections.abc import Callable, Sequence
from types import FrameType
from typing import Any

from services.lib.argtypes import FramegateParser, print_error

# Every command with its one-line summary, in the order `framegate --help` lists them.
COMMANDS: dict[str, str] = {
    "demo": "run the whole pipeline on this host with a live status view",
    "launch": "start the services a deploy file assigns to this host",
    "run": "start one service (camera, gyro, mediator, detector, vision, ros2)",
    "ls": "list live services, their buffers and who subscribes",
    "info": "describe a buffer: retention, size, span, rate, subscriptions, counters",
    "query": "print (or save) the elements of a buffer in a time range",
    "echo": "print each new element of a buffer: metadata fields and payload summary",
    "watch": "print a buffer's notifications as they arrive",
    "hz": "measure a buffer's rate, jitter and bandwidth",
    "pub": "publish test elements of a kind under a temporary service",
    "view": "stream buffers live to Foxglove",
    "record": "record buffers to an MCAP file",
    "play": "offer the buffers of an MCAP recording again",
    "router": "run a Zenoh router until Ctrl-C",
    "simulate": "render the bumpy-approach scenario into a dataset",
    "calibrate": "derive the blur scale b0 from a dataset",
    "experiment": "reproduce the paper's marker experiment",
    "bench": "benchmark framegate against raw Zenoh",
    "soak": "run the pipeline at full speed; report memory growth and losses",
    "faults": "kill each service repeatedly; report restart times",
}


# What a ROS 2 user types first, and framegate's command that answers the same question.
_ROS2_WORDS: dict[str, dict[str, str]] = {
    "topic": {"list": "ls", "info": "info", "echo": "echo", "hz": "hz", "bw": "hz", "pub": "pub"},
    "bag": {"record": "record", "play": "play", "info": "info"},
    "node": {"list": "ls", "info": "ls"},
}


def _ros2_word(words: list[str]) -> str | None:
    """The one-line hint for ``framegate topic echo ...`` and the like, or None."""
    if not words:
        return None
    first, rest = words[0], words[1:]
    if first == "help":
        return "framegate has no 'help' command: framegate --help lists the commands"
    if first not in _ROS2_WORDS:
        return None
    ours = _ROS2_WORDS[first]
    if rest and rest[0] in ours:
        return (
            f"framegate has no {first!r} command: 'ros2 {first} {rest[0]}' is "
            f"'framegate {ours[rest[0]]}' here (framegate --help lists the commands)"
        )
    names = list(dict.fromkeys(ours.values()))
    listed = ", ".join(names[:-1]) + f" and {names[-1]}" if len(names) > 1 else names[0]
    return (
        f"framegate has no {first!r} command: its {listed} answer what "
        f"'ros2 {first} ...' does (framegate --help lists the commands)"
    )


def _version() -> str:
    """The installed distribution's version, looked up only when asked."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("framegate")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown (not installed)"


class _VersionAction(argparse.Action):
    """``framegate --version`` (listed by ``--help``)."""

    def __call__(self, parser: argparse.ArgumentParser, *_: object) -> None:
        print(f"framegate {_version()}")
        parser.exit(0)


def build_parser(only: str | None = None) -> FramegateParser:
    """The top-level parser; with ``only`` (a command name) that command fully registered.

    Without ``only`` every command is listed by its summary but none is imported: enough
    for ``--help`` and for naming a misspelt command.
    """
    parser = FramegateParser(
        prog="framegate",
        description="Named, flow-controlled camera/gyro buffers over Zenoh, and the "
        "blur-aware mediator that keeps blurred frames away from vision code.",
        epilog="framegate COMMAND --help describes a command.",
    )
    parser.add_argument(
        "--version", action=_VersionAction, nargs=0, help="print framegate's version and exit"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, summary in COMMANDS.items():
        if name == only:
            importlib.import_module(f"services.cli.{name}").register(sub)
        else:
            sub.add_parser(name, help=summary, add_help=False)
    return parser


_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


# Set by the first stop signal. Python ignores an exception raised in some callbacks (the
# import system's module-lock weakref callback, a __del__), so a signal during an import
# may not interrupt it: before the command runs, ``_main`` checks this too.
_requested = [False]


def _interrupt(_signum: int, _frame: FrameType | None) -> None:
    _requested[0] = True
    raise KeyboardInterrupt


def _quiet_unraisable(unraisable: Any) -> None:
    """Python's report of an exception it ignored, except our own stop (taken later)."""
    if not isinstance(unraisable.exc_value, KeyboardInterrupt):
        sys.__unraisablehook__(unraisable)


_Handler = Callable[[int, FrameType | None], Any] | int | None


def _catch_stop_signals() -> dict[signal.Signals, _Handler]:
    """SIGINT and SIGTERM raise KeyboardInterrupt from here on; the previous handlers."""
    return {signum: signal.signal(signum, _interrupt) for signum in _STOP_SIGNALS}


def _leave(code: int) -> None:
    """End a console process with ``code`` once its command has returned.

    The command has closed its sessions and files in its own ``finally``. What may be left
    is a daemon thread still inside a Zenoh call (a bridge thread blocked in a query, a
    worker abandoned after a stop) or a thread Zenoh itself runs Python on: when the
    interpreter finalises, such a thread is unwound through Rust frames and the process
    aborts (SIGABRT, "FATAL: exception not rethrown") instead of exiting with ``code``.
    Nothing is left to finalise that the command did not already close, so end here."""
    logging = sys.modules.get("logging")
    if logging is not None:
        logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # a closed pipe: nothing to say
            stream.flush()
    os._exit(code)


def _stopped(console: bool) -> int:
    """Exit code 0 for a stop by signal; a console process ends at once.

    A signal may land anywhere, e.g. right after a Zenoh session opened and before its
    ``with`` block was entered; a process whose session is left open may never finish
    its interpreter shutdown. What a command must keep (a recording's last chunk, the
    launcher's children) it handles in its own ``finally``, which has already run here."""
    if console:
        _leave(0)
    return 0


def _by_interrupt(exc: BaseException) -> bool:
    """Whether ``exc`` wraps a KeyboardInterrupt: Python 3.11 turns one raised while a class
    is being created (a dataclass field's ``__set_name__`` during an import) into a
    RuntimeError whose cause it is."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        if isinstance(current, KeyboardInterrupt):
            return True
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return False


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``framegate`` console script."""
    previous: dict[signal.Signals, _Handler] = {}
    unraisable = sys.unraisablehook
    try:  # from the very first line: Python's own SIGINT handler raises until ours is in
        previous = _catch_stop_signals()  # first: before any command module is imported
        sys.unraisablehook = _quiet_unraisable
        # A signal that arrived while the two were blocked (a launcher stopping a service
        # that was still starting) is delivered here, to the handler, inside this try.
        signal.pthread_sigmask(signal.SIG_UNBLOCK, _STOP_SIGNALS)
        code = _main(argv)
        if argv is None:
            _leave(code)
        return code
    except KeyboardInterrupt:
        # Ctrl-C or SIGTERM: a stop the user asked for, not a failure (see the CLI reference).
        return _stopped(console=argv is None)
    except Exception as exc:
        if _by_interrupt(exc):
            return _stopped(console=argv is None)
        raise
    finally:
        if argv is not None:  # called in-process (tests): leave the caller's handlers as they were
            sys.unraisablehook = unraisable
            for signum, handler in previous.items():
                signal.signal(signum, handler)


def _main(argv: Sequence[str] | None) -> int:
    words = list(sys.argv[1:] if argv is None else argv)
    if "--version" in words:  # after a command too: `framegate ls --version`
        print(f"framegate {_version()}")
        return 0
    chosen = next((w for w in words if not w.startswith("-")), None)
    if chosen is not None and chosen not in COMMANDS:
        hint = _ros2_word(words[words.index(chosen) :])
        if hint:
            print_error(hint)
            return 1
    parser = build_parser(chosen if chosen in COMMANDS else None)
    try:
        args = parser.parse_args(words)
    except SystemExit as exc:  # --help (0) or a one-line mistake (1)
        return int(exc.code or 0)
    if _requested[0]:  # stopped during the imports, where the interrupt may be swallowed
        raise KeyboardInterrupt
    if not getattr(args, "func", None):
        parser.print_usage(sys.stderr)
        print_error("name a command; framegate --help lists them")
        return 1
    try:
        return int(args.func(args))
    except BrokenPipeError:
        # `framegate query ... | head` closed the pipe: not an error worth a traceback.
        sys.stderr.close()
        return 0
    except Exception as exc:
        if _by_interrupt(exc):
            raise
        # Only our own errors are a one-liner; anything else is a bug worth its traceback.
        middleware = sys.modules.get("middleware")
        if middleware is not None and isinstance(exc, middleware.FramegateError):
            print_error(str(exc))
            return 1
        if isinstance(exc, OSError) and exc.strerror:
            where = f" {exc.filename}" if exc.filename else ""
            print_error(f"{exc.strerror}{where}")
            return 1
        raise


if __name__ == "__main__":
    sys.exit(main())
