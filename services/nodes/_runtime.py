"""What every service process shares: logging, a common start time, pacing, shutdown."""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time

from middleware import ConfigError

START_AT_ENV = "FRAMEGATE_START_AT_NS"


def setup_logging(name: str, level: int = logging.INFO) -> logging.Logger:
    """Plain one-line logs on stderr; the launcher prefixes them with the service name."""
    logging.basicConfig(level=level, format="%(levelname)s %(message)s", force=True)
    return logging.getLogger(f"framegate.{name}")


def start_at_ns(flag_value: int | None) -> int:
    """Wall-clock ns at which replayed time zero happens.

    Camera and gyro replays started by one launch share it (the launcher sets
    FRAMEGATE_START_AT_NS), so their streams stay aligned although they are separate
    processes. Without either, start now.
    """
    if flag_value is not None:
        return flag_value
    raw = os.environ.get(START_AT_ENV)
    if raw:
        try:
            return int(raw)
        except ValueError as exc:
            raise ConfigError(f"{START_AT_ENV} must be integer ns, got {raw!r}") from exc
    return time.time_ns()


def sleep_until_ns(wall_ns: int, stop: threading.Event) -> bool:
    """Sleep until the wall clock reaches ``wall_ns``; False if ``stop`` was set first."""
    while True:
        remaining = (wall_ns - time.time_ns()) / 1e9
        if remaining <= 0:
            return not stop.is_set()
        if stop.wait(min(remaining, 0.5)):
            return False


class Monotonic:
    """Strictly increasing int ns keys from the wall clock (for decision records)."""

    def __init__(self) -> None:
        self._last = 0
        self._lock = threading.Lock()

    def next(self) -> int:
        with self._lock:
            self._last = max(self._last + 1, time.time_ns())
            return self._last


def serve_until_stopped(stop: threading.Event) -> None:
    """Keep a finished source's buffers answering queries until stopped (or Ctrl-C)."""
    with contextlib.suppress(KeyboardInterrupt):
        stop.wait()
