"""Every parameter of the bumpy-approach scenario, in one frozen, overridable dataclass."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, fields
from typing import Any, Literal

import numpy as np

from middleware import ConfigError
from services.lib.argtypes import did_you_mean
from services.lib.camera_model import CameraModel

Track = Literal["left", "right", "both"]
_TRACKS = ("left", "right", "both")

FLOOR_PRESETS: dict[str, dict[str, float]] = {
    "smooth": {
        "bump_mean_spacing_m": 0.8,
        "bump_height_min_m": 0.001,
        "bump_height_max_m": 0.005,
    },
    "default": {
        "bump_mean_spacing_m": 0.5,
        "bump_height_min_m": 0.003,
        "bump_height_max_m": 0.01,
    },
    "rough": {
        "bump_mean_spacing_m": 0.35,
        "bump_height_min_m": 0.005,
        "bump_height_max_m": 0.015,
    },
}
"""Floors for :meth:`ScenarioConfig.with_floor`: bump parameters changed from the defaults.

``default`` holds the defaults (3-10 mm bumps every 0.5 m on average, the paper's "bumps of
a maximum height of 1 cm"), so its scenarios, and their cached datasets, stay what they were.
``smooth`` has a third as many, lower bumps (1-5 mm every 0.8 m); ``rough`` more and higher
ones (5-15 mm every 0.35 m).
"""


@dataclass(frozen=True, slots=True)
class Bump:
    """One bump on the floor, crossed by the wheels of one or both tracks.

    ``at_travel_m``: how far the robot has travelled since the first exposure started when its
    front wheels reach the bump (negative: during the lead-in). The rear wheels reach it one
    wheelbase later. The wheel centre follows a raised-cosine of ``height_m`` over ``length_m``
    (the obstacle as enveloped by the tyre).
    """

    at_travel_m: float
    height_m: float = 0.01
    length_m: float = 0.1
    track: Track = "both"

    def __post_init__(self) -> None:
        if self.track not in _TRACKS:
            raise ConfigError(f"bump track {self.track!r} is not one of {', '.join(_TRACKS)}")
        if self.length_m <= 0 or self.height_m < 0:
            raise ConfigError(
                f"bump needs length_m > 0 and height_m >= 0, got {self.length_m}, {self.height_m}"
            )


@dataclass(frozen=True, slots=True)
class ScenarioConfig:
    """The robot approaching the marker board over a bumpy floor (paper §5.2).

    Defaults follow the paper: a 2/3-inch monochrome CCD (8.8 mm wide) behind a 4.8 mm lens,
    read out at 1024x768 (f = 558.5 px), 15 frames/s, 60 ms exposure, global shutter; the
    robot drives straight at the board from 13 m at 0.54 m/s, so 319 frames end about 1.5 m
    from it. Override with :meth:`replace`. Times are int ns, lengths m, angles deg.
    """

    seed: int = 0

    # -- camera and timing --
    frame_count: int = 319
    frame_rate_hz: float = 15.0
    # 30-60 ms in the paper; auto exposure is assumed, so a shorter exposure means more
    # light (same image brightness and noise), not a darker image.
    exposure_ns: int = 60_000_000
    width_px: int = 1024
    height_px: int = 768
    sensor_width_mm: float = 8.8
    lens_focal_mm: float = 4.8
    # 0 = global shutter (the paper's CCD); > 0 renders a rolling shutter row by row.
    line_readout_ns: int = 0
    # Simulated time before the first exposure and after the last one, so gyro data
    # covers every exposure whatever the clock offset.
    lead_in_ns: int = 500_000_000
    lead_out_ns: int = 500_000_000

    # -- camera mounting on the robot body (body: x forward, y left, z up) --
    camera_height_m: float = 0.5
    camera_forward_m: float = 0.0
    camera_tilt_deg: float = 5.0  # down

    # -- approach --
    start_distance_m: float = 13.0  # camera to wall when the first exposure starts
    speed_m_s: float = 0.54
    board_bottom_m: float = 0.70  # board's lower edge above the floor
    board_lateral_m: float = 0.0  # board centre left (+) of the robot's path

    # -- robot body: sprung mass on a two-axle chassis --
    wheelbase_m: float = 0.5
    track_width_m: float = 0.4
    heave_hz: float = 3.0
    pitch_hz: float = 2.5
    roll_hz: float = 3.5
    heave_damping: float = 0.25  # damping ratios
    pitch_damping: float = 0.2
    roll_damping: float = 0.2
    dynamics_step_ns: int = 500_000

    # -- floor bumps (random unless ``bumps`` lists them) --
    bump_mean_spacing_m: float = 0.5
    bump_height_min_m: float = 0.003
    bump_height_max_m: float = 0.01
    bump_length_min_m: float = 0.06
    bump_length_max_m: float = 0.15
    bump_both_tracks_probability: float = 0.4
    bumps: tuple[Bump, ...] | None = None

    # -- gyro (mounted with the body axes: x forward, y left, z up) --
    gyro_rate_hz: float = 1000.0
    gyro_noise_rad_s: float = 0.002  # white noise, std per sample
    gyro_bias_rad_s: float = 0.005  # std of the constant per-axis bias drawn from the seed
    gyro_time_offset_ns: int = 2_500_000

    # -- scene appearance --
    # The wall repeats after wall_period_m across and wall_height_m up: endless, yet stored
    # once; 16 m is wider than the view at 13 m, 8 m higher than the view ever reaches.
    wall_texel_m: float = 0.004
    wall_period_m: float = 16.384
    wall_height_m: float = 8.192
    wall_reflectance: float = 0.5
    wall_contrast: float = 0.12  # std of the wall's reflectance
    floor_texel_m: float = 0.02
    floor_period_m: float = 10.24
    floor_feature_m: float = 0.2  # smallest floor detail; the floor is deliberately smooth
    floor_reflectance: float = 0.3
    floor_contrast: float = 0.05
    board_texel_m: float = 0.001

    # -- sensor --
    optics_blur_px: float = 0.7  # Gaussian sigma of lens and pixel aperture
    white_signal_e: float = 10_000.0  # electrons from a reflectance-1 surface per exposure
    full_scale_e: float = 13_000.0  # electrons at 255 DN
    read_noise_e: float = 10.0
    black_level_dn: float = 4.0

    # -- rendering --
    max_substep_px: float = 0.75  # largest image motion between consecutive warps
    max_substeps: int = 64
    truth_samples: int = 256  # path segments per exposure for the true blur length

    def __post_init__(self) -> None:
        positive = (
            "frame_rate_hz", "exposure_ns", "width_px", "height_px", "sensor_width_mm",
            "lens_focal_mm", "camera_height_m", "start_distance_m", "wheelbase_m",
            "track_width_m", "heave_hz", "pitch_hz", "roll_hz", "dynamics_step_ns",
            "bump_mean_spacing_m", "bump_length_min_m", "gyro_rate_hz", "wall_texel_m",
            "wall_period_m", "wall_height_m", "floor_texel_m", "floor_period_m", "floor_feature_m",
            "board_texel_m", "white_signal_e", "full_scale_e", "max_substep_px",
            "max_substeps", "truth_samples",
        )  # fmt: skip
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name} must be > 0, got {getattr(self, name)!r}")
        non_negative = (
            "seed", "frame_count", "line_readout_ns", "lead_in_ns", "lead_out_ns", "speed_m_s",
            "bump_height_min_m", "gyro_noise_rad_s", "gyro_bias_rad_s", "optics_blur_px",
            "read_noise_e",
        )  # fmt: skip
        for name in non_negative:
            if getattr(self, name) < 0:
                raise ConfigError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if self.exposure_ns > self.frame_period_ns:
            raise ConfigError(
                f"exposure_ns={self.exposure_ns} is longer than the frame period "
                f"{self.frame_period_ns} ns at {self.frame_rate_hz} frames/s"
            )
        if self.bump_height_max_m < self.bump_height_min_m:
            raise ConfigError("bump_height_max_m must be >= bump_height_min_m")
        if self.bump_length_max_m < self.bump_length_min_m:
            raise ConfigError("bump_length_max_m must be >= bump_length_min_m")
        if not 0 <= self.bump_both_tracks_probability <= 1:
            raise ConfigError("bump_both_tracks_probability must be within [0, 1]")
        if self.end_distance_m <= 0.5:
            raise ConfigError(
                f"the approach ends {self.end_distance_m:.2f} m from the wall; "
                "lower frame_count or speed_m_s, or raise start_distance_m"
            )

    def replace(self, **changes: Any) -> ScenarioConfig:
        """A copy with some fields changed (validated like the original)."""
        _check_known(changes, {f.name for f in fields(self)})
        return dataclasses.replace(self, **changes)

    @staticmethod
    def floor_names() -> tuple[str, ...]:
        """The floor presets :meth:`with_floor` knows, smoothest first."""
        return tuple(FLOOR_PRESETS)

    def with_floor(self, floor: str) -> ScenarioConfig:
        """A copy on the named floor (``smooth``, ``default``, ``rough``): its bump
        parameters set from the preset, everything else kept."""
        if floor not in FLOOR_PRESETS:
            raise ConfigError(
                f"unknown floor {floor!r}{did_you_mean(floor, FLOOR_PRESETS, quote=True)}; "
                f"choose one of {', '.join(FLOOR_PRESETS)}"
            )
        return self.replace(**FLOOR_PRESETS[floor])

    # -- derived values --

    @property
    def frame_period_ns(self) -> int:
        """Nominal time between exposure starts."""
        return round(1e9 / self.frame_rate_hz)

    @property
    def focal_px(self) -> float:
        """Focal length in pixels: lens focal length over pixel pitch."""
        return self.lens_focal_mm * self.width_px / self.sensor_width_mm

    @property
    def end_distance_m(self) -> float:
        """Camera to wall when the last exposure starts."""
        last_start_s = self.frame_start_ns(max(self.frame_count - 1, 0)) * 1e-9
        return self.start_distance_m - self.speed_m_s * (last_start_s - self.lead_in_ns * 1e-9)

    @property
    def duration_ns(self) -> int:
        """Simulated time span: lead-in, every frame, lead-out."""
        last_end = self.frame_start_ns(max(self.frame_count - 1, 0)) + self.exposure_ns
        return last_end + self.lead_out_ns

    @property
    def rotation_gyro_to_camera(self) -> np.ndarray:
        """R with v_camera = R @ v_gyro; the gyro axes are the body axes."""
        tilt = math.radians(self.camera_tilt_deg)
        s, c = math.sin(tilt), math.cos(tilt)
        # Rows: the camera's x (right), y (down), z (optical axis, tilted down) in body axes.
        return np.array([[0.0, -1.0, 0.0], [-s, 0.0, -c], [c, 0.0, -s]])

    def frame_start_ns(self, frame_id: int) -> int:
        """Exposure start of a frame on the camera clock (dataset epoch = simulation start)."""
        return self.lead_in_ns + round(frame_id * 1e9 / self.frame_rate_hz)

    def camera_model(self) -> CameraModel:
        """The camera description the dataset's ``camera.xml`` carries."""
        return CameraModel(
            width_px=self.width_px,
            height_px=self.height_px,
            fx_px=self.focal_px,
            fy_px=self.focal_px,
            cx_px=(self.width_px - 1) / 2,
            cy_px=(self.height_px - 1) / 2,
            line_readout_ns=self.line_readout_ns,
            gyro_to_camera=tuple(float(v) for v in self.rotation_gyro_to_camera.ravel()),
            gyro_time_offset_ns=self.gyro_time_offset_ns,
            name="sim",
        )

    # -- JSON form (scenario.json) --

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready values; ``bumps`` becomes a list of dicts or None."""
        out: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "bumps" and value is not None:
                value = [dataclasses.asdict(b) for b in value]
            out[f.name] = value
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ScenarioConfig:
        """Inverse of :meth:`to_dict`; missing keys take their defaults, unknown keys fail."""
        known = {f.name: f for f in fields(cls)}
        _check_known(data, set(known))
        values = dict(data)
        for name, value in values.items():
            _check_type(name, value, known[name].default)
        if values.get("bumps") is not None:
            try:
                values["bumps"] = tuple(Bump(**b) for b in values["bumps"])
            except TypeError as exc:
                raise ConfigError(f"bad bump in scenario: {exc}") from exc
        return cls(**values)


def _check_type(name: str, value: Any, default: Any) -> None:
    """ConfigError for a number or switch given as something else (``--set seed=abc`` met
    a comparison inside the checks, ``--set frame_count=true`` rendered 1 frame)."""
    if type(default) is bool:
        ok, wanted = type(value) is bool, "true or false"
    elif type(default) is int:
        ok, wanted = type(value) is int, "an integer"
    elif type(default) is float:
        ok, wanted = type(value) in (int, float), "a number"
    else:
        return
    if not ok:
        words = {"None": "null", "True": "true", "False": "false"}  # as written in JSON
        shown = words[repr(value)] if value is None or type(value) is bool else repr(value)
        raise ConfigError(f"scenario parameter {name} must be {wanted}, got {shown}")


def _check_known(names: dict[str, Any], known: set[str]) -> None:
    """ConfigError naming the parameters that are not fields (a did-you-mean for one)."""
    unknown = sorted(set(names) - known)
    if unknown:
        near = did_you_mean(unknown[0], known, quote=True) if len(unknown) == 1 else ""
        raise ConfigError(f"unknown scenario parameter(s): {', '.join(unknown)}{near}")
