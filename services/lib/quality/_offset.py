"""Estimating the camera-to-gyro time offset from a recorded sequence.

A wrong offset integrates the wrong stretch of rates, so predicted blur and measured image
sharpness disagree. For each candidate offset the predicted blur of every frame is ranked
against a sharpness signal; the offset with the best rank agreement wins. Rank correlation
(Spearman) needs no model of how sharpness falls with blur, only that it does.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from services.lib.camera_model import CameraModel

from ._blur import DEFAULT_OPTIONS, BlurOptions, estimate_blur
from ._errors import CalibrationError, CoverageError, QualityInputError
from ._exposure import Exposure
from ._gyro import GyroSamples

Floats = npt.NDArray[np.float64]

_MIN_FRAMES = 8


def laplacian_variance(image: npt.NDArray[np.generic]) -> float:
    """Sharpness of an image: the variance of its Laplacian (higher is sharper).

    Takes mono (H, W) or 3-channel (H, W, 3, BGR order) images of any numeric type.
    """
    import cv2  # here, not at import: the mediator and gyro never call this and start faster

    array = np.asarray(image)
    if array.ndim == 3 and array.shape[2] == 3:
        array = cv2.cvtColor(array.astype(np.float32), cv2.COLOR_BGR2GRAY)
    elif array.ndim != 2:
        raise QualityInputError(f"expected an (H, W) or (H, W, 3) image, got shape {array.shape}")
    laplacian = cv2.Laplacian(array.astype(np.float64), cv2.CV_64F)
    return float(laplacian.var())


def _ranks(values: Floats) -> Floats:
    """Ranks 1..n, ties sharing their mean rank."""
    order = np.argsort(values, kind="mergesort")
    ordered = values[order]
    new = np.concatenate([[True], ordered[1:] != ordered[:-1]])
    dense = np.cumsum(new)
    ends = np.concatenate([np.flatnonzero(new), [values.size]])
    mean_rank = 0.5 * (ends[dense - 1] + ends[dense] + 1)
    ranks = np.empty(values.size)
    ranks[order] = mean_rank
    return ranks


def rank_correlation(a: npt.ArrayLike, b: npt.ArrayLike) -> float:
    """Spearman's rank correlation of two equally long sequences (nan if one is constant)."""
    ra = _ranks(np.asarray(a, dtype=np.float64).ravel())
    rb = _ranks(np.asarray(b, dtype=np.float64).ravel())
    if ra.size != rb.size:
        raise QualityInputError(f"sequences differ in length: {ra.size} and {rb.size}")
    ra -= ra.mean()
    rb -= rb.mean()
    norm = float(np.sqrt((ra * ra).sum() * (rb * rb).sum()))
    return float((ra * rb).sum()) / norm if norm > 0.0 else float("nan")


@dataclass(frozen=True, slots=True, eq=False)
class OffsetEstimate:
    """The best camera-to-gyro offset and the score curve it was picked from.

    ``scores[i]`` is the rank correlation of -blur with sharpness at ``candidates_ns[i]``;
    ``frames_used`` counts frames the gyro covered at every candidate.
    """

    offset_ns: int
    score: float
    candidates_ns: npt.NDArray[np.int64]
    scores: Floats
    frames_used: int


def estimate_time_offset(
    exposures: Sequence[Exposure],
    gyro: GyroSamples,
    sharpness: npt.ArrayLike,
    camera: CameraModel,
    *,
    candidates_ns: npt.ArrayLike | None = None,
    search_ns: int = 50_000_000,
    step_ns: int = 1_000_000,
    options: BlurOptions = DEFAULT_OPTIONS,
) -> OffsetEstimate:
    """Search ``gyro_time_offset_ns`` values; return the one whose blur best explains sharpness.

    Candidates are ``candidates_ns`` or ``camera.gyro_time_offset_ns`` +- ``search_ns`` in
    steps of ``step_ns``. Frames the gyro does not cover at every candidate are left out.
    A flat maximum resolves to its middle. Raises CalibrationError when fewer than 8
    frames remain or no candidate gives a defined score (e.g. the camera never moved).
    """
    sharp = np.asarray(sharpness, dtype=np.float64).ravel()
    if sharp.size != len(exposures):
        raise QualityInputError(f"{len(exposures)} exposures but {sharp.size} sharpness values")
    if candidates_ns is None:
        if step_ns <= 0 or search_ns < 0:
            raise QualityInputError(
                f"need step_ns > 0 and search_ns >= 0, got {step_ns}, {search_ns}"
            )
        steps = np.arange(-(search_ns // step_ns), search_ns // step_ns + 1, dtype=np.int64)
        candidates = camera.gyro_time_offset_ns + steps * step_ns
    else:
        candidates = np.unique(np.asarray(candidates_ns, dtype=np.int64).ravel())
        if candidates.size == 0:
            raise QualityInputError("candidates_ns is empty")
    blur = np.full((candidates.size, len(exposures)), np.nan)
    for row, offset in enumerate(candidates.tolist()):
        shifted = dataclasses.replace(camera, gyro_time_offset_ns=offset)
        for column, exposure in enumerate(exposures):
            try:
                blur[row, column] = estimate_blur(gyro, exposure, shifted, options).blur_px
            except CoverageError:
                continue
    usable = np.all(np.isfinite(blur), axis=0)
    used = int(usable.sum())
    if used < _MIN_FRAMES:
        raise CalibrationError(
            f"only {used} of {len(exposures)} frames are covered by gyro samples at every "
            f"candidate offset; need {_MIN_FRAMES} (narrow the search or record longer)"
        )
    scores = np.array(
        [rank_correlation(-row[usable], sharp[usable]) for row in blur], dtype=np.float64
    )
    if not bool(np.any(np.isfinite(scores))):
        raise CalibrationError(
            "predicted blur or sharpness is the same for every frame, so no offset explains "
            "it better than another; record a sequence with varied motion"
        )
    best = np.nanmax(scores)
    ties = np.flatnonzero(scores == best)
    pick = int(ties[ties.size // 2])
    return OffsetEstimate(
        offset_ns=int(candidates[pick]),
        score=float(best),
        candidates_ns=candidates,
        scores=scores,
        frames_used=used,
    )
