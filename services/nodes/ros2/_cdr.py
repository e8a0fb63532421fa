"""ROS 2 messages in and out of CDR, through ``rosbags``' type store (no ROS 2 install).

The type store of the chosen distro gives the CDR layout and the RIHS01 type hash of every
message the bridge speaks. ``vision_msgs`` is not among rosbags' built-in types, so its
definitions (vision_msgs 4.x, Humble and later) are registered from their ``.msg`` text;
rosbags computes their hash from that text like rosidl does.

Copies: decoding an image yields a read-only numpy view into the received buffer (no copy);
encoding one copies the pixels once, after the head rosbags serializes.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from middleware import ConfigError
from services.lib.frame_layout import FRAME_BYTES_PER_PIXEL, FRAME_SAMPLE_BYTES

IMAGE = "sensor_msgs/msg/Image"
IMU = "sensor_msgs/msg/Imu"
STRING = "std_msgs/msg/String"
DETECTIONS = "vision_msgs/msg/Detection2DArray"

# vision_msgs 4.x, field for field (the hash covers names and types, not comments).
_VISION_MSGS = {
    "vision_msgs/msg/Point2D": "float64 x\nfloat64 y\n",
    "vision_msgs/msg/Pose2D": "vision_msgs/Point2D position\nfloat64 theta\n",
    "vision_msgs/msg/BoundingBox2D": "vision_msgs/Pose2D center\nfloat64 size_x\nfloat64 size_y\n",
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": (
        "vision_msgs/ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n"
    ),
    "vision_msgs/msg/Detection2D": (
        "std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\n"
        "vision_msgs/BoundingBox2D bbox\nstring id\n"
    ),
    DETECTIONS: "std_msgs/Header header\nvision_msgs/Detection2D[] detections\n",
}
_STORES = {
    "humble": Stores.ROS2_HUMBLE,
    "jazzy": Stores.ROS2_JAZZY,
    "kilted": Stores.ROS2_KILTED,
    "rolling": Stores.LATEST,
}
_EMPTY = np.empty(0, dtype=np.uint8)
_LENGTH = struct.Struct("<I")  # a CDR sequence length, little-endian like the head
# Bytes per pixel of the encodings a framegate frame can hold (one table: a frame's).
BYTES_PER_PIXEL = FRAME_BYTES_PER_PIXEL


class CdrError(ValueError):
    """A message that cannot be what it claims: its text names the bad value."""


class StampError(CdrError):
    """A ``builtin_interfaces/msg/Time`` out of range (a ``bad-stamp``, not a bad message)."""


@dataclass(frozen=True, slots=True)
class Image:
    """A decoded ``sensor_msgs/msg/Image``: stamp, size and a view of its pixel rows;
    ``swap``: its samples are big-endian and wider than a byte (``is_bigendian`` mono16)."""

    stamp_ns: int
    frame_id: str
    width: int
    height: int
    encoding: str
    step: int
    data: npt.NDArray[np.uint8]
    swap: bool = False

    def pixels(self) -> bytes:
        """The image without row padding, as framegate stores it (one copy), its samples
        little-endian."""
        row = self.width * BYTES_PER_PIXEL[self.encoding]
        rows = self.data[: self.step * self.height].reshape(self.height, self.step)[:, :row]
        if self.swap:
            # Swapped, not refused: the values are the camera's all the same, and frames
            # are little-endian (frame.xsd). This rare path copies twice.
            return rows.view(">u2").astype("<u2").tobytes()
        if self.step == row:
            return self.data.tobytes()
        return rows.tobytes()


def stamp_ns(stamp: Any) -> int:
    """A ROS 2 time in ns, field by field: ``nanosec`` must be below 10^9 (4e9 is not +4 s)
    and ``sec`` not negative (before 1970); StampError otherwise. ``sec`` is an int32, so
    the largest stamp is in 2038; the caller's horizon check refuses such a future."""
    sec, nanosec = int(stamp.sec), int(stamp.nanosec)
    if not 0 <= nanosec < 1_000_000_000 or sec < 0:
        raise StampError(f"header.stamp sec={sec} nanosec={nanosec} is not a time")
    return sec * 1_000_000_000 + nanosec


class Codec:
    """Encode and decode the bridge's messages for one distro's type store."""

    def __init__(self, distro: str) -> None:
        if distro not in _STORES:
            raise ConfigError(f"unknown ROS 2 distro {distro!r}; use one of {', '.join(_STORES)}")
        self.distro = distro
        self.store = get_typestore(_STORES[distro])
        missing = {k: v for k, v in _VISION_MSGS.items() if k not in self.store.types}
        for name, text in missing.items():
            self.store.register(get_types_from_msg(text, name))
        types = self.store.types
        self._image, self._header_cls, self._time = (
            types[IMAGE],
            types["std_msgs/msg/Header"],
            types["builtin_interfaces/msg/Time"],
        )

    def first_field(self, ros_type: str) -> str | None:
        """The type of a message type's first field (``std_msgs/msg/Header``, ``string``),
        or None when the type store does not know ``ros_type`` (a node's own package)."""
        try:
            _consts, fields = self.store.fielddefs[ros_type]
            kind = fields[0][1][1]
        except (KeyError, IndexError, TypeError):
            return None
        return str(kind[0] if isinstance(kind, tuple) else kind)

    def rihs01(self, ros_type: str) -> str:
        """The RIHS01 type hash of ``ros_type``."""
        return str(self.store.hash_rihs01(ros_type))

    def _stamp(self, t_ns: int) -> Any:
        return self._time(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)

    def _header_type(self, t_ns: int, frame_id: str) -> Any:
        return self._header_cls(stamp=self._stamp(t_ns), frame_id=frame_id)

    # -- images ------------------------------------------------------------------------------
    def decode_image(self, raw: bytes) -> Image:
        """CdrError for a message that is not a consistent image of an encoding a frame
        can have (``FRAME_CHANNELS``; the text names them)."""
        try:
            # A memoryview: rosbags slices it (a bytes slice would copy the whole message)
            # and the pixels stay a view into ``raw``.
            msg: Any = self.store.deserialize_cdr(memoryview(raw), IMAGE)
        except Exception as exc:  # rosbags raises several types for truncated input
            raise CdrError(f"not a CDR {IMAGE}: {exc}") from exc
        width, height, step = int(msg.width), int(msg.height), int(msg.step)
        encoding = str(msg.encoding)
        if encoding not in BYTES_PER_PIXEL:
            raise CdrError(f"encoding {encoding!r} (framegate takes {', '.join(BYTES_PER_PIXEL)})")
        row = width * BYTES_PER_PIXEL[encoding]
        if width <= 0 or height <= 0 or step < row or len(msg.data) != step * height:
            raise CdrError(
                f"{width}x{height} {encoding} with step {step} needs {step * height} bytes "
                f"(step >= {row}), data has {len(msg.data)}"
            )
        return Image(
            stamp_ns(msg.header.stamp),
            str(msg.header.frame_id),
            width,
            height,
            encoding,
            step,
            msg.data,
            swap=bool(msg.is_bigendian) and FRAME_SAMPLE_BYTES[encoding] > 1,
        )

    def encode_image(
        self, t_ns: int, frame_id: str, width: int, height: int, encoding: str, pixels: bytes
    ) -> bytes:
        """A CDR ``sensor_msgs/msg/Image``; the pixels are copied once, into the result.

        rosbags serializes everything but the pixels (the message with empty ``data`` ends
        with the sequence's uint32 length, 0); the result is that head with the length set,
        then the pixels, joined in one allocation. A full rosbags serialization would first
        zero a buffer of the frame's size and then copy into it (test_cdr checks that both
        give the same bytes).
        """
        step = width * BYTES_PER_PIXEL[encoding]  # frames are little-endian: is_bigendian=0
        head = self._image(
            header=self._header_type(t_ns, frame_id),
            height=height,
            width=width,
            encoding=encoding,
            is_bigendian=0,
            step=step,
            data=_EMPTY,
        )
        cdr = self.store.serialize_cdr(head, IMAGE)
        return b"".join((cdr[:-4], _LENGTH.pack(memoryview(pixels).nbytes), pixels))

    # -- IMU ---------------------------------------------------------------------------------
    def decode_imu_frame(self, raw: bytes) -> tuple[int, tuple[float, float, float], str]:
        """(stamp, angular velocity in rad/s, header.frame_id); CdrError for a malformed message."""
        try:
            msg: Any = self.store.deserialize_cdr(memoryview(raw), IMU)
        except Exception as exc:
            raise CdrError(f"not a CDR {IMU}: {exc}") from exc
        w = msg.angular_velocity
        rates = (float(w.x), float(w.y), float(w.z))
        if not all(np.isfinite(rates)):
            raise CdrError(f"angular velocity {rates} is not finite")
        return stamp_ns(msg.header.stamp), rates, str(msg.header.frame_id)

    # -- detections and verdicts -------------------------------------------------------------
    def encode_detections(
        self,
        t_ns: int,
        frame_id: str,
        markers: list[tuple[int, list[float]]],
        scores: list[float | None] | None = None,
    ) -> bytearray:
        """A ``vision_msgs/msg/Detection2DArray``: one axis-aligned box per marker (its
        corners' extent), class id = the marker id, score = its ``scores`` entry (in the
        same order), 1 where it has none (a marker detector's find is certain)."""
        t = self.store.types
        header = self._header_type(t_ns, frame_id)
        pose = t["geometry_msgs/msg/PoseWithCovariance"](
            pose=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](0.0, 0.0, 0.0),
                orientation=t["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 1.0),
            ),
            covariance=np.zeros(36, dtype=np.float64),
        )
        detections = []
        for n, (marker_id, corners) in enumerate(markers):
            score = scores[n] if scores is not None and n < len(scores) else None
            xs, ys = corners[0::2], corners[1::2]
            x0, x1, y0, y1 = min(xs), max(xs), min(ys), max(ys)
            box = t["vision_msgs/msg/BoundingBox2D"](
                center=t["vision_msgs/msg/Pose2D"](
                    position=t["vision_msgs/msg/Point2D"]((x0 + x1) / 2, (y0 + y1) / 2),
                    theta=0.0,
                ),
                size_x=x1 - x0,
                size_y=y1 - y0,
            )
            hypothesis = t["vision_msgs/msg/ObjectHypothesisWithPose"](
                hypothesis=t["vision_msgs/msg/ObjectHypothesis"](
                    str(marker_id), 1.0 if score is None else float(score)
                ),
                pose=pose,
            )
            detections.append(
                t["vision_msgs/msg/Detection2D"](
                    header=header, results=[hypothesis], bbox=box, id=str(marker_id)
                )
            )
        message = t[DETECTIONS](header=header, detections=detections)
        return _owner(self.store.serialize_cdr(message, DETECTIONS))

    def encode_string(self, fields: dict[str, Any]) -> bytearray:
        """A ``std_msgs/msg/String`` holding ``fields`` as one line of JSON."""
        text = json.dumps(fields, separators=(",", ":"), sort_keys=True)
        return _owner(self.store.serialize_cdr(self.store.types[STRING](data=text), STRING))

    def decode(self, raw: bytes, ros_type: str) -> Any:
        """Any message of the store (for tests and tools)."""
        return self.store.deserialize_cdr(raw, ros_type)


def _owner(view: memoryview) -> bytearray:
    """The bytearray rosbags serialized into (Zenoh takes bytearrays, not memoryviews)."""
    owner = view.obj
    if isinstance(owner, bytearray) and len(owner) == view.nbytes:
        return owner
    return bytearray(view)  # only if rosbags ever hands out a slice
