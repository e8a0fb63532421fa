"""Deadlines for tests, scaled by one setting.

No test may fail because the machine is slow: every wait in the suite is a deadline for a
condition, generous enough for a machine ten times slower than the 2-core development VM,
and ``FRAMEGATE_TEST_TIMEOUT_SCALE`` (a number, default 1) multiplies all of them, so that
CI or a user on a busy laptop can raise every deadline at once. How fast something is
belongs in a benchmark row (``framegate bench``), never in an assertion.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import TypeVar

from middleware import FramegateError

SCALE_VARIABLE = "FRAMEGATE_TEST_TIMEOUT_SCALE"

T = TypeVar("T")

# How long a service that does not answer may be a live one that lost its lease (see
# ``answered``): reconnecting took seconds at load 22 on 2 cores.
LEASE_LAPSE_S = 20.0


def _read_scale() -> float:
    text = os.environ.get(SCALE_VARIABLE, "").strip()
    if not text:
        return 1.0
    try:
        scale = float(text)
    except ValueError:
        scale = float("nan")
    if not scale >= 1.0 or scale == float("inf"):
        raise ValueError(f"{SCALE_VARIABLE}={text!r}: must be a finite number >= 1")
    return scale


# Read once, at import: the suite's autouse fixture clears FRAMEGATE_* variables per test so
# that a developer's shell does not leak into the processes a test starts.
TIMEOUT_SCALE = _read_scale()


def scaled(seconds: float) -> float:
    """``seconds`` of waiting on this machine: multiplied by the suite's timeout scale."""
    return seconds * TIMEOUT_SCALE


def wait_until(
    predicate: Callable[[], T | None], timeout_s: float, what: str | Callable[[], str]
) -> T:
    """Poll ``predicate`` until it returns something truthy and return that; fail naming
    ``what`` when ``scaled(timeout_s)`` passes first. A callable ``what`` is called then, so
    that a log it shows is the one at the deadline, not the one when the wait began."""
    limit_s = scaled(timeout_s)
    deadline = time.monotonic() + limit_s
    while True:
        began = time.monotonic()
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            said = what() if callable(what) else what
            raise AssertionError(f"timed out after {limit_s:g} s waiting for {said}")
        time.sleep(_pause_s(time.monotonic() - began))


# Between two looks, at least ``POLL_S``, and at least ``LOOK_SHARE`` times what the last look
# took, up to ``POLL_MAX_S``: a look that queries a service (every decision a mediator
# stored, parsed) costs the test and the service CPU, and at a fixed 20 ms the suite's
# pipeline tests spent whole seconds of it on looking.
POLL_S = 0.02
LOOK_SHARE = 3.0
POLL_MAX_S = 0.25


def _pause_s(look_s: float) -> float:
    return min(POLL_MAX_S, max(POLL_S, LOOK_SHARE * look_s))


def answered(ask: Callable[[], T], what: str, wait_s: float = LEASE_LAPSE_S) -> T:
    """``ask()``'s result, asked again while it raises a FramegateError, for ``scaled(wait_s)``.

    Every look at another process (``ls``, ``info``, a query, a liveliness look) goes through
    this (or ``wait_until``), never once: on a loaded machine a live process can go without
    CPU for longer than its session's lease (measured: a camera's Zenoh transmit thread
    runnable but not run for 2.3 s at load 22 on 2 cores); its peers then drop it until it
    reconnects, seconds later, and meanwhile nobody answers for it. A service that is really
    gone still fails, naming ``what``, once the deadline passes."""
    got: list[T] = []
    errors: list[FramegateError] = []

    def once() -> bool:
        try:
            got.append(ask())
        except FramegateError as exc:
            errors[:] = [exc]
            return False
        return True

    wait_until(once, wait_s, lambda: f"{what} (last error: {errors[-1] if errors else None})")
    return got[-1]
