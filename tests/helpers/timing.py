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

SCALE_VARIABLE = "FRAMEGATE_TEST_TIMEOUT_SCALE"

T = TypeVar("T")


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


def wait_until(predicate: Callable[[], T | None], timeout_s: float, what: str) -> T:
    """Poll ``predicate`` until it returns something truthy and return that; fail naming
    ``what`` when ``scaled(timeout_s)`` passes first."""
    limit_s = scaled(timeout_s)
    deadline = time.monotonic() + limit_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {limit_s:g} s waiting for {what}")
        time.sleep(0.02)
