"""Simulated approaches, rendered once per scenario and kept by the hash of its parameters."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

from services.lib.sim import Dataset, DatasetError, ScenarioConfig, read_dataset, simulate

from ._config import ExperimentError


def scenario_for(seed: int, frame_count: int | None, floor: str = "default") -> ScenarioConfig:
    """The paper's approach for one seed: simulator defaults, only the seed, the floor
    preset (see ``ScenarioConfig.with_floor``) and for a smoke test the frame count changed."""
    config = ScenarioConfig(seed=seed).with_floor(floor)
    return config if frame_count is None else config.replace(frame_count=frame_count)


def scenario_hash(config: ScenarioConfig) -> str:
    """A short stable name for a scenario: every parameter goes into it."""
    text = json.dumps(config.to_dict(), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]


def cached_dataset(config: ScenarioConfig, cache: Path, *, progress: bool = True) -> Dataset:
    """The dataset of ``config`` from ``cache/<hash>``, rendering it first if it is not there.

    Rendering goes to ``<hash>.partial`` and is renamed when complete, so an interrupted
    render is never mistaken for a dataset.
    """
    root = cache / scenario_hash(config)
    if not root.is_dir():
        cache.mkdir(parents=True, exist_ok=True)
        partial = cache / f"{root.name}.partial"
        if partial.exists():
            shutil.rmtree(partial)
        simulate(config, partial, progress=progress)
        partial.rename(root)
    try:
        dataset = read_dataset(root)
    except DatasetError as exc:
        raise ExperimentError(f"cached dataset {root} is unreadable ({exc}); delete it") from exc
    if dataset.truth is None or dataset.scenario != config:
        raise ExperimentError(
            f"cached dataset {root} does not hold seed {config.seed}'s scenario with truth; "
            "delete it to render it again"
        )
    return dataset
