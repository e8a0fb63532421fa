"""Quality from blur (eq. 3 with a scale) and the acceptance test (paper §4.3)."""

from __future__ import annotations

import math

import pytest

from services.lib.quality import DEFAULT_B0_PX, QualityInputError, accept, quality


def test_quality_is_exp_of_minus_blur_over_b0() -> None:
    assert quality(0.0) == 1.0
    assert quality(5.0, 5.0) == pytest.approx(math.exp(-1.0))
    assert quality(2.0, 1.0) == pytest.approx(math.exp(-2.0))  # the paper's literal e^-b
    assert DEFAULT_B0_PX == 5.0
    assert quality(DEFAULT_B0_PX) == pytest.approx(1 / math.e)


def test_quality_never_reaches_zero() -> None:
    assert quality(math.inf) > 0.0
    assert quality(1e6, 1.0) > 0.0


@pytest.mark.parametrize(
    ("blur", "b0", "message"),
    [
        (-1.0, 5.0, "blur_px must be >= 0"),
        (math.nan, 5.0, "blur_px must be >= 0"),
        (1.0, 0.0, "b0_px must be a positive finite"),
        (1.0, math.inf, "b0_px must be a positive finite"),
    ],
)
def test_quality_refuses_bad_numbers(blur: float, b0: float, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        quality(blur, b0)


def test_accept_iff_quality_beats_load_and_meets_the_minimum() -> None:
    assert accept(0.5, 0.4)
    assert not accept(0.4, 0.4)
    assert not accept(0.3, 0.4)
    assert accept(0.5, 0.0, q_min=0.5)
    assert not accept(0.49, 0.0, q_min=0.5)


def test_an_idle_consumer_takes_even_heavily_blurred_frames() -> None:
    assert accept(quality(1000.0), 0.0)


@pytest.mark.parametrize(
    ("q", "load", "q_min", "message"),
    [
        (0.0, 0.5, 0.0, r"q must be in \(0, 1\]"),
        (1.5, 0.5, 0.0, r"q must be in \(0, 1\]"),
        (float("nan"), 0.5, 0.0, r"q must be in \(0, 1\]"),
        (0.5, -0.1, 0.0, r"load must be in \[0, 1\], got -0.1"),
        (0.5, 1.1, 0.0, r"load must be in \[0, 1\]"),
        (0.5, 0.5, 2.0, r"q_min must be in \[0, 1\]"),
    ],
)
def test_accept_refuses_out_of_range_values(
    q: float, load: float, q_min: float, message: str
) -> None:
    with pytest.raises(QualityInputError, match=message):
        accept(q, load, q_min)
