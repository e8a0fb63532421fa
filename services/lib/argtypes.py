"""Argument parsing that gives one line a person can act on.

``FramegateParser`` is the parser of every command: a mistake prints one line,
``error: PROG: ...`` with a did-you-mean for a misspelt command, choice or flag, and exits
with code 1 (argparse's default is a usage dump and code 2). The number types check a
flag's value while parsing, so ``--rate nan`` or ``--retention-frames 0`` is refused with
the flag and the allowed range instead of failing later, or silently doing nothing:

    parser.add_argument("--rate", type=positive_float, default=1.0)

This module imports nothing heavy: the services' ``add_arguments`` use it too.
"""

from __future__ import annotations

import argparse
import difflib
import math
import os
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any, NoReturn

# Exit code of every command-line mistake (argparse's own is 2).
USAGE_EXIT_CODE = 1


def closest(word: str, candidates: Iterable[str]) -> str | None:
    """The candidate ``word`` is most likely a misspelling of, if any."""
    names = list(candidates)
    hint = difflib.get_close_matches(word, names, n=1, cutoff=0.6)
    if not hint:  # two letters swapped in a short word (``sl``) are too far for difflib
        hint = [n for n in names if len(n) == len(word) and sorted(n) == sorted(word)][:1]
    return hint[0] if hint else None


def did_you_mean(word: str, candidates: Iterable[str], *, quote: bool = False) -> str:
    """`` (did you mean x?)`` for the closest candidate, or ``""``; ``quote``: a name the
    message quotes (``'x'``), as opposed to a flag or command word."""
    hint = closest(word, candidates)
    if hint is None:
        return ""
    return f" (did you mean {hint!r}?)" if quote else f" (did you mean {hint}?)"


# What a ROS 2 user types out of habit (``ros2 topic ...``, ``ros2 bag ...``), per command,
# and how framegate says it: named before any did-you-mean, which pointed elsewhere
# (``echo --once`` suggested --json, ``record -a`` nothing).
ROS2_FLAGS: dict[str, dict[str, str]] = {
    "echo": {"--once": "--count 1 here"},
    "pub": {"--once": "--count 1 here", "-t": "--count N here", "--times": "--count N here"},
    "hz": {"-w": "--window N here"},
    "record": {"-a": "--all here", "--topics": "not needed here: name SERVICE/BUFFER ..."},
    "play": {
        "-r": "--rate R here",
        "--topics": "--only SERVICE/BUFFER here",
        "-d": "--start-delay S here",
    },
    "info": {"-v": "not needed here: info lists the subscriptions always"},
    "ls": {"-t": "not needed here: ls shows each buffer's kind always"},
}
# ROS 2 habits that are framegate flags of another meaning: said when that flag's own use
# fails (``play run.mcap -l``: "argument --listen/-l: expected one argument").
ROS2_SHADOWED: dict[str, dict[str, str]] = {"play": {"-l": "--loop"}}


def _ros2_flag(prog: str, flag: str) -> str:
    """`` (ros2's --once is --count 1 here)`` for a ROS 2 habit of command ``prog``."""
    ours = ROS2_FLAGS.get(prog.split()[-1], {}).get(flag)
    return f" (ros2's {flag} is {ours})" if ours else ""


def _short_hint(flag: str, options: list[str]) -> str:
    """A did-you-mean for ``flag``; for a short one (``-o``) the one long option it may
    abbreviate (``--out``), which no spelling distance finds."""
    if len(flag) == 2 and flag[0] == "-" and flag[1] != "-":
        starting = [o for o in options if o.startswith(f"--{flag[1]}")]
        if len(starting) == 1:
            return f" (did you mean {starting[0]}?)"
    return did_you_mean(flag, options)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _long(parser: argparse.ArgumentParser, flag: str) -> str:
    """The long name of ``parser``'s option ``flag`` (``-l`` -> ``--listen``)."""
    for action in parser._actions:
        if flag in action.option_strings:
            return max(action.option_strings, key=len)
    return flag


def _options(parser: argparse.ArgumentParser) -> list[str]:
    return [s for a in parser._actions for s in a.option_strings if s.startswith("--")]


def _subparser(
    parser: argparse.ArgumentParser, namespace: argparse.Namespace
) -> argparse.ArgumentParser | None:
    """The subcommand parser ``namespace`` went through, if any."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            chosen = getattr(namespace, action.dest or "", None)
            if isinstance(chosen, str) and chosen in action.choices:
                sub: argparse.ArgumentParser = action.choices[chosen]
                return _subparser(sub, namespace) or sub
    return None


class FramegateParser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line, with a did-you-mean, and exit code 1."""

    _seen: tuple[str, ...] = ()

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        # Kept for ``error``: a subcommand's parser is handed its own share of the words.
        self._seen = tuple(sys.argv[1:] if args is None else args)
        return super().parse_known_args(args, namespace)

    def _unknown_option(self) -> str | None:
        """The first word of ours that looks like an option and is none of this parser's."""
        known = {s for a in self._actions for s in a.option_strings}
        for word in self._seen:
            flag = word.split("=", 1)[0]
            if word == "--":
                return None
            if flag.startswith("-") and flag not in known and not _is_number(flag):
                return word
        return None

    def error(self, message: str) -> NoReturn:
        if message.startswith("the following arguments are required") and (
            word := self._unknown_option()
        ):
            # argparse says what is missing before what it did not know: ``simulate -o x``
            # was "required: --out", with no word on the -o that was meant for it.
            flag = word.split("=", 1)[0]
            hint = _ros2_flag(self.prog, flag) or _short_hint(flag, _options(self))
            message = f"unknown option {word!r}{hint}; see {self.prog} --help"
        for flag, ours in ROS2_SHADOWED.get(self.prog.split()[-1], {}).items():
            if message.startswith("argument ") and f"/{flag}:" in message.split(" ", 2)[1]:
                message += f" ({flag} is {_long(self, flag)} here; ros2's {flag} is {ours})"
        self.exit(USAGE_EXIT_CODE, f"error: {self.prog}: {message}\n")

    def parse_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> argparse.Namespace:
        parsed, extras = self.parse_known_args(args, namespace)
        if extras:
            sub = _subparser(self, parsed)
            target = sub or self
            known = _options(target) + ([] if sub is None else _options(self))
            first = extras[0]
            flag = first.split("=", 1)[0]
            hint = _ros2_flag(target.prog, flag) or (
                _short_hint(flag, known) if first.startswith("-") else ""
            )
            what = "unknown option" if first.startswith("-") else "unexpected argument"
            target.error(f"{what} {first!r}{hint}; see {target.prog} --help")
        return parsed

    def _check_value(self, action: argparse.Action, value: Any) -> None:
        # argparse's own message lists every choice but suggests none.
        choices = action.choices
        if choices is not None and value not in choices:
            names = [str(c) for c in choices]
            raise argparse.ArgumentError(
                action,
                f"invalid choice: {value!r}{did_you_mean(str(value), names)} "
                f"(choose from {', '.join(names)})",
            )


def _number(
    kind: type[int] | type[float], low: float | None, *, strict: bool, high: float | None = None
) -> Callable[[str], Any]:
    if low is None:
        allowed = "a finite number"
    else:
        allowed = f"{'an integer' if kind is int else 'a number'} {'>' if strict else '>='} {low:g}"
    if high is not None:
        allowed += f" and <= {int(high) if kind is int else format(high, 'g')}"

    def parse(text: str) -> int | float:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {allowed}, got {text!r}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"must be {allowed}, got {text!r}")
        too_low = low is not None and (value <= low if strict else value < low)
        if too_low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"must be {allowed}, got {text!r}")
        return value

    parse.__name__ = kind.__name__  # argparse names the type in some messages
    return parse


# The largest rate, period or scale a flag takes. Times inside are int nanoseconds:
# 10^9 s still fits an int64, and a larger duration crashed its service with a traceback
# (``--consumer-timeout-ms 1e303``: OverflowError turning it into nanoseconds).
MAX_FLOAT = 1e9
#: Finite, > 0, at most ``MAX_FLOAT``: rates, periods, scales.
positive_float = _number(float, 0, strict=True, high=MAX_FLOAT)
#: From ``1 / MAX_FLOAT`` to ``MAX_FLOAT``: a rate or speed factor whose reciprocal is a
#: period (``pub --rate 1e-12`` waited 10^12 s, past what a thread can wait: OverflowError).
positive_rate = _number(float, 1 / MAX_FLOAT, strict=False, high=MAX_FLOAT)
#: Finite, >= 0, at most ``MAX_FLOAT``: delays, waits, minimums.
non_negative_float = _number(float, 0, strict=False, high=MAX_FLOAT)
#: Finite, any sign.
#: In [0, 1]: qualities, fractions.
unit_float = _number(float, 0, strict=False, high=1)
#: >= 1: counts, queue sizes, retention.
positive_int = _number(int, 0, strict=True)
#: >= 0.
non_negative_int = _number(int, 0, strict=False)


def queue_size(limit: int) -> Callable[[str], int]:
    """A queue size flag's type: an integer >= 1 and at most ``limit`` (the middleware's
    ``OBSERVE_QUEUE_MAX`` or ``FLOW_QUEUE_MAX``), refused by the flag's name while parsing."""
    return _number(int, 0, strict=True, high=limit)


#: A TCP port to listen on or connect to: 1..65535.
port_number = _number(int, 1, strict=False, high=65535)


def print_error(message: str) -> None:
    """The one-line form of every error."""
    print(f"error: {message}", file=sys.stderr)


def report_file(text: str) -> Path:
    """A file a long run writes its JSON report to at its end (``bench``, ``soak``,
    ``faults`` ``--json FILE``): a directory, or a file in a directory that does not exist,
    is refused now, not after the run (soak's 10 minutes ended in "No such file")."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(
            f"{text} is a directory; give a file, e.g. {path / 'report.json'}"
        )
    if not path.parent.is_dir():
        raise argparse.ArgumentTypeError(
            f"cannot write {text}: directory {path.parent} does not exist"
        )
    if not os.access(path.parent, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise argparse.ArgumentTypeError(f"cannot write {text}: permission denied")
    return path
