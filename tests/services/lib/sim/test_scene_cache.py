"""The scenario cache gives back exactly what building computes, and is never trusted blindly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from services.lib.sim import ScenarioConfig
from services.lib.sim._scene import Scene
from services.lib.sim._scene_cache import cache_dir

SMALL = ScenarioConfig(seed=4, wall_texel_m=0.05, floor_texel_m=0.05)


@pytest.fixture(autouse=True)
def _private_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))


def _textures(scene: Scene) -> list[np.ndarray]:
    return [scene.wall.levels[0], scene.floor.levels[0]]


def test_a_cached_scene_equals_a_built_one() -> None:
    built = Scene.build(SMALL)
    assert list(cache_dir().glob("*.npz")), "the first build stores an entry"
    cached = Scene.build(SMALL)
    for a, b in zip(_textures(built), _textures(cached), strict=True):
        assert np.array_equal(a, b)


def test_a_damaged_entry_is_rebuilt_not_used() -> None:
    built = Scene.build(SMALL)
    for entry in cache_dir().glob("*.npz"):
        entry.write_bytes(b"not an npz file")
    again = Scene.build(SMALL)
    for a, b in zip(_textures(built), _textures(again), strict=True):
        assert np.array_equal(a, b)


def test_another_seed_does_not_share_an_entry() -> None:
    Scene.build(SMALL)
    other = Scene.build(ScenarioConfig(seed=5, wall_texel_m=0.05, floor_texel_m=0.05))
    assert len(list(cache_dir().glob("*.npz"))) == 2
    assert not np.array_equal(other.wall.levels[0], Scene.build(SMALL).wall.levels[0])


def test_cached_motion_equals_integrated_motion() -> None:
    from services.lib.sim._motion import Motion

    t = np.linspace(0.0, 1.0, 257)
    integrated = Motion(SMALL)
    assert list(cache_dir().glob("motion-*.npz")), "the first build stores the knots"
    cached = Motion(SMALL)
    for got, want in zip(integrated.camera_pose(t), cached.camera_pose(t), strict=True):
        assert np.array_equal(got, want)  # rotations (pitch, roll) and centres (heave)
    assert np.array_equal(integrated.body_rate_rad_s(t), cached.body_rate_rad_s(t))


def test_motion_matches_scipys_cubic_hermite_spline() -> None:
    from scipy.interpolate import CubicHermiteSpline

    from services.lib.sim._motion import _hermite

    rng = np.random.default_rng(7)
    knots = np.cumsum(rng.uniform(0.1, 1.0, 40))
    values, rates = rng.normal(size=(40, 3)), rng.normal(size=(40, 3))
    spline = CubicHermiteSpline(knots, values, rates, axis=0, extrapolate=False)
    t = np.concatenate([rng.uniform(knots[0] - 1, knots[-1] + 1, 500), knots])
    for ours, theirs in (
        (_hermite(knots, values, rates, t, derivative=False), spline(t)),
        (_hermite(knots, values, rates, t, derivative=True), spline.derivative()(t)),
    ):
        assert np.array_equal(np.isnan(ours), np.isnan(theirs))
        assert np.allclose(ours, theirs, rtol=0, atol=1e-12, equal_nan=True)
