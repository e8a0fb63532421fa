"""Frames of the simulated approach kept on disk as a live camera renders them.

A ``sim`` camera renders each frame as it is due (about 50 ms of CPU per frame on a small
machine). Where ``FRAMEGATE_SIM_CACHE`` names a directory, each frame it renders is also
written there and read back the next time any camera asks for it: a frame is a function of
the scenario and its index alone (its noise is seeded by both), so the pixels are the same
and only the CPU is saved. Repeated runs of one scenario, such as the test suite's many short
pipelines, then render each frame once. Entries are keyed by ``scenario_hash``, written
atomically, and a damaged or foreign file is rendered again, never trusted.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from ._approaches import scenario_hash
from ._config import ScenarioConfig
from ._dataset import _PNG_PARAMS
from ._scene_cache import store_atomically


class FrameCache:
    """Rendered frames of one scenario under ``root/<scenario hash>/``."""

    ENV = "FRAMEGATE_SIM_CACHE"

    def __init__(self, root: Path, config: ScenarioConfig) -> None:
        self._dir = root / scenario_hash(config)
        self._shape = (config.height_px, config.width_px)

    @classmethod
    def from_env(cls, config: ScenarioConfig) -> FrameCache | None:
        """The cache ``FRAMEGATE_SIM_CACHE`` names, or None when it is unset or empty."""
        root = os.environ.get(cls.ENV, "").strip()
        return cls(Path(root), config) if root else None

    def frame(self, index: int, render: Callable[[], np.ndarray]) -> np.ndarray:
        """Frame ``index`` from the cache, else ``render()``'s, stored for the next asker."""
        path = self._dir / f"{index:06d}.png"
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if path.is_file() else None
        if image is not None and image.dtype == np.uint8 and image.shape == self._shape:
            return np.asarray(image)
        image = render()
        self._store(path, image)
        return image

    @staticmethod
    def _store(path: Path, image: np.ndarray) -> None:
        """Write ``image`` as a cache entry; one that cannot be written is skipped: the
        camera goes on rendering."""
        ok, encoded = cv2.imencode(".png", image, _PNG_PARAMS)
        if ok:
            store_atomically(path, lambda stream: stream.write(encoded.tobytes()))
