"""A loop on a thread of its own for as long as a ``with`` block lasts."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager


@contextmanager
def in_background(loop: Callable[[threading.Event], object]) -> Iterator[None]:
    """Run ``loop(stop)`` on a daemon thread; at the block's end set ``stop`` and join it
    (``loop`` returns once ``stop`` is set)."""
    stop = threading.Event()
    thread = threading.Thread(target=loop, args=(stop,), daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
