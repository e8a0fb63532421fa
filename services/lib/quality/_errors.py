"""The quality library's errors: its part of framegate's one exception tree."""

from __future__ import annotations

from middleware import FramegateError


class QualityInputError(FramegateError, ValueError):
    """A frame, gyro batch, exposure or option given to the quality library is invalid.

    A ``ValueError`` too, so code that validated with ``ValueError`` keeps working.
    """


class CoverageError(FramegateError):
    """Gyro samples do not cover a frame's exposure (no data, or a gap longer than allowed)."""


class CalibrationError(FramegateError, ValueError):
    """Recorded data cannot determine a calibration value (b0, time offset)."""
