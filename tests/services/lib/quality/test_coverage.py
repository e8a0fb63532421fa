"""Missing gyro data raises CoverageError naming the exposure and what is missing."""

from __future__ import annotations

import numpy as np
import pytest

from services.lib.quality import (
    BlurMode,
    BlurOptions,
    CoverageError,
    Exposure,
    GyroSamples,
    estimate_blur,
)
from tests.services.lib.quality.quality_synth import camera, constant

EXPOSURE = Exposure(100_000_000, 60_000_000)


def test_no_samples_raise() -> None:
    with pytest.raises(CoverageError, match=r"exposure \[100000000, 160000000\].*0 gyro samples"):
        estimate_blur(GyroSamples.empty(), EXPOSURE, camera())


def test_a_single_sample_raises() -> None:
    one = GyroSamples(np.array([100_000_000]), np.zeros((1, 3)))
    with pytest.raises(CoverageError, match="is 1 gyro sample"):
        estimate_blur(one, EXPOSURE, camera())


def test_an_exposure_starting_before_the_first_sample_raises() -> None:
    gyro = constant((0.0, 1.0, 0.0), start_ns=110_000_000)
    with pytest.raises(CoverageError, match=r"start at 110000000 ns, 10\.000 ms after"):
        estimate_blur(gyro, EXPOSURE, camera())


def test_an_exposure_ending_after_the_last_sample_raises() -> None:
    gyro = constant((0.0, 1.0, 0.0), end_ns=150_000_000)
    with pytest.raises(CoverageError, match=r"end at 150000000 ns, 10\.000 ms before"):
        estimate_blur(gyro, EXPOSURE, camera())


def test_the_time_offset_decides_coverage() -> None:
    gyro = constant((0.0, 1.0, 0.0), start_ns=0, end_ns=170_000_000)
    estimate_blur(gyro, EXPOSURE, camera())
    with pytest.raises(CoverageError, match=r"\[120000000, 180000000\] ns \(gyro clock, offset "):
        estimate_blur(gyro, EXPOSURE, camera(gyro_time_offset_ns=20_000_000))


def _with_gap(gap_from_ns: int, gap_to_ns: int) -> GyroSamples:
    full = constant((0.0, 1.0, 0.0))
    keep = (full.t_ns <= gap_from_ns) | (full.t_ns >= gap_to_ns)
    return GyroSamples(full.t_ns[keep], full.rates_rad_s[keep], 2_000_000)


def test_a_gap_inside_the_exposure_raises() -> None:
    gyro = _with_gap(120_000_000, 130_000_000)
    with pytest.raises(
        CoverageError,
        match=r"gap of 10\.000 ms between the gyro samples at 120000000 and 130000000",
    ):
        estimate_blur(gyro, EXPOSURE, camera())


def test_a_gap_around_the_exposure_start_raises() -> None:
    gyro = _with_gap(96_000_000, 104_000_000)
    with pytest.raises(CoverageError, match=r"gap of 8\.000 ms"):
        estimate_blur(gyro, EXPOSURE, camera())


def test_a_gap_of_two_periods_is_allowed_but_not_more() -> None:
    estimate_blur(_with_gap(120_000_000, 124_000_000), EXPOSURE, camera())
    with pytest.raises(CoverageError, match=r"gap of 6\.000 ms"):
        estimate_blur(_with_gap(120_000_000, 126_000_000), EXPOSURE, camera())


def test_a_gap_outside_the_exposure_is_harmless() -> None:
    estimate_blur(_with_gap(20_000_000, 60_000_000), EXPOSURE, camera())


def test_max_gap_ns_overrides_the_nominal_rule() -> None:
    gyro = _with_gap(120_000_000, 130_000_000)
    options = BlurOptions(max_gap_ns=15_000_000)
    assert estimate_blur(gyro, EXPOSURE, camera(), options).blur_px > 0
    strict = BlurOptions(max_gap_ns=5_000_000, mode=BlurMode.MAX)
    with pytest.raises(CoverageError, match=r"longer than the allowed 5\.000 ms"):
        estimate_blur(gyro, EXPOSURE, camera(), strict)


def test_rolling_shutter_needs_the_last_row_covered_too() -> None:
    cam = camera(line_readout_ns=30_000)  # last row starts ~23 ms after the first
    gyro = constant((0.0, 1.0, 0.0), end_ns=170_000_000)
    estimate_blur(gyro, EXPOSURE, cam)
    with pytest.raises(CoverageError, match="end at 170000000 ns"):
        estimate_blur(gyro, EXPOSURE, cam, BlurOptions(rolling_shutter=True, mode=BlurMode.MAX))
