"""The ``framegate`` command line: a thin shell over the library.

Each command lives in its own module here and exposes ``register(subparsers)``, which adds
its parser and sets ``func`` to a function ``(args) -> int``. Commands catch only
``FramegateError``, print ``error: ...`` on stderr and return a non-zero exit code.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from middleware import FramegateError

# Command modules, in the order `framegate --help` lists them.
_COMMANDS = (
    "demo",
    "launch",
    "run",
    "ls",
    "info",
    "query",
    "watch",
    "hz",
    "view",
    "record",
    "play",
    "router",
    "simulate",
    "calibrate",
    "experiment",
    "bench",
    "soak",
    "faults",
)


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The top-level parser with every available command (or just ``only``) registered.

    Registering one command imports only its module, so ``framegate ls`` does not pay for
    OpenCV and SciPy.
    """
    parser = argparse.ArgumentParser(
        prog="framegate",
        description="Named, flow-controlled camera/gyro buffers over Zenoh, and the "
        "blur-aware mediator that keeps blurred frames away from vision code.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in (only,) if only in _COMMANDS else _COMMANDS:
        importlib.import_module(f"services.cli.{name}").register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``framegate`` console script."""
    words = list(sys.argv[1:] if argv is None else argv)
    chosen = next((w for w in words if not w.startswith("-")), None)
    parser = build_parser(chosen)
    args = parser.parse_args(words)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args))
    except FramegateError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # `framegate query ... | head` closed the pipe: not an error worth a traceback.
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
