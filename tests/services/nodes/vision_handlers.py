"""Vision handlers the tests load by name (``--handler tests.services.nodes.vision_handlers:…``)."""

from __future__ import annotations

import threading
import time

import numpy as np
import numpy.typing as npt

from services.lib.vision import Box, FrameMeta, Output

NOT_A_FUNCTION = 42


def brightest(image: npt.NDArray[np.uint8], frame: FrameMeta) -> list[Box]:
    """A cheap handler: one box around the image's brightest pixel."""
    y, x = np.unravel_index(int(np.argmax(image)), image.shape[:2])
    return [Box.from_xywh(0, float(x) - 2, float(y) - 2, 4, 4, score=float(image[y, x]) / 255)]


def slow(image: npt.NDArray[np.uint8], frame: FrameMeta) -> list[Box]:
    """As ``brightest``, but busy for 2.5 s per frame: slower than the camera even on a
    machine so loaded that it makes one frame a second (seen at load 40 on 2 cores, where a
    1 s handler kept up with it and was rightly sent every frame)."""
    time.sleep(2.5)
    return brightest(image, frame)


def odd_frames_raise(image: npt.NDArray[np.uint8], frame: FrameMeta) -> list[Box]:
    """Raises ValueError on odd frame ids; finds nothing on even ones."""
    if frame.frame_id % 2:
        raise ValueError(f"odd frame {frame.frame_id}")
    return []


def histogram(image: npt.NDArray[np.uint8], frame: FrameMeta) -> Output:
    """A generic result: the 16-bin histogram as the payload, the mean as a field."""
    counts, _edges = np.histogram(image, bins=16, range=(0, 256))
    return Output(counts.astype("<u4").tobytes(), {"mean": float(image.mean())})


def stuck(image: npt.NDArray[np.uint8], frame: FrameMeta) -> list[Box]:
    """Never returns in any test's lifetime: a stop must not wait for it."""
    time.sleep(600)
    return []


def one_argument(image: npt.NDArray[np.uint8]) -> list[Box]:
    """Takes the image alone: every frame failed with a TypeError, counted, not at start."""
    return []


async def coroutine(image: npt.NDArray[np.uint8], frame: FrameMeta) -> list[Box]:
    """An ``async def`` handler: it would give a coroutine per frame, never a result."""
    return []


class TakesNothing:
    """A class named as the handler, whose instances take no (image, frame)."""


class ThreadBound:
    """A handler class with per-thread state, as a model bound to the thread that made it
    has: each result says whether it runs on the thread ``__init__`` ran on, and how many
    calls that thread has run."""

    def __init__(self) -> None:
        self._local = threading.local()
        self._local.calls = 0

    def __call__(self, image: npt.NDArray[np.uint8], frame: FrameMeta) -> Output:
        created_here = hasattr(self._local, "calls")
        self._local.calls = getattr(self._local, "calls", 0) + 1
        return Output(b"", {"created_here": created_here, "calls_here": self._local.calls})
