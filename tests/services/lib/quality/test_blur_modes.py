"""Whole-frame and region summaries, rolling shutter and blur direction."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.lib.quality import BlurMode, BlurOptions, Exposure, Roi, estimate_blur
from tests.services.lib.quality.quality_synth import camera, constant, sampled, shaky

EXPOSURE = Exposure(100_000_000, 40_000_000)


def test_default_mode_is_the_paper_centre() -> None:
    assert BlurMode.DEFAULT is BlurMode.CENTER
    assert BlurOptions().mode is BlurMode.CENTER
    assert BlurMode("center") is BlurMode.CENTER


def test_under_roll_the_max_is_at_a_corner_and_the_mean_in_between() -> None:
    cam = camera(fy_px=600.0)
    gyro = constant((0.0, 0.0, 3.0))
    angle = 3.0 * 0.04
    mean = estimate_blur(gyro, EXPOSURE, cam, BlurOptions(mode=BlurMode.MEAN))
    worst = estimate_blur(gyro, EXPOSURE, cam, BlurOptions(mode=BlurMode.MAX))
    centre = estimate_blur(gyro, EXPOSURE, cam)
    # Farthest grid point from (cx, cy): the bottom-right cell centre of the 16x12 grid.
    corner = math.hypot(992.0 - cam.cx_px, 736.0 - cam.cy_px)
    assert centre.blur_px == pytest.approx(0.0, abs=1e-9)
    assert worst.blur_px == pytest.approx(corner * angle, rel=1e-4)
    assert 0.0 < mean.blur_px < worst.blur_px
    assert (worst.x_px, worst.y_px) == (992.0, 736.0)
    assert (mean.x_px, mean.y_px) == (512.0, 384.0)
    # Over a square around the centre, roll has no dominant direction and no net motion.
    square = Roi(cam.cx_px - 300, cam.cy_px - 300, 600, 600)
    around = estimate_blur(gyro, EXPOSURE, cam, BlurOptions(mode=BlurMode.MEAN, roi=square))
    assert around.anisotropy < 0.01
    assert around.dx_px == pytest.approx(0.0, abs=1e-9)
    assert around.dy_px == pytest.approx(0.0, abs=1e-9)


def test_a_roi_measures_only_its_own_rectangle() -> None:
    cam = camera(fy_px=600.0)
    gyro = constant((0.0, 0.0, 3.0))
    near = Roi(cam.cx_px - 10, cam.cy_px - 10, 20, 20)
    far = Roi(900.0, 600.0, 100.0, 100.0)
    small = estimate_blur(gyro, EXPOSURE, cam, BlurOptions(mode=BlurMode.MAX, roi=near))
    large = estimate_blur(gyro, EXPOSURE, cam, BlurOptions(mode=BlurMode.MAX, roi=far, grid=(4, 4)))
    assert small.blur_px < 2.0
    assert large.blur_px > 40.0
    assert 900.0 <= large.x_px <= 1000.0 and 600.0 <= large.y_px <= 700.0


def test_for_pure_yaw_every_mode_agrees_closely_with_the_centre() -> None:
    cam = camera()
    gyro = constant((0.0, 1.0, 0.0))
    centre = estimate_blur(gyro, EXPOSURE, cam).blur_px
    for mode in (BlurMode.MEAN, BlurMode.MAX):
        other = estimate_blur(gyro, EXPOSURE, cam, BlurOptions(mode=mode)).blur_px
        # Off-centre, yaw moves points faster (by up to 1 + x^2 + ... in normalised
        # coordinates, ~1.8 at these corners), never slower.
        assert centre <= other < 2.0 * centre


def test_blur_direction_follows_the_motion_axis() -> None:
    cam = camera(fy_px=600.0)
    # Equal pitch and yaw: the centre moves diagonally up-left (or down-right), 135 degrees.
    result = estimate_blur(constant((1.0, 1.0, 0.0)), EXPOSURE, cam)
    assert result.direction_rad == pytest.approx(3 * math.pi / 4, abs=1e-6)
    assert result.anisotropy == pytest.approx(1.0)
    assert math.atan2(result.dy_px, result.dx_px) == pytest.approx(3 * math.pi / 4, abs=1e-6)


def test_rolling_shutter_centre_is_the_centre_row_exposed_later() -> None:
    cam = camera(line_readout_ns=30_000)
    gyro = sampled(shaky(seed=11, amplitude_rad_s=3.0))
    rolling = estimate_blur(gyro, EXPOSURE, cam, BlurOptions(rolling_shutter=True))
    shift = round(cam.cy_px * cam.line_readout_ns)
    moved = Exposure(EXPOSURE.start_ns + shift, EXPOSURE.duration_ns)
    assert rolling.blur_px == pytest.approx(estimate_blur(gyro, moved, cam).blur_px, rel=1e-6)
    assert rolling.blur_px != pytest.approx(estimate_blur(gyro, EXPOSURE, cam).blur_px, rel=1e-3)


def test_rolling_shutter_rows_see_different_motion() -> None:
    # Yaw only starts 20 ms after row 0's exposure ends: the bottom rows catch it.
    def rates(t: np.ndarray) -> np.ndarray:
        yaw = np.where(t >= 0.16, 2.0, 0.0)
        return np.stack([np.zeros_like(t), yaw, np.zeros_like(t)], axis=1)

    cam = camera(line_readout_ns=50_000)  # row 767 starts 38 ms late
    gyro = sampled(rates, period_ns=1_000_000)
    exposure = Exposure(100_000_000, 40_000_000)
    top = BlurOptions(mode=BlurMode.POINT, point_px=(511.5, 10.0), rolling_shutter=True)
    bottom = BlurOptions(mode=BlurMode.POINT, point_px=(511.5, 760.0), rolling_shutter=True)
    assert estimate_blur(gyro, exposure, cam, top).blur_px == pytest.approx(0.0, abs=1e-9)
    assert estimate_blur(gyro, exposure, cam, bottom).blur_px > 10.0
    worst = estimate_blur(gyro, exposure, cam, BlurOptions(mode=BlurMode.MAX, rolling_shutter=True))
    assert worst.y_px > 700.0
    assert estimate_blur(gyro, exposure, cam).blur_px == pytest.approx(0.0, abs=1e-9)


def test_rolling_shutter_without_line_time_is_a_global_shutter() -> None:
    cam = camera()
    gyro = sampled(shaky(seed=2))
    options = BlurOptions(mode=BlurMode.MEAN, rolling_shutter=True)
    plain = BlurOptions(mode=BlurMode.MEAN)
    assert estimate_blur(gyro, EXPOSURE, cam, options) == estimate_blur(gyro, EXPOSURE, cam, plain)


def test_rolling_and_global_paths_agree_when_rows_share_a_window() -> None:
    # A tiny line time exercises the rolling code with (almost) the global windows.
    cam = camera(line_readout_ns=1)
    gyro = sampled(shaky(seed=4, amplitude_rad_s=3.0))
    for mode in (BlurMode.MEAN, BlurMode.MAX):
        rolled = estimate_blur(gyro, EXPOSURE, cam, BlurOptions(mode=mode, rolling_shutter=True))
        plain = estimate_blur(gyro, EXPOSURE, cam, BlurOptions(mode=mode))
        assert rolled.blur_px == pytest.approx(plain.blur_px, rel=1e-4)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"mode": BlurMode.POINT}, "needs point_px"),
        ({"grid": (0, 4)}, "grid must be"),
        ({"max_gap_ns": 0}, "max_gap_ns must be positive"),
    ],
)
def test_bad_options_are_refused(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        BlurOptions(**kwargs)  # type: ignore[arg-type]


def test_an_empty_roi_is_refused() -> None:
    with pytest.raises(ValueError, match="positive size"):
        Roi(0.0, 0.0, 0.0, 10.0)
