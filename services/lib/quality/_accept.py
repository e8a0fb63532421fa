"""Quality from blur (paper eq. 3, with a scale) and the acceptance test (paper §4.3).

The policies that apply the test, and the load it compares against, are
``services.lib.decisions``.
"""

from __future__ import annotations

import math
import sys

import numpy as np

from services.lib.camera_model import CameraModel

from ._blur import DEFAULT_OPTIONS, BlurOptions, estimate_blur
from ._errors import QualityInputError
from ._exposure import Exposure
from ._gyro import GyroSamples

DEFAULT_B0_PX = 5.0
"""Blur scale b0 of q = exp(-blur_px / b0_px), in pixels.

The paper's literal q = e^-b with b in pixels (b0 = 1) rejects so much at 1024x768,
f ~ 558 px, that the processor idles and recognition ends up worse than dropping frames at
random. A scale near the blur at which the target's recognition rate halves works; that is
about 4-6 px for ArUco markers at that size. ``derive_b0`` measures it from recorded frames.
"""

# q never reaches 0, so an idle consumer (load 0) still accepts any frame (paper §4.3).
_MIN_Q = sys.float_info.min


def _check_unit(name: str, value: float, *, open_low: bool = False) -> None:
    low_ok = value > 0.0 if open_low else value >= 0.0
    if not (low_ok and value <= 1.0):
        interval = "(0, 1]" if open_low else "[0, 1]"
        raise QualityInputError(f"{name} must be in {interval}, got {value!r}")


def quality(blur_px: float, b0_px: float = DEFAULT_B0_PX) -> float:
    """q = exp(-blur_px / b0_px) in (0, 1]; 1 is a still camera."""
    if not blur_px >= 0.0:
        raise QualityInputError(f"blur_px must be >= 0 (inf allowed), got {blur_px!r}")
    if not (b0_px > 0.0 and math.isfinite(b0_px)):
        raise QualityInputError(f"b0_px must be a positive finite number of pixels, got {b0_px!r}")
    return max(math.exp(-blur_px / b0_px), _MIN_Q)


def frame_quality(
    gyro: GyroSamples,
    exposure: Exposure,
    camera: CameraModel,
    b0_px: float = DEFAULT_B0_PX,
    options: BlurOptions = DEFAULT_OPTIONS,
) -> tuple[float, float]:
    """(blur_px, quality) of one frame: the one way from a frame to its quality, used by the
    mediator and by the experiment's replay.

    CoverageError when ``gyro`` does not cover ``exposure``; QualityInputError when the blur
    is not a number (INF or NaN in the camera model) or an input is invalid.
    """
    with np.errstate(all="ignore"):  # a NaN result is checked below, not warned about
        blur = float(estimate_blur(gyro, exposure, camera, options).blur_px)
    if not blur >= 0.0:
        raise QualityInputError(f"blur of {blur} px")
    return blur, quality(blur, b0_px)


def accept(q: float, load: float, q_min: float = 0.0) -> bool:
    """The acceptance test: a frame passes iff q > load and q >= q_min.

    An idle consumer (load 0) takes every frame; a full one (load 1) takes none.
    """
    _check_unit("q", q, open_low=True)
    _check_unit("load", load)
    _check_unit("q_min", q_min)
    return q > load and q >= q_min
