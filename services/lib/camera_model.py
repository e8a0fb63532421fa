"""The camera description shared by the simulator, the camera service and the quality estimate.

Pinhole intrinsics, image size, rolling-shutter line time, and how the camera relates to the
gyro (rotation and clock offset). Round-trips through the ``camera`` metadata kind
(``schemas/common.xsd`` CameraType) so a dataset's ``camera.xml`` and every frame's metadata
carry the same description.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from middleware import ConfigError, SchemaError, field_text, make_metadata, validate_metadata

_IDENTITY = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


# A rolling shutter reads a frame in milliseconds; a second is no camera.
MAX_READOUT_NS = 1_000_000_000
# Camera and gyro clocks closer than this (one host, or synchronized hosts); farther is no
# calibration but a broken or hostile description.
MAX_GYRO_OFFSET_NS = 3600 * 1_000_000_000


@dataclass(frozen=True, slots=True)
class CameraModel:
    """Pinhole camera. Camera frame: x right, y down, z along the optical axis.

    ``gyro_to_camera`` is a row-major 3x3 rotation R with v_camera = R @ v_gyro.
    ``gyro_time_offset_ns``: an instant the camera clock labels t, the gyro clock labels
    t + offset. ``line_readout_ns`` is the rolling-shutter delay per row (0 = global shutter).
    """

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    line_readout_ns: int = 0
    gyro_to_camera: tuple[float, ...] = field(default=_IDENTITY)
    gyro_time_offset_ns: int = 0
    name: str = "camera"

    def __post_init__(self) -> None:
        # Schema-valid is not sane: xs:double admits NaN and INF, and a peer's metadata
        # reaches the blur estimate through here, so every number is checked once.
        if not (self.width_px > 0 and self.height_px > 0):
            raise ConfigError(f"camera size must be positive, got {self.width_px}x{self.height_px}")
        for name in ("fx_px", "fy_px"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"camera {name} must be finite and positive, got {value}")
        for name in ("cx_px", "cy_px"):
            if not math.isfinite(getattr(self, name)):
                raise ConfigError(f"camera {name} must be finite, got {getattr(self, name)}")
        if not 0 <= self.line_readout_ns * self.height_px <= MAX_READOUT_NS:
            raise ConfigError(
                f"line_readout_ns must be >= 0 and read the {self.height_px} rows within "
                f"{MAX_READOUT_NS / 1e9:g} s, got {self.line_readout_ns}"
            )
        if abs(self.gyro_time_offset_ns) > MAX_GYRO_OFFSET_NS:
            raise ConfigError(
                f"gyro_time_offset_ns must be within ±{MAX_GYRO_OFFSET_NS / 1e9:g} s, got "
                f"{self.gyro_time_offset_ns}"
            )
        check_rotation(self.gyro_to_camera, "gyro_to_camera")

    @property
    def rotation_gyro_to_camera(self) -> np.ndarray:
        """R as a 3x3 array (v_camera = R @ v_gyro)."""
        return np.asarray(self.gyro_to_camera, dtype=float).reshape(3, 3)

    def camera_fields(self) -> dict[str, Any]:
        """The ``<camera>`` element's content for ``make_metadata``."""
        return {
            "@name": self.name,
            "width_px": self.width_px,
            "height_px": self.height_px,
            "fx_px": float(self.fx_px),
            "fy_px": float(self.fy_px),
            "cx_px": float(self.cx_px),
            "cy_px": float(self.cy_px),
            "line_readout_ns": int(self.line_readout_ns),
            "gyro_to_camera": [float(v) for v in self.gyro_to_camera],
            "gyro_time_offset_ns": int(self.gyro_time_offset_ns),
        }

    def to_xml(
        self,
        timestamp_ns: int = 0,
        *,
        exposure_ns: int | None = None,
        frame_period_ns: int | None = None,
    ) -> bytes:
        """A standalone ``camera`` metadata document (e.g. a dataset's camera.xml)."""
        fields: dict[str, Any] = {"camera": self.camera_fields()}
        if exposure_ns is not None:
            fields["exposure_ns"] = int(exposure_ns)
        if frame_period_ns is not None:
            fields["frame_period_ns"] = int(frame_period_ns)
        return make_metadata("camera", timestamp_ns, fields)

    @classmethod
    def from_element(cls, root: Any, path: str = "camera") -> CameraModel:
        """Read the ``<camera>`` element under a validated metadata root."""

        def req(name: str) -> str:
            text = field_text(root, f"{path}/{name}")
            if text is None:
                raise SchemaError(f"camera description lacks <{name}>")
            return text

        camera = root.find("{urn:framegate:1}" + path)
        try:
            return cls._from_texts(req, root, path, camera)
        except (ConfigError, ValueError) as exc:
            raise SchemaError(f"metadata describes an impossible camera: {exc}") from exc

    @classmethod
    def _from_texts(cls, req: Any, root: Any, path: str, camera: Any) -> CameraModel:
        return cls(
            width_px=int(req("width_px")),
            height_px=int(req("height_px")),
            fx_px=float(req("fx_px")),
            fy_px=float(req("fy_px")),
            cx_px=float(req("cx_px")),
            cy_px=float(req("cy_px")),
            line_readout_ns=int(field_text(root, f"{path}/line_readout_ns") or 0),
            gyro_to_camera=tuple(float(v) for v in req("gyro_to_camera").split()),
            gyro_time_offset_ns=int(field_text(root, f"{path}/gyro_time_offset_ns") or 0),
            name=str(camera.get("name") or "camera") if camera is not None else "camera",
        )

    @classmethod
    def from_xml(cls, data: bytes | str) -> CameraModel:
        """Parse and validate a metadata document (kind ``camera`` or ``frame``) and read it."""
        root = validate_metadata(data)
        return cls.from_element(root)


def check_rotation(values: Sequence[float], what: str) -> None:
    """ConfigError naming ``what`` (a field or a flag) unless ``values`` are a row-major
    3x3 rotation: 9 finite numbers, orthonormal, determinant +1."""
    if len(values) != 9:
        raise ConfigError(f"{what} needs 9 numbers (row-major 3x3), got {len(values)}")
    rotation = np.asarray(values, dtype=float).reshape(3, 3)
    with np.errstate(over="ignore", invalid="ignore"):  # 1e300 entries: refused, not logged
        is_rotation = bool(
            np.isfinite(rotation).all()
            and np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-3)
            and np.linalg.det(rotation) > 0
        )
    if not is_rotation:
        raise ConfigError(f"{what} must be a rotation matrix, got {tuple(values)}")
