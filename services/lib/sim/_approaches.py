"""Rendered approaches kept on disk by the hash of their parameters, rendered only once.

Rendering an approach costs about a second of CPU per frame, far too slow for a camera to
keep its frame rate live on a small machine; a dataset rendered once (with a progress bar)
and read back frame by frame costs a PNG decode per frame. The experiment keeps its
approaches under its output directory, the demo's camera under the user's cache directory
(``$XDG_CACHE_HOME/framegate/approaches``, else ``~/.cache/framegate/approaches``).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import threading
from pathlib import Path

from ._config import ScenarioConfig
from ._dataset import Dataset, DatasetError, read_dataset
from ._simulate import simulate


def approach_cache_dir() -> Path:
    """The default cache of rendered approaches (created on first render)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "framegate" / "approaches"


def scenario_hash(config: ScenarioConfig) -> str:
    """A short stable name for a scenario: every parameter goes into it."""
    text = json.dumps(config.to_dict(), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]


def cached_dataset(
    config: ScenarioConfig,
    cache: Path,
    *,
    progress: bool = True,
    stop: threading.Event | None = None,
) -> Dataset:
    """The dataset of ``config`` from ``cache/<hash>``, rendering it first if it is not there.

    Rendering goes to ``<hash>.partial-<pid>`` and is renamed when complete, so an interrupted
    render is never mistaken for a dataset. Raises ``DatasetError`` naming the directory
    when a cached entry is unreadable or holds another scenario; ``RenderStopped`` when
    ``stop`` is set during a render (its partial directory is removed).
    """
    root = cache / scenario_hash(config)
    if not root.is_dir():
        cache.mkdir(parents=True, exist_ok=True)
        # Per process: a camera and a gyro started together may both render; the first
        # rename wins and the other's copy is discarded.
        partial = cache / f"{root.name}.partial-{os.getpid()}"
        if partial.exists():
            shutil.rmtree(partial)
        try:
            simulate(config, partial, progress=progress, stop=stop)
        except BaseException:
            shutil.rmtree(partial, ignore_errors=True)
            raise
        try:
            partial.rename(root)
        except OSError:
            if not root.is_dir():
                raise
            shutil.rmtree(partial, ignore_errors=True)
    try:
        dataset = read_dataset(root)
    except DatasetError as exc:
        raise DatasetError(f"cached dataset {root} is unreadable ({exc}); delete it") from exc
    if dataset.truth is None or dataset.scenario != config:
        raise DatasetError(
            f"cached dataset {root} does not hold seed {config.seed}'s scenario with truth; "
            "delete it to render it again"
        )
    return dataset
