"""Robot motion: floor bumps, the sprung body's response, camera poses and gyro rates.

World frame: X forward (towards the wall, which is the plane X = 0), Y left, Z up; the floor
is Z = 0. The robot drives along X at constant speed with no yaw. The body is a sprung mass
with three decoupled, damped modes (heave, pitch, roll), each excited through its spring and
damper by what the four wheels follow on the floor. Attitude and its rate are one smooth
function of time (cubic Hermite through the integrated states), and both the renderer and the
gyro read that same function, so images and gyro data agree by construction.
"""

from __future__ import annotations

import math

import numpy as np

from . import _scene_cache
from ._config import Bump, ScenarioConfig, Track
from ._rng import Stream, rng_for

_NS = 1e-9


def draw_bumps(config: ScenarioConfig) -> tuple[Bump, ...]:
    """The scenario's bumps: ``config.bumps`` if given, else drawn from the seed.

    Spacing along the path is a minimum gap (no overlap on one track) plus an exponential
    remainder, so the mean spacing is ``bump_mean_spacing_m``.
    """
    if config.bumps is not None:
        return config.bumps
    rng = rng_for(config.seed, Stream.BUMPS)
    min_gap = config.bump_length_max_m
    spread = max(config.bump_mean_spacing_m - min_gap, 0.0)
    travel = -config.speed_m_s * config.lead_in_ns * _NS
    end = config.speed_m_s * (config.duration_ns - config.lead_in_ns) * _NS
    bumps: list[Bump] = []
    while True:
        travel += min_gap + (float(rng.exponential(spread)) if spread > 0 else 0.0)
        if travel > end:
            return tuple(bumps)
        height = float(rng.uniform(config.bump_height_min_m, config.bump_height_max_m))
        length = float(rng.uniform(config.bump_length_min_m, config.bump_length_max_m))
        track: Track = "both"
        if float(rng.random()) >= config.bump_both_tracks_probability:
            track = "left" if rng.random() < 0.5 else "right"
        bumps.append(Bump(travel, height, length, track))


def _floor_under(bumps: tuple[Bump, ...], side: str, travel_m: np.ndarray) -> np.ndarray:
    """Height of a wheel on one side whose front-axle-equivalent travel is ``travel_m``."""
    height = np.zeros_like(travel_m)
    for bump in bumps:
        if bump.track not in (side, "both"):
            continue
        phase = (travel_m - bump.at_travel_m) / bump.length_m
        inside = (phase >= 0) & (phase <= 1)
        height[inside] += bump.height_m * 0.5 * (1 - np.cos(2 * np.pi * phase[inside]))
    return height


def _sprung_mode(
    u: np.ndarray, natural_hz: float, damping: float, step_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Response x, dx/dt of x'' = -2 z w (x' - u') - w^2 (x - u), at rest at the start.

    Discretised exactly for a piecewise-linear input (first-order hold), so the result does
    not depend on the step beyond the sampling of ``u``.
    """
    # Imported here: SciPy's signal package takes about a second to import, and a restarted
    # camera or gyro reads these responses from the scenario cache instead.
    from scipy.signal import cont2discrete, lfilter, ss2tf

    w = 2 * math.pi * natural_hz
    z = damping
    # State (x, x' - 2 z w u) keeps u' out of the equations; outputs are x and x'.
    a = np.array([[0.0, 1.0], [-(w**2), -2 * z * w]])
    b = np.array([[2 * z * w], [w**2 - 4 * z**2 * w**2]])
    c = np.eye(2)
    d = np.array([[0.0], [2 * z * w]])
    ad, bd, cd, dd, _ = cont2discrete((a, b, c, d), step_s, method="foh")
    num, den = ss2tf(ad, bd, cd, dd)
    return lfilter(num[0], den, u), lfilter(num[1], den, u)


def _hermite(
    knots: np.ndarray, values: np.ndarray, rates: np.ndarray, t: np.ndarray, *, derivative: bool
) -> np.ndarray:
    """The cubic Hermite interpolant through (knots, values) with slopes ``rates`` at ``t``
    (its derivative with ``derivative``); NaN outside the knots, like SciPy's
    ``CubicHermiteSpline(..., extrapolate=False)``, which this replaces so that a scenario
    read from the cache needs no SciPy import at all."""
    t = np.asarray(t, dtype=float)
    i = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, len(knots) - 2)
    h = (knots[i + 1] - knots[i])[:, None]
    s = ((t - knots[i]) / h[:, 0])[:, None]
    y0, y1, m0, m1 = values[i], values[i + 1], rates[i], rates[i + 1]
    if derivative:
        out = (
            ((6 * s**2 - 6 * s) * (y0 - y1)) / h
            + (3 * s**2 - 4 * s + 1) * m0
            + (3 * s**2 - 2 * s) * m1
        )
    else:
        out = (
            (2 * s**3 - 3 * s**2 + 1) * y0
            + (s**3 - 2 * s**2 + s) * h * m0
            + (-2 * s**3 + 3 * s**2) * y1
            + (s**3 - s**2) * h * m1
        )
    outside = (t < knots[0]) | (t > knots[-1])
    out[outside] = np.nan
    return np.asarray(out)


class Motion:
    """Body and camera motion over the simulated span; times in s on the camera clock."""

    def __init__(self, config: ScenarioConfig) -> None:
        self.config = config
        self.bumps = draw_bumps(config)
        step_s = config.dynamics_step_ns * _NS
        count = math.ceil(config.duration_ns * _NS / step_s) + 3
        t = np.arange(count) * step_s
        front = self.travel_m(t)
        shapes = {"values": (count, 3), "rates": (count, 3)}
        knots = _scene_cache.load(config, "motion", shapes, np.float64)
        if knots is None:
            knots = self._integrate(front, step_s)
            _scene_cache.save(config, "motion", knots)
        # (heave m, pitch rad, roll rad) and their exact derivatives at the samples; between
        # them one cubic Hermite piece each.
        self._t = t
        self._values, self._rates = knots["values"], knots["rates"]
        self._r_cam_from_body = config.rotation_gyro_to_camera
        self._camera_offset = np.array(
            [config.camera_forward_m, 0.0, config.camera_height_m], dtype=float
        )

    def _integrate(self, front: np.ndarray, step_s: float) -> dict[str, np.ndarray]:
        config = self.config
        rear = front - config.wheelbase_m
        fl, fr = _floor_under(self.bumps, "left", front), _floor_under(self.bumps, "right", front)
        rl, rr = _floor_under(self.bumps, "left", rear), _floor_under(self.bumps, "right", rear)
        heave_in = (fl + fr + rl + rr) / 4
        # Pitch is positive nose-down (right-handed about y = left): front up is negative.
        pitch_in = -np.arctan(((fl + fr) - (rl + rr)) / 2 / config.wheelbase_m)
        roll_in = np.arctan(((fl + rl) - (fr + rr)) / 2 / config.track_width_m)
        modes = [
            _sprung_mode(heave_in, config.heave_hz, config.heave_damping, step_s),
            _sprung_mode(pitch_in, config.pitch_hz, config.pitch_damping, step_s),
            _sprung_mode(roll_in, config.roll_hz, config.roll_damping, step_s),
        ]
        return {
            "values": np.ascontiguousarray(np.stack([m[0] for m in modes], axis=1)),
            "rates": np.ascontiguousarray(np.stack([m[1] for m in modes], axis=1)),
        }

    def _state(self, t_s: np.ndarray) -> np.ndarray:
        return _hermite(self._t, self._values, self._rates, t_s, derivative=False)

    def _rate(self, t_s: np.ndarray) -> np.ndarray:
        return _hermite(self._t, self._values, self._rates, t_s, derivative=True)

    def travel_m(self, t_s: np.ndarray) -> np.ndarray:
        """Distance travelled since the first exposure started (negative before)."""
        return self.config.speed_m_s * (np.asarray(t_s, dtype=float) - self.config.lead_in_ns * _NS)

    def body_rate_rad_s(self, t_s: np.ndarray) -> np.ndarray:
        """(n, 3) angular velocity of the body in body axes (x forward, y left, z up)."""
        t_s = np.asarray(t_s, dtype=float)
        state, rate = np.asarray(self._state(t_s)), np.asarray(self._rate(t_s))
        roll, pitch_rate, roll_rate = state[:, 2], rate[:, 1], rate[:, 2]
        # For R = Ry(pitch) Rx(roll): omega_body = (roll', pitch' cos roll, -pitch' sin roll).
        return np.stack([roll_rate, pitch_rate * np.cos(roll), -pitch_rate * np.sin(roll)], axis=1)

    def camera_pose(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World-to-camera rotations (n, 3, 3) and camera centres in the world (n, 3)."""
        t_s = np.atleast_1d(np.asarray(t_s, dtype=float))
        state = np.asarray(self._state(t_s))
        if np.isnan(state).any():
            raise ValueError("camera pose asked for outside the simulated span")
        heave, pitch, roll = state[:, 0], state[:, 1], state[:, 2]
        cp, sp, cr, sr = np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
        zero, one = np.zeros_like(pitch), np.ones_like(pitch)
        r_pitch = np.stack(
            [np.stack([cp, zero, sp], 1), np.stack([zero, one, zero], 1),
             np.stack([-sp, zero, cp], 1)], axis=1,
        )  # fmt: skip
        r_roll = np.stack(
            [np.stack([one, zero, zero], 1), np.stack([zero, cr, -sr], 1),
             np.stack([zero, sr, cr], 1)], axis=1,
        )  # fmt: skip
        r_world_body = r_pitch @ r_roll
        body_x = -self.config.start_distance_m - self.config.camera_forward_m + self.travel_m(t_s)
        body = np.stack([body_x, zero, heave], axis=1)
        centre = body + r_world_body @ self._camera_offset
        r_cam_world = self._r_cam_from_body @ np.transpose(r_world_body, (0, 2, 1))
        return r_cam_world, centre


def gyro_trace(motion: Motion) -> tuple[np.ndarray, np.ndarray]:
    """Gyro samples: int64 times on the gyro clock (ns) and (n, 3) rates in rad/s.

    Samples fall on the gyro clock's own grid; each reads the body rate at the true instant
    (gyro time minus the clock offset) plus a constant bias and white noise.
    """
    config = motion.config
    period_ns = round(1e9 / config.gyro_rate_hz)
    offset = config.gyro_time_offset_ns
    first = -(-max(offset, 0) // period_ns)
    last = (config.duration_ns + offset) // period_ns
    t_ns = np.arange(first, last + 1, dtype=np.int64) * period_ns
    true_s = (t_ns - offset) * _NS
    rng = rng_for(config.seed, Stream.GYRO)
    bias = rng.normal(0.0, config.gyro_bias_rad_s, 3)
    noise = rng.normal(0.0, config.gyro_noise_rad_s, (len(t_ns), 3))
    return t_ns, motion.body_rate_rad_s(true_s) + bias + noise
