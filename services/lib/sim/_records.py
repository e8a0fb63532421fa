"""Typed records of a (simulated or recorded) camera/gyro dataset."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True, slots=True)
class FrameInfo:
    """One frame's timing on the camera clock, ns since the dataset epoch."""

    frame_id: int
    exposure_start_ns: int
    exposure_ns: int


@dataclass(frozen=True, slots=True)
class GyroTrace:
    """Gyro samples: ``t_ns`` (n,) int64 on the gyro clock; ``rate_rad_s`` (n, 3) float64
    in the gyro frame. Arrays are read-only."""

    t_ns: np.ndarray
    rate_rad_s: np.ndarray

    def __post_init__(self) -> None:
        t = np.asarray(self.t_ns, dtype=np.int64)
        rate = np.asarray(self.rate_rad_s, dtype=np.float64)
        if t.ndim != 1 or rate.shape != (len(t), 3):
            raise ValueError(
                f"gyro needs t_ns (n,) and rate_rad_s (n, 3), got {t.shape}, {rate.shape}"
            )
        if len(t) > 1 and not (np.diff(t) > 0).all():
            raise ValueError("gyro timestamps must increase strictly")
        t.flags.writeable = False
        rate.flags.writeable = False
        object.__setattr__(self, "t_ns", t)
        object.__setattr__(self, "rate_rad_s", rate)

    def __len__(self) -> int:
        return len(self.t_ns)

    @property
    def rate_hz(self) -> float:
        """Mean sample rate."""
        if len(self.t_ns) < 2:
            return 0.0
        return float((len(self.t_ns) - 1) * 1e9 / (self.t_ns[-1] - self.t_ns[0]))

    def between(self, start_ns: int, end_ns: int) -> GyroTrace:
        """Samples with start_ns <= t_ns < end_ns (gyro clock)."""
        lo, hi = np.searchsorted(self.t_ns, [start_ns, end_ns])
        return GyroTrace(self.t_ns[lo:hi], self.rate_rad_s[lo:hi])


@dataclass(frozen=True, slots=True)
class MarkerTruth:
    """Ground truth for one board marker in one frame.

    ``in_view``: all four corners inside the image at exposure midpoint. ``size_px``: mean
    projected side length then. ``blur_px``: length of the image path its centre traces over
    the exposure. ``detected_sharp``: found by ``detect_markers`` in a blur-free render of the
    midpoint pose (with the same lens blur and sensor noise), i.e. recognizable in principle;
    None when not checked.
    """

    name: str
    marker_id: int
    in_view: bool
    size_px: float
    blur_px: float
    centre_px: tuple[float, float]
    detected_sharp: bool | None


@dataclass(frozen=True, slots=True)
class FrameTruth:
    """Ground truth for one frame.

    ``centre_blur_px``: the world point that projects to the principal point at exposure start
    (first row of a rolling shutter: the centre row's start); the summed length of its image
    path over the exposure under the true pose, rotation and translation. ``substeps``: how
    many instants the renderer averaged. ``camera_distance_m``: camera to wall at midpoint.
    """

    frame_id: int
    centre_blur_px: float
    camera_distance_m: float
    substeps: int
    markers: tuple[MarkerTruth, ...]

    def marker(self, name: str) -> MarkerTruth:
        """The truth of one marker by name."""
        for marker in self.markers:
            if marker.name == name:
                return marker
        raise KeyError(name)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FrameTruth:
        """Inverse of :meth:`to_dict`."""
        markers = tuple(
            MarkerTruth(**{**m, "centre_px": tuple(m["centre_px"])}) for m in data["markers"]
        )
        return cls(
            frame_id=int(data["frame_id"]),
            centre_blur_px=float(data["centre_blur_px"]),
            camera_distance_m=float(data["camera_distance_m"]),
            substeps=int(data["substeps"]),
            markers=markers,
        )
