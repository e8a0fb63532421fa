"""Synthetic cameras, gyro streams and a slow reference integrator for the quality tests."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from services.lib.camera_model import CameraModel
from services.lib.quality import GyroSamples

PERIOD_NS = 2_000_000  # 500 Hz

RateFn = Callable[[npt.NDArray[np.float64]], npt.NDArray[np.float64]]


def camera(**overrides: object) -> CameraModel:
    """1024x768, fx != fy so tests can tell which focal length was used."""
    fields: dict[str, object] = {
        "width_px": 1024,
        "height_px": 768,
        "fx_px": 600.0,
        "fy_px": 500.0,
        "cx_px": 511.5,
        "cy_px": 383.5,
    }
    fields.update(overrides)
    return CameraModel(**fields)  # type: ignore[arg-type]


def sampled(
    rates: RateFn, start_ns: int = 0, end_ns: int = 400_000_000, period_ns: int = PERIOD_NS
) -> GyroSamples:
    """Gyro samples of ``rates(t_s) -> (N, 3)`` every ``period_ns`` over [start, end]."""
    t_ns = np.arange(start_ns, end_ns + 1, period_ns, dtype=np.int64)
    return GyroSamples(t_ns, rates(t_ns * 1e-9), period_ns)


def constant(rate_rad_s: tuple[float, float, float], **kwargs: int) -> GyroSamples:
    """Constant angular rate (gyro frame)."""
    vector = np.asarray(rate_rad_s, dtype=np.float64)
    return sampled(lambda t: np.tile(vector, (t.size, 1)), **kwargs)


def shaky(seed: int, amplitude_rad_s: float = 1.0) -> RateFn:
    """Smooth random shake on all axes (sums of sines, 1-12 Hz)."""
    rng = np.random.default_rng(seed)
    freqs = rng.uniform(1.0, 12.0, (3, 4))
    phases = rng.uniform(0.0, 2 * np.pi, (3, 4))
    amps = rng.uniform(0.2, 1.0, (3, 4)) * amplitude_rad_s / 2

    def rates(t_s: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        waves = amps * np.sin(2 * np.pi * freqs * t_s[:, None, None] + phases)
        return np.asarray(waves.sum(axis=2))

    return rates


def _exp(theta: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    angle = float(np.linalg.norm(theta))
    if angle < 1e-15:
        return np.eye(3)
    k = theta / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def reference_blur(
    gyro: GyroSamples,
    cam: CameraModel,
    start_ns: int,
    end_ns: int,
    x_px: float,
    y_px: float,
    steps: int = 4000,
) -> float:
    """Path length by a plain sequential product of small rotations (slow, obviously right).

    Rates are interpolated linearly between samples, as the estimate assumes.
    """
    r = cam.rotation_gyro_to_camera
    t = np.linspace(start_ns, end_ns, steps + 1)
    mid = 0.5 * (t[1:] + t[:-1])
    w = np.stack([np.interp(mid, gyro.t_ns, gyro.rates_rad_s[:, i]) for i in range(3)], 1)
    w = w @ r.T
    dt = (end_ns - start_ns) * 1e-9 / steps
    world = np.array([(x_px - cam.cx_px) / cam.fx_px, (y_px - cam.cy_px) / cam.fy_px, 1.0])
    orientation = np.eye(3)
    points = [(x_px, y_px)]
    for rate in w:
        orientation = orientation @ _exp(rate * dt)
        v = orientation.T @ world
        points.append((cam.cx_px + cam.fx_px * v[0] / v[2], cam.cy_px + cam.fy_px * v[1] / v[2]))
    path = np.diff(np.asarray(points), axis=0)
    return float(np.hypot(path[:, 0], path[:, 1]).sum())
