"""derive_b0: the blur at which recognition halves, from recorded frames."""

from __future__ import annotations

import numpy as np
import pytest

from services.lib.calibrate import derive_b0
from services.lib.quality import CalibrationError


def _frames(count: int, halving_px: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Recognition falls as 0.9 / (1 + (b / halving)^3): exactly half at ``halving``."""
    rng = np.random.default_rng(seed)
    blur = rng.uniform(0.0, 5 * halving_px, count)
    rate = 0.9 / (1.0 + (blur / halving_px) ** 3)
    return blur, rng.random(count) < rate


@pytest.mark.parametrize("halving_px", [2.0, 5.0, 12.0])
def test_recovers_a_known_halving_blur(halving_px: float) -> None:
    blur, recognized = _frames(3000, halving_px, seed=1)
    assert derive_b0(blur, recognized) == pytest.approx(halving_px, rel=0.1)


def test_stays_reasonable_with_few_frames() -> None:
    estimates = [derive_b0(*_frames(40, 5.0, seed)) for seed in range(20)]
    assert 3.0 < float(np.median(estimates)) < 7.5
    assert all(1.0 < b0 < 15.0 for b0 in estimates)


def test_ties_in_blur_are_pooled() -> None:
    blur = np.repeat([0.0, 2.0, 4.0, 6.0, 8.0], 20)
    recognized = np.concatenate([np.ones(20), np.ones(20), np.r_[np.ones(10), np.zeros(10)]])
    recognized = np.concatenate([recognized, np.zeros(40)]).astype(bool)
    assert derive_b0(blur, recognized) == pytest.approx(4.0)


def test_too_few_frames_cannot_determine_b0() -> None:
    with pytest.raises(CalibrationError, match=r"5 frames are too few.*at least 20"):
        derive_b0([0, 1, 2, 3, 4], [True] * 5)


def test_no_recognised_sharp_frame_cannot_determine_b0() -> None:
    with pytest.raises(CalibrationError, match="none of the 5 sharpest frames"):
        derive_b0(np.arange(30.0), np.zeros(30, bool))


def test_recognition_that_never_halves_cannot_determine_b0() -> None:
    blur, _ = _frames(200, 5.0, seed=2)
    with pytest.raises(CalibrationError, match=r"never falls to half.*record frames with more"):
        derive_b0(blur / 10, blur < 100)


def test_mismatched_or_bad_inputs_are_refused() -> None:
    with pytest.raises(ValueError, match="3 blur values but 2 recognition flags"):
        derive_b0([1.0, 2.0, 3.0], [True, False])
    with pytest.raises(ValueError, match="finite and >= 0"):
        derive_b0([1.0, -2.0, 3.0], [True, False, True])


def test_calibration_errors_are_framegate_errors() -> None:
    from middleware import FramegateError

    assert issubclass(CalibrationError, FramegateError)
