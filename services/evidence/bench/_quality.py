"""``quality``: microseconds per frame of each blur mode of ``services.lib.quality``.

There is no raw counterpart: the goal is on the centre estimate itself. Timing is wall
clock on purpose (the best chunk of 50 frames, as timeit advises: the minimum is the cost of
the code itself), so each sample also records ``cpu_share``, the fraction of that wall time
this thread was on a CPU: well below 1 means the machine was busy and the figure is high.
"""

from __future__ import annotations

import time

import numpy as np

from services.lib.camera_model import CameraModel
from services.lib.quality import (
    BlurMode,
    BlurOptions,
    Exposure,
    GyroSamples,
    Roi,
    estimate_blur,
)

from ._options import BenchOptions
from ._records import Goal, Row, ScenarioResult

FULL_FRAMES = 500
QUICK_FRAMES = 100
CENTRE_GOAL_US = 50.0
# Timing chunks this short are often not interrupted by other processes.
_CHUNK = 50

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


def time_blur_modes(
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


def run_quality(options: BenchOptions) -> ScenarioResult:
    frames = QUICK_FRAMES if options.quick else FULL_FRAMES
    result = ScenarioResult(
        "quality",
        params={"frames": frames, "what": "us per frame per blur mode (best chunk of 50)"},
    )
    rows: dict[str, Row] = {}
    for pair in range(options.pairs):
        wall, cpu = time.perf_counter(), time.thread_time()
        timings = time_blur_modes(frames=frames)
        cpu_share = (time.thread_time() - cpu) / max(time.perf_counter() - wall, 1e-9)
        for mode, micros in timings.items():
            row = rows.setdefault(mode, Row(mode, "blur estimate", "us/frame", False, raw=None))
            row.framegate.append({"pair": pair, "value": micros, "cpu_share": cpu_share})
        options.progress(
            f"quality run {pair + 1}/{options.pairs}: "
            + ", ".join(f"{k} {v:.0f} us" for k, v in timings.items())
            + f"; this thread had the CPU {100 * cpu_share:.0f}% of the wall time"
        )
    shares = [s["cpu_share"] for row in rows.values() for s in row.framegate]
    if min(shares) < 0.8:
        for row in rows.values():
            row.note = f"wall clock, busy machine: CPU share {min(shares):.2f}..{max(shares):.2f}"
    centre = rows["center"]
    centre.goal = Goal(
        f"centre estimate <= {CENTRE_GOAL_US:g} us/frame",
        CENTRE_GOAL_US,
        False,
        centre.median("framegate"),
    )
    result.rows = list(rows.values())
    return result
