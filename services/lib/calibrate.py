"""Derive the blur scale b0 from a recorded sequence (simulated or real).

For every frame of a dataset: the gyro-estimated blur at the image centre (the mediator's
own estimate) and whether the target was recognized (the detector's own ArUco detection).
b0 is the blur at which recognition halves relative to sharp frames
(``derive_b0``). With ground truth (simulated datasets) each marker that
was recognizable in a blur-free render counts as one trial; without it, a frame counts as
recognized when any marker is detected.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
from tqdm import tqdm

from services.lib.markers import detect_markers
from services.lib.quality import (
    CalibrationError,
    CoverageError,
    Exposure,
    GyroSamples,
    estimate_blur,
)

Floats = npt.NDArray[np.float64]

# The sharpest frames set the reference rate: this share of them, but at least this many.
_SHARP_SHARE = 0.1
_SHARP_MIN = 5


def _decreasing_fit(values: Floats, weights: Floats) -> Floats:
    """Weighted least-squares non-increasing fit (pool adjacent violators)."""
    means: list[float] = []
    sizes: list[float] = []
    counts: list[int] = []
    for value, weight in zip(values.tolist(), weights.tolist(), strict=True):
        means.append(value)
        sizes.append(weight)
        counts.append(1)
        while len(means) > 1 and means[-2] < means[-1]:
            mean, size, count = means.pop(), sizes.pop(), counts.pop()
            total = sizes[-1] + size
            means[-1] = (means[-1] * sizes[-1] + mean * size) / total
            sizes[-1] = total
            counts[-1] += count
    return np.repeat(np.array(means), counts)


def derive_b0(blur_px: npt.ArrayLike, recognized: npt.ArrayLike, *, min_frames: int = 20) -> float:
    """The blur in pixels at which the recognition rate halves relative to sharp frames.

    Fits recognition against blur as a non-increasing curve (isotonic regression, so no
    shape is assumed and a few frames cannot make it rise again), takes the rate of the
    sharpest 10 % of frames (at least 5) as the reference, and returns where the fitted
    curve, interpolated linearly, falls to half of it. Use it as ``b0_px``.

    Raises CalibrationError when there are fewer than ``min_frames`` frames, no sharp frame
    was recognised, or recognition never falls to half within the recorded blur.
    """
    blur = np.asarray(blur_px, dtype=np.float64).ravel()
    hits = np.asarray(recognized, dtype=bool).ravel().astype(np.float64)
    if blur.size != hits.size:
        raise CalibrationError(f"{blur.size} blur values but {hits.size} recognition flags")
    if not bool(np.all(np.isfinite(blur) & (blur >= 0.0))):
        raise CalibrationError("blur_px must be finite and >= 0 for every frame")
    if blur.size < max(min_frames, 2):
        raise CalibrationError(
            f"{blur.size} frames are too few to fit recognition against blur; "
            f"record at least {max(min_frames, 2)}"
        )
    order = np.argsort(blur, kind="stable")
    blur, hits = blur[order], hits[order]
    sharp = max(_SHARP_MIN, int(np.ceil(_SHARP_SHARE * blur.size)))
    reference = float(hits[:sharp].mean())
    if reference == 0.0:
        raise CalibrationError(
            f"none of the {sharp} sharpest frames (blur <= {blur[sharp - 1]:.3g} px) was "
            "recognised, so there is no reference rate to halve; check the detector"
        )
    # Frames with equal blur must get one fitted value: pool them first.
    levels, start, count = np.unique(blur, return_index=True, return_counts=True)
    rate = np.add.reduceat(hits, start) / count
    fitted = _decreasing_fit(rate, count.astype(np.float64))
    # One point per pooled block of the fit: its weighted mean blur and its value.
    change = np.flatnonzero(np.diff(fitted)) + 1
    bounds = np.concatenate([[0], change, [fitted.size]])
    weights = count.astype(np.float64)
    centres = np.add.reduceat(levels * weights, bounds[:-1]) / np.add.reduceat(weights, bounds[:-1])
    values = fitted[bounds[:-1]]
    target = reference / 2.0
    below = np.flatnonzero(values <= target)
    if below.size == 0:
        raise CalibrationError(
            f"recognition never falls to half of the sharp rate ({reference:.2f} -> "
            f"{target:.2f}) within the recorded blur (up to {blur[-1]:.3g} px); "
            "record frames with more motion"
        )
    hi = int(below[0])
    if hi == 0:
        return float(centres[0])
    lo = hi - 1
    share = (values[lo] - target) / (values[lo] - values[hi])
    return float(centres[lo] + share * (centres[hi] - centres[lo]))


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
    # disable=None: no bar when stderr is no terminal (a log gets no \r updates).
    bar = tqdm(dataset.frames, disable=None if progress else True, unit="frame")
    for index, info in enumerate(bar):
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
