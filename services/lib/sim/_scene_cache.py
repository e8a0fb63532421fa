"""A disk cache of what a scenario computes at start, so a restarted camera or gyro is quick.

Building the wall and floor textures (1/f noise by FFT, posters) costs about a second of CPU
per start, and the body's dynamics need SciPy's signal package (a second to import); a
supervised camera or gyro that restarts after a crash should produce again within a few
seconds, so the textures and the motion's knots of each configuration are kept under the
user's cache directory (``$XDG_CACHE_HOME/framegate/scenes``, else ``~/.cache/framegate/scenes``).
An entry is keyed by every scenario parameter and a format version, holds plain arrays
(``np.load`` without pickle), is written atomically and is ignored, never trusted, when it
cannot be read or has the wrong shape: the textures are then built again.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from ._config import ScenarioConfig

# Bump when the texture code changes what it draws, so old entries are never read.
FORMAT = 1


def cache_dir() -> Path:
    """Where entries live (created on first save)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "framegate" / "scenes"


def _path(config: ScenarioConfig, kind: str) -> Path:
    key = hashlib.sha256(f"{FORMAT}:{kind}:{config!r}".encode()).hexdigest()[:24]
    return cache_dir() / f"{kind}-{key}.npz"


def load(
    config: ScenarioConfig, kind: str, shapes: Mapping[str, tuple[int, ...]], dtype: type
) -> dict[str, np.ndarray] | None:
    """The cached ``kind`` arrays named in ``shapes``, or None (missing, damaged, stale)."""
    try:
        with np.load(_path(config, kind), allow_pickle=False) as entry:
            arrays = {name: entry[name] for name in shapes}
    except (OSError, KeyError, ValueError, EOFError):
        return None
    for name, shape in shapes.items():
        if arrays[name].shape != shape or arrays[name].dtype != dtype:
            return None
    return arrays


def save(config: ScenarioConfig, kind: str, arrays: dict[str, np.ndarray]) -> None:
    """Store ``arrays`` for ``config``; a cache that cannot be written is simply skipped."""
    savez: Any = np.savez  # numpy's stubs take names for keywords only
    store_atomically(_path(config, kind), lambda stream: savez(stream, **arrays))


def store_atomically(path: Path, write: Callable[[BinaryIO], object]) -> None:
    """``write`` a cache entry to ``path`` so that a reader sees the old entry or the whole
    new one, never part of it; a cache that cannot be written is skipped."""
    with contextlib.suppress(OSError):
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as stream:
                write(stream)
            os.replace(tmp, path)
        except OSError:
            os.unlink(tmp)
