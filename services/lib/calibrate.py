"""Derive the blur scale b0 from a recorded sequence (simulated or real).

For every frame of a dataset: the gyro-estimated blur at the image centre (the mediator's
own estimate) and whether the target was recognized (the detector's own ArUco detection).
b0 is the blur at which recognition halves relative to sharp frames
(``services.lib.quality.derive_b0``). With ground truth (simulated datasets) each marker that
was recognizable in a blur-free render counts as one trial; without it, a frame counts as
recognized when any marker is detected.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from middleware import CoverageError
from services.lib.markers import detect_markers
from services.lib.quality import (
    CalibrationError,
    Exposure,
    GyroSamples,
    derive_b0,
    estimate_blur,
)


@dataclass(frozen=True, slots=True)
class Calibration:
    """The derived b0 and the trials it came from."""

    b0_px: float
    trials: int
    frames: int
    skipped_no_gyro: int
    per_marker_b0_px: dict[str, float]


def calibrate_b0(dataset_dir: Path, *, progress: bool = True) -> Calibration:
    """Estimate blur and detect markers on every frame of ``dataset_dir``; derive b0."""
    from services.lib.sim import read_dataset

    dataset = read_dataset(dataset_dir)
    gyro = GyroSamples(dataset.gyro.t_ns, dataset.gyro.rate_rad_s)
    blur: list[float] = []
    hits: list[bool] = []
    per_marker: dict[str, tuple[list[float], list[bool]]] = {}
    skipped = 0
    for index, info in enumerate(tqdm(dataset.frames, disable=not progress, unit="frame")):
        exposure = Exposure(info.exposure_start_ns, info.exposure_ns)
        try:
            blur_px = estimate_blur(gyro, exposure, dataset.camera).blur_px
        except CoverageError:
            skipped += 1
            continue
        if not np.isfinite(blur_px):
            skipped += 1
            continue
        found = {d.name for d in detect_markers(dataset.image(index))}
        if dataset.truth is None:
            blur.append(blur_px)
            hits.append(bool(found))
            continue
        for marker in dataset.truth[index].markers:
            if not (marker.in_view and marker.detected_sharp):
                continue
            blur.append(blur_px)
            hits.append(marker.name in found)
            b, h = per_marker.setdefault(marker.name, ([], []))
            b.append(blur_px)
            h.append(marker.name in found)
    per_marker_b0: dict[str, float] = {}
    for name, (b, h) in per_marker.items():
        try:
            per_marker_b0[name] = derive_b0(b, h)
        except (ValueError, CalibrationError):
            continue  # e.g. a marker whose recognition never halves has no b0 of its own
    return Calibration(
        b0_px=derive_b0(blur, hits),
        trials=len(blur),
        frames=len(dataset.frames),
        skipped_no_gyro=skipped,
        per_marker_b0_px=per_marker_b0,
    )
