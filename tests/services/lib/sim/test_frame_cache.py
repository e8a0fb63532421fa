"""A sim camera's frame cache gives back exactly the frames it would render, and is never
trusted blindly."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np
import pytest

from services.lib.sim import FrameCache, Scenario, ScenarioConfig


def _count(calls: list[int], scenario: Scenario, index: int) -> np.ndarray:
    calls.append(index)
    return scenario.render(index)


def test_a_cached_frame_equals_the_rendered_one_and_is_rendered_once(
    tmp_path: Path, small_config: Callable[..., ScenarioConfig]
) -> None:
    config = small_config(seed=5)
    scenario = Scenario(config)
    cache = FrameCache(tmp_path, config)
    calls: list[int] = []
    first = cache.frame(2, lambda: _count(calls, scenario, 2))
    again = FrameCache(tmp_path, config).frame(2, lambda: _count(calls, scenario, 2))
    assert calls == [2]
    assert np.array_equal(first, scenario.render(2)) and np.array_equal(again, first)
    # Another scenario has its own entries.
    other = small_config(seed=6)
    FrameCache(tmp_path, other).frame(2, lambda: _count(calls, Scenario(other), 2))
    assert calls == [2, 2]


def test_a_damaged_or_foreign_entry_is_rendered_again(
    tmp_path: Path, small_config: Callable[..., ScenarioConfig]
) -> None:
    config = small_config(seed=5)
    scenario = Scenario(config)
    FrameCache(tmp_path, config).frame(1, lambda: scenario.render(1))
    (entry,) = tmp_path.glob("*/000001.png")
    for damage in (b"not a png", entry.read_bytes()[:100]):
        entry.write_bytes(damage)
        calls: list[int] = []
        image = FrameCache(tmp_path, config).frame(1, partial(_count, calls, scenario, 1))
        assert calls == [1] and np.array_equal(image, scenario.render(1))


def test_the_variable_names_the_cache_and_unset_means_none(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, small_config: Callable[..., ScenarioConfig]
) -> None:
    monkeypatch.setenv(FrameCache.ENV, " ")
    assert FrameCache.from_env(small_config()) is None
    monkeypatch.setenv(FrameCache.ENV, str(tmp_path))
    assert FrameCache.from_env(small_config()) is not None
