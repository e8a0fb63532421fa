from __future__ import annotations

import numpy as np
import pytest

from middleware import ConfigError
from services.lib.sim import Bump, ScenarioConfig


def test_defaults_follow_the_paper() -> None:
    config = ScenarioConfig()
    assert config.focal_px == pytest.approx(558.5, abs=0.1)
    assert config.frame_count == 319
    assert config.frame_period_ns == 66_666_667
    assert config.exposure_ns == 60_000_000
    assert config.end_distance_m == pytest.approx(1.5, abs=0.1)


def test_gyro_to_camera_is_a_rotation_with_the_optical_axis_tilted_down() -> None:
    r = ScenarioConfig(camera_tilt_deg=5.0).rotation_gyro_to_camera
    assert np.allclose(r @ r.T, np.eye(3))
    assert np.linalg.det(r) == pytest.approx(1.0)
    optical_axis_in_body = r.T @ np.array([0.0, 0.0, 1.0])  # x forward, y left, z up
    assert optical_axis_in_body[0] > 0.99
    assert np.degrees(np.arcsin(-optical_axis_in_body[2])) == pytest.approx(5.0)
    # Image right is the robot's right; image down is (mostly) the robot's down.
    assert np.allclose(r.T @ [1.0, 0, 0], [0, -1.0, 0])
    assert (r.T @ [0, 1.0, 0])[2] < -0.99


def test_camera_model_carries_offset_and_mounting() -> None:
    config = ScenarioConfig(gyro_time_offset_ns=-1_000_000)
    camera = config.camera_model()
    assert camera.gyro_time_offset_ns == -1_000_000
    assert np.allclose(camera.rotation_gyro_to_camera, config.rotation_gyro_to_camera)
    assert (camera.cx_px, camera.cy_px) == (511.5, 383.5)


def test_replace_overrides_and_validates() -> None:
    config = ScenarioConfig().replace(exposure_ns=30_000_000, seed=7)
    assert (config.exposure_ns, config.seed) == (30_000_000, 7)
    with pytest.raises(ConfigError, match=r"unknown scenario parameter.*exposure_ms"):
        ScenarioConfig().replace(exposure_ms=30)
    with pytest.raises(ConfigError, match="longer than the frame period"):
        ScenarioConfig().replace(exposure_ns=80_000_000)
    with pytest.raises(ConfigError, match="speed_m_s must be >= 0"):
        ScenarioConfig(speed_m_s=-1.0)
    with pytest.raises(ConfigError, match="approach ends"):
        ScenarioConfig(start_distance_m=3.0)


def test_dict_round_trip_keeps_explicit_bumps() -> None:
    config = ScenarioConfig(seed=3, bumps=(Bump(1.0, 0.01, 0.1, "left"),))
    assert ScenarioConfig.from_dict(config.to_dict()) == config
    with pytest.raises(ConfigError, match="track 'middle'"):
        Bump(1.0, track="middle")  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("name", "value", "message"),
    [
        ("seed", "abc", "seed must be an integer, got 'abc'"),  # a comparison's TypeError
        ("frame_count", True, "frame_count must be an integer, got true"),  # 1 frame rendered
        ("exposure_ns", 1.5, "exposure_ns must be an integer, got 1.5"),
        ("wall_texel_m", None, "wall_texel_m must be a number, got null"),
    ],
)
def test_a_parameter_of_the_wrong_type_is_named(name: str, value: object, message: str) -> None:
    """`framegate simulate --set seed=abc` said `bad scenario parameter: '<' not supported
    between instances of 'str' and 'int'`; `--set frame_count=true` rendered 1 frame."""
    with pytest.raises(ConfigError, match=f"^scenario parameter {message}$"):
        ScenarioConfig.from_dict({name: value})
