"""Small scenario configurations that keep the simulator tests fast."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest

from services.lib.sim import ScenarioConfig


@pytest.fixture
def small_config() -> Callable[..., ScenarioConfig]:
    """Factory of small configurations: a few frames at reduced resolution with coarse
    textures, for tests about files and determinism rather than image detail."""
    base = ScenarioConfig(
        frame_count=4, width_px=256, height_px=192, wall_texel_m=0.016, board_texel_m=0.004
    )

    def make(**changes: Any) -> ScenarioConfig:
        return base.replace(**changes)

    return make
