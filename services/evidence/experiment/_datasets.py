"""Simulated approaches, rendered once per scenario and kept by the hash of its parameters."""

from __future__ import annotations

from pathlib import Path

from services.lib.sim import Dataset, DatasetError, ScenarioConfig, scenario_hash
from services.lib.sim import cached_dataset as sim_cached_dataset

from ._config import ExperimentError

__all__ = ["cached_dataset", "scenario_for", "scenario_hash"]


def scenario_for(seed: int, frame_count: int | None, floor: str = "default") -> ScenarioConfig:
    """The paper's approach for one seed: simulator defaults, only the seed, the floor
    preset (see ``ScenarioConfig.with_floor``) and for a smoke test the frame count changed."""
    config = ScenarioConfig(seed=seed).with_floor(floor)
    return config if frame_count is None else config.replace(frame_count=frame_count)


def cached_dataset(config: ScenarioConfig, cache: Path, *, progress: bool = True) -> Dataset:
    """The dataset of ``config`` from ``cache/<hash>``, rendering it first if it is not there
    (``services.lib.sim.cached_dataset``, which the demo's camera shares)."""
    try:
        return sim_cached_dataset(config, cache, progress=progress)
    except DatasetError as exc:
        raise ExperimentError(str(exc)) from exc
