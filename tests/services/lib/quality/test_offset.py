"""Camera-to-gyro time offset from a recorded sequence, and the sharpness signal."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.lib.quality import (
    CalibrationError,
    Exposure,
    GyroSamples,
    estimate_blur,
    estimate_time_offset,
    laplacian_variance,
    rank_correlation,
)
from tests.services.lib.quality.quality_synth import camera, sampled, shaky


def test_laplacian_variance_falls_as_an_image_blurs() -> None:
    rng = np.random.default_rng(0)
    image = (rng.random((120, 160)) * 255).astype(np.uint8)
    sharpness = [laplacian_variance(image)]
    for length in (3, 7, 15):
        kernel = np.full((1, length), 1.0 / length)
        sharpness.append(laplacian_variance(cv2.filter2D(image, -1, kernel)))
    assert sharpness == sorted(sharpness, reverse=True)
    colour = np.dstack([image] * 3)
    assert laplacian_variance(colour) == pytest.approx(sharpness[0], rel=1e-3)
    with pytest.raises(ValueError, match="expected an"):
        laplacian_variance(np.zeros((2, 2, 2)))


def test_rank_correlation_is_spearman() -> None:
    assert rank_correlation([1, 2, 3, 4], [10, 20, 30, 1000]) == pytest.approx(1.0)
    assert rank_correlation([1, 2, 3, 4], [4, 3, 2, 1]) == pytest.approx(-1.0)
    assert rank_correlation([1, 1, 2, 2], [1, 2, 3, 4]) == pytest.approx(0.8944271909999159)
    assert np.isnan(rank_correlation([1, 1, 1], [1, 2, 3]))


def _sequence(true_offset_ns: int, seed: int) -> tuple[list[Exposure], GyroSamples, np.ndarray]:
    """Frames at 30/s whose sharpness follows the true blur, with noise."""
    gyro = sampled(shaky(seed, amplitude_rad_s=2.0), end_ns=4_200_000_000)
    exposures = [Exposure(100_000_000 + i * 33_333_333, 20_000_000) for i in range(110)]
    truth = camera(gyro_time_offset_ns=true_offset_ns)
    blur = np.array([estimate_blur(gyro, e, truth).blur_px for e in exposures])
    rng = np.random.default_rng(seed)
    sharpness = 100.0 * np.exp(-blur / 5.0) + rng.normal(0.0, 1.0, blur.size)
    return exposures, gyro, sharpness


def test_recovers_a_known_offset_from_synthetic_frames() -> None:
    exposures, gyro, sharpness = _sequence(true_offset_ns=7_000_000, seed=8)
    found = estimate_time_offset(
        exposures, gyro, sharpness, camera(), search_ns=20_000_000, step_ns=1_000_000
    )
    assert abs(found.offset_ns - 7_000_000) <= 1_000_000
    assert found.score == pytest.approx(found.scores.max())
    assert found.candidates_ns.size == found.scores.size == 41
    assert found.frames_used == len(exposures)
    # The curve peaks at the truth: far offsets explain the sharpness worse.
    assert found.scores[0] < found.score - 0.1 and found.scores[-1] < found.score - 0.1


def test_explicit_candidates_and_frames_outside_the_gyro_are_left_out() -> None:
    exposures, gyro, sharpness = _sequence(true_offset_ns=-4_000_000, seed=9)
    early = [Exposure(0, 20_000_000), *exposures]  # before the first gyro sample at -4 ms
    found = estimate_time_offset(
        early, gyro, np.r_[50.0, sharpness], camera(), candidates_ns=[-8_000_000, -4_000_000, 0]
    )
    assert found.offset_ns == -4_000_000
    assert found.frames_used == len(exposures)


def test_no_motion_cannot_determine_the_offset() -> None:
    still = sampled(lambda t: np.zeros((t.size, 3)))
    exposures = [Exposure(50_000_000 + i * 20_000_000, 10_000_000) for i in range(10)]
    with pytest.raises(CalibrationError, match="same for every frame"):
        estimate_time_offset(exposures, still, np.arange(10.0), camera(), search_ns=2_000_000)


def test_too_few_covered_frames_cannot_determine_the_offset() -> None:
    gyro = sampled(shaky(1), end_ns=100_000_000)
    exposures = [Exposure(20_000_000 + i * 10_000_000, 5_000_000) for i in range(10)]
    with pytest.raises(CalibrationError, match=r"only \d+ of 10 frames are covered"):
        estimate_time_offset(exposures, gyro, np.arange(10.0), camera(), search_ns=30_000_000)
