"""Timing the blur estimate per frame, for ``python -m services.lib.quality.bench``."""

from __future__ import annotations

import time

import numpy as np

from services.lib.camera_model import CameraModel

from ._blur import BlurMode, BlurOptions, Roi, estimate_blur
from ._exposure import Exposure
from ._gyro import GyroSamples

# 1024x768 with f ~ 558 px (about 85 degrees across), rows read out over ~20 ms.
BENCH_CAMERA = CameraModel(
    width_px=1024,
    height_px=768,
    fx_px=558.0,
    fy_px=558.0,
    cx_px=511.5,
    cy_px=383.5,
    line_readout_ns=26_000,
)


def _shaky_gyro(duration_ns: int, rate_hz: float, seed: int) -> GyroSamples:
    """Smooth random shake on all three axes, around 1 rad/s."""
    rng = np.random.default_rng(seed)
    period_ns = round(1e9 / rate_hz)
    t_ns = np.arange(0, duration_ns + period_ns, period_ns, dtype=np.int64)
    t_s = t_ns * 1e-9
    rates = np.zeros((t_ns.size, 3))
    for axis in range(3):
        for _ in range(4):
            freq = rng.uniform(0.5, 8.0)
            rates[:, axis] += rng.uniform(0.1, 0.5) * np.sin(
                2 * np.pi * freq * t_s + rng.uniform(0, 2 * np.pi)
            )
    return GyroSamples(t_ns, rates, period_ns)


def bench_quality(
    *,
    frames: int = 500,
    exposure_ns: int = 60_000_000,
    gyro_rate_hz: float = 500.0,
    camera: CameraModel = BENCH_CAMERA,
    seed: int = 0,
    repeat: int = 3,
) -> dict[str, float]:
    """Microseconds per frame of each blur mode on synthetic shake.

    Each mode runs ``repeat`` times over the frames in chunks of 50; the result is the
    best chunk's mean, so load from other processes inflates it as little as possible.

    Keys: ``center`` (the paper's estimate), ``point``, ``mean_grid``, ``max_grid`` (16x12),
    ``roi_max`` (8x8 over a 200 px square off-centre, where roll matters),
    ``rolling_center``, ``rolling_max_grid``.
    """
    if frames < 1 or repeat < 1:
        raise ValueError(f"frames and repeat must be >= 1, got {frames} and {repeat}")
    frame_period_ns = 33_333_333
    span_ns = frames * frame_period_ns + exposure_ns + 100_000_000
    gyro = _shaky_gyro(span_ns, gyro_rate_hz, seed)
    exposures = [Exposure(50_000_000 + i * frame_period_ns, exposure_ns) for i in range(frames)]
    roi = Roi(700.0, 100.0, 200.0, 200.0)
    modes = {
        "center": BlurOptions(),
        "point": BlurOptions(mode=BlurMode.POINT, point_px=(900.0, 700.0)),
        "mean_grid": BlurOptions(mode=BlurMode.MEAN),
        "max_grid": BlurOptions(mode=BlurMode.MAX),
        "roi_max": BlurOptions(mode=BlurMode.MAX, roi=roi, grid=(8, 8)),
        "rolling_center": BlurOptions(rolling_shutter=True),
        "rolling_max_grid": BlurOptions(mode=BlurMode.MAX, rolling_shutter=True),
    }
    results: dict[str, float] = {}
    chunks = [exposures[i : i + _CHUNK] for i in range(0, frames, _CHUNK)]
    for name, options in modes.items():
        estimate_blur(gyro, exposures[0], camera, options)  # warm the plan cache
        best = float("inf")
        for _ in range(repeat):
            for chunk in chunks:
                began = time.perf_counter_ns()
                for exposure in chunk:
                    estimate_blur(gyro, exposure, camera, options)
                best = min(best, (time.perf_counter_ns() - began) / len(chunk) / 1e3)
        results[name] = best
    return results


# Timing chunks this short are often not interrupted by other processes; the best chunk
# is the cost of the code itself (as timeit advises, the minimum is the informative number).
_CHUNK = 50
