"""The paper's centre estimate against closed forms (eq. 2), and what goes beyond it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.lib.quality import BlurMode, BlurOptions, Exposure, estimate_blur
from tests.services.lib.quality.quality_synth import (
    camera,
    constant,
    reference_blur,
    sampled,
    shaky,
)

T_NS = 60_000_000
T_S = T_NS * 1e-9
EXPOSURE = Exposure(100_000_000, T_NS)


def point(x_px: float, y_px: float) -> BlurOptions:
    return BlurOptions(mode=BlurMode.POINT, point_px=(x_px, y_px))


@pytest.mark.parametrize("rate", [0.5, 2.0, -3.0, 8.0])
def test_constant_yaw_blurs_the_centre_by_fx_tan_angle(rate: float) -> None:
    cam = camera()
    result = estimate_blur(constant((0.0, rate, 0.0)), EXPOSURE, cam)
    expected = cam.fx_px * math.tan(abs(rate) * T_S)
    assert result.blur_px == pytest.approx(expected, rel=1e-9)
    # Right-hand yaw about +y (down) turns the camera to the right: the scene moves left.
    assert result.dx_px == pytest.approx(-math.copysign(expected, rate), rel=1e-9)
    assert result.dy_px == pytest.approx(0.0, abs=1e-9)
    assert result.direction_rad == pytest.approx(0.0, abs=1e-9)
    assert result.anisotropy == pytest.approx(1.0)


@pytest.mark.parametrize("rate", [0.5, -2.0, 6.0])
def test_constant_pitch_blurs_the_centre_by_fy_tan_angle(rate: float) -> None:
    cam = camera()
    result = estimate_blur(constant((rate, 0.0, 0.0)), EXPOSURE, cam)
    expected = cam.fy_px * math.tan(abs(rate) * T_S)
    assert result.blur_px == pytest.approx(expected, rel=1e-9)
    assert result.dy_px == pytest.approx(math.copysign(expected, rate), rel=1e-9)
    assert result.dx_px == pytest.approx(0.0, abs=1e-9)
    assert result.direction_rad == pytest.approx(math.pi / 2)


def test_pure_roll_does_not_blur_the_centre() -> None:
    result = estimate_blur(constant((0.0, 0.0, 5.0)), EXPOSURE, camera())
    assert result.blur_px == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("radius_px", [50.0, 200.0, 400.0])
def test_pure_roll_blurs_off_centre_by_radius_times_angle(radius_px: float) -> None:
    cam = camera(fy_px=600.0)  # square pixels, so roll draws circles
    rate = 2.0
    gyro = constant((0.0, 0.0, rate))
    for angle in (0.0, 1.0, 2.5):
        x = cam.cx_px + radius_px * math.cos(angle)
        y = cam.cy_px + radius_px * math.sin(angle)
        result = estimate_blur(gyro, EXPOSURE, cam, point(x, y))
        assert result.blur_px == pytest.approx(radius_px * rate * T_S, rel=1e-5)


def test_a_rate_changing_sign_sums_path_length_not_net_displacement() -> None:
    # One full period of cos: the camera swings right, back, left and back.
    amplitude = 3.0
    omega = 2 * math.pi / T_S
    start_s = EXPOSURE.start_ns * 1e-9

    def rates(t: np.ndarray) -> np.ndarray:
        yaw = amplitude * np.cos(omega * (t - start_s))
        return np.stack([np.zeros_like(t), yaw, np.zeros_like(t)], axis=1)

    cam = camera()
    result = estimate_blur(sampled(rates), EXPOSURE, cam)
    swing = amplitude / omega  # largest angle reached
    assert abs(result.dx_px) < 0.5
    assert result.blur_px == pytest.approx(4 * cam.fx_px * math.tan(swing), rel=0.01)
    assert result.direction_rad == pytest.approx(0.0, abs=1e-6)


def test_gyro_to_camera_rotation_is_honoured() -> None:
    # Gyro mounted so its x axis is the camera's y axis: gyro-x rate is camera yaw.
    swap = (0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, -1.0)
    cam = camera(gyro_to_camera=swap)
    result = estimate_blur(constant((2.0, 0.0, 0.0)), EXPOSURE, cam)
    assert result.blur_px == pytest.approx(cam.fx_px * math.tan(2.0 * T_S), rel=1e-9)
    assert result.dy_px == pytest.approx(0.0, abs=1e-9)
    rolled = estimate_blur(constant((0.0, 0.0, 2.0)), EXPOSURE, cam)
    assert rolled.blur_px == pytest.approx(0.0, abs=1e-9)


def test_time_offset_moves_the_exposure_on_the_gyro_clock() -> None:
    # Yaw only during gyro time [200, 260) ms; the frame is exposed at camera time [100, 160).
    def rates(t: np.ndarray) -> np.ndarray:
        yaw = np.where((t >= 0.2) & (t < 0.26), 2.0, 0.0)
        return np.stack([np.zeros_like(t), yaw, np.zeros_like(t)], axis=1)

    gyro = sampled(rates, period_ns=1_000_000)
    exposure = Exposure(100_000_000, T_NS)
    still = estimate_blur(gyro, exposure, camera())
    assert still.blur_px == pytest.approx(0.0, abs=1e-9)
    moved = estimate_blur(gyro, exposure, camera(gyro_time_offset_ns=100_000_000))
    # Gyro window [200, 260) ms: 60 ms of yaw, give or take the 1 ms ramps at the edges.
    assert moved.blur_px == pytest.approx(600.0 * math.tan(2.0 * T_S), rel=0.02)
    early = estimate_blur(gyro, exposure, camera(gyro_time_offset_ns=130_000_000))
    assert early.blur_px == pytest.approx(moved.blur_px / 2, rel=0.05)


def test_shaky_motion_matches_a_sequential_reference_integration() -> None:
    cam = camera(gyro_to_camera=(0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0))
    gyro = sampled(shaky(seed=3, amplitude_rad_s=3.0))
    exposure = Exposure(123_456_789, 80_000_000)
    for x, y in [(cam.cx_px, cam.cy_px), (20.0, 30.0), (1000.0, 700.0)]:
        got = estimate_blur(gyro, exposure, cam, point(x, y)).blur_px
        want = reference_blur(gyro, cam, exposure.start_ns, exposure.end_ns, x, y)
        assert got == pytest.approx(want, rel=2e-3, abs=0.05)


def test_centre_mode_equals_the_general_path_at_the_principal_point() -> None:
    cam = camera()
    gyro = sampled(shaky(seed=5, amplitude_rad_s=4.0))
    for start in range(10_000_000, 300_000_000, 37_000_001):
        exposure = Exposure(start, 45_000_000)
        centre = estimate_blur(gyro, exposure, cam)
        general = estimate_blur(gyro, exposure, cam, point(cam.cx_px, cam.cy_px))
        assert centre.blur_px == pytest.approx(general.blur_px, rel=1e-9)
        assert centre.dx_px == pytest.approx(general.dx_px, rel=1e-9, abs=1e-9)
        assert centre.direction_rad == pytest.approx(general.direction_rad, abs=1e-9)


def test_turning_past_ninety_degrees_reports_infinite_blur() -> None:
    result = estimate_blur(constant((0.0, 30.0, 0.0)), EXPOSURE, camera())
    assert result.blur_px == math.inf
