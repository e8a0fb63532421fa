"""Exposure ends between gyro samples are interpolated, never rounded to a sample."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.lib.quality import Exposure, estimate_blur
from tests.services.lib.quality.quality_synth import camera, constant, sampled


def _yaw_step(t: np.ndarray) -> np.ndarray:
    yaw = np.where(t >= 0.2, 2.0, 0.0)
    return np.stack([np.zeros_like(t), yaw, np.zeros_like(t)], axis=1)


def test_sliding_the_exposure_across_samples_changes_blur_in_small_even_steps() -> None:
    gyro = sampled(_yaw_step)  # samples every 2 ms; the step is at 200 ms
    cam = camera()
    starts = range(150_000_000, 156_000_001, 100_000)  # 0.1 ms steps across three samples
    blur = np.array([estimate_blur(gyro, Exposure(s, 60_000_000), cam).blur_px for s in starts])
    steps = np.diff(blur)
    # 0.1 ms more of 2 rad/s at f = 600 px is ~0.12 px; rounding to samples would jump 2.4 px.
    assert np.all(steps > 0.0)
    assert steps.max() < 0.2
    assert steps.max() / steps.min() < 1.05


def test_an_exposure_inside_one_sample_interval_uses_the_interpolated_rates() -> None:
    gyro = constant((0.0, 3.0, 0.0))
    cam = camera()
    result = estimate_blur(gyro, Exposure(100_300_000, 1_000_000), cam)
    assert result.blur_px == pytest.approx(cam.fx_px * math.tan(3.0 * 1e-3), rel=1e-9)


def test_a_ramp_inside_one_sample_interval_is_integrated_exactly() -> None:
    # Two samples: 0 rad/s at 0 ms and 4 rad/s at 2 ms; the exposure is [0.5, 1.5] ms.
    from services.lib.quality import GyroSamples

    gyro = GyroSamples(
        np.array([0, 2_000_000]), np.array([[0.0, 0.0, 0.0], [0.0, 4.0, 0.0]]), 2_000_000
    )
    cam = camera()
    result = estimate_blur(gyro, Exposure(500_000, 1_000_000), cam)
    angle = 2.0 * 1e-3  # mean rate 2 rad/s over 1 ms
    assert result.blur_px == pytest.approx(cam.fx_px * math.tan(angle), rel=1e-9)


def test_a_zero_length_exposure_has_no_blur() -> None:
    result = estimate_blur(constant((1.0, 2.0, 3.0)), Exposure(100_000_000, 0), camera())
    assert result.blur_px == 0.0
    assert (result.dx_px, result.dy_px) == (0.0, 0.0)


def test_exposure_ends_on_samples_exactly() -> None:
    cam = camera()
    result = estimate_blur(constant((0.0, 1.0, 0.0)), Exposure(100_000_000, 20_000_000), cam)
    assert result.blur_px == pytest.approx(cam.fx_px * math.tan(0.02), rel=1e-9)
