"""Properties that hold for every input (hypothesis)."""

from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st

from services.lib.quality import BlurMode, BlurOptions, Exposure, accept, estimate_blur, quality
from tests.services.lib.quality.quality_synth import camera, constant

rates = st.tuples(*[st.floats(-6.0, 6.0)] * 3)
starts = st.integers(20_000_000, 200_000_000)
durations = st.integers(0, 100_000_000)
CAMERA = camera()
MODES = st.sampled_from(
    [
        BlurOptions(),
        BlurOptions(mode=BlurMode.POINT, point_px=(100.0, 650.0)),
        BlurOptions(mode=BlurMode.MAX, grid=(4, 3)),
        BlurOptions(mode=BlurMode.MEAN, grid=(4, 3)),
    ]
)


@settings(max_examples=60, deadline=None)
@given(rate=rates, start=starts, duration=durations, options=MODES)
def test_blur_is_never_negative(
    rate: tuple[float, float, float], start: int, duration: int, options: BlurOptions
) -> None:
    result = estimate_blur(constant(rate), Exposure(start, duration), CAMERA, options)
    assert result.blur_px >= 0.0
    assert 0.0 <= result.direction_rad < math.pi
    assert 0.0 <= result.anisotropy <= 1.0


@settings(max_examples=60, deadline=None)
@given(rate=rates, start=starts, short=durations, extra=st.integers(0, 50_000_000))
def test_blur_does_not_shrink_with_longer_exposure_at_constant_rates(
    rate: tuple[float, float, float], start: int, short: int, extra: int
) -> None:
    gyro = constant(rate)
    shorter = estimate_blur(gyro, Exposure(start, short), CAMERA).blur_px
    longer = estimate_blur(gyro, Exposure(start, short + extra), CAMERA).blur_px
    assert longer >= shorter - 1e-9 * max(1.0, shorter)


@settings(deadline=None)  # no wall-clock bound per example
@given(blur=st.floats(0.0, math.inf), b0=st.floats(0.01, 1e6))
def test_quality_is_in_the_unit_interval_open_at_zero(blur: float, b0: float) -> None:
    q = quality(blur, b0)
    assert 0.0 < q <= 1.0


@settings(deadline=None)  # no wall-clock bound per example
@given(q=st.floats(0.0, 1.0, exclude_min=True))
def test_an_idle_consumer_accepts_every_frame_of_positive_quality(q: float) -> None:
    assert accept(q, 0.0)


@settings(deadline=None)  # no wall-clock bound per example
@given(q=st.floats(0.0, 1.0, exclude_min=True))
def test_a_full_consumer_accepts_nothing(q: float) -> None:
    assert not accept(q, 1.0)
