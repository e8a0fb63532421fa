"""Motion-blur quality of frames from gyro rates (paper §4.2-4.3), and what goes beyond it.

The mediator calls ``frame_quality`` for every frame (``estimate_blur``, then the blur
mapped to a quality by ``quality``); its policies (``services.lib.decisions``) apply the
acceptance test ``accept``.
"""

from ._accept import DEFAULT_B0_PX, accept, frame_quality, quality
from ._blur import BlurEstimate, BlurMode, BlurOptions, Roi, estimate_blur
from ._errors import CalibrationError, CoverageError, QualityInputError
from ._exposure import Exposure
from ._gyro import GYRO_DTYPE, GyroSamples
from ._offset import OffsetEstimate, estimate_time_offset, laplacian_variance, rank_correlation

__all__ = [
    "DEFAULT_B0_PX",
    "GYRO_DTYPE",
    "BlurEstimate",
    "BlurMode",
    "BlurOptions",
    "CalibrationError",
    "CoverageError",
    "Exposure",
    "GyroSamples",
    "OffsetEstimate",
    "QualityInputError",
    "Roi",
    "accept",
    "estimate_blur",
    "estimate_time_offset",
    "frame_quality",
    "laplacian_variance",
    "quality",
    "rank_correlation",
]
