"""A raw frame's layout: its encoding's channels, their bytes and the payload size they
make, the one place that says how many bytes a ``frame`` element's payload must hold.

Light on purpose (no NumPy): ``record`` and ``query --save`` read layouts before anything
else is imported, and the ROS 2 bridge checks every frame it publishes with it.
"""

from __future__ import annotations

from dataclasses import dataclass

from middleware import FramegateError, SchemaError, field_text, parse_untrusted

# Channels per pixel of the raw encodings frame.xsd allows (the ROS 2 sensor_msgs names):
# bgra8/rgba8 are colour with alpha (a ZED camera publishes bgra8), row-major, no padding.
FRAME_CHANNELS = {"mono8": 1, "mono16": 1, "bgr8": 3, "rgb8": 3, "bgra8": 4, "rgba8": 4}
# Bytes per channel: mono16 (16-bit mono or IR cameras) has 2, little-endian always, as a
# ROS 2 image with is_bigendian=0 has them (the bridge swaps a big-endian one's bytes).
FRAME_SAMPLE_BYTES = {"mono8": 1, "mono16": 2, "bgr8": 1, "rgb8": 1, "bgra8": 1, "rgba8": 1}
# Bytes per pixel, what a row and a payload are counted in.
FRAME_BYTES_PER_PIXEL = {e: n * FRAME_SAMPLE_BYTES[e] for e, n in FRAME_CHANNELS.items()}


class FrameError(SchemaError):
    """A frame no consumer could use, whatever its XSD allowed: metadata that names no raw
    frame, a payload that does not hold the frame it names, an exposure no camera takes;
    ``reason`` names the check (``bad-size``, ``bad-encoding``, ``bad-payload-size``,
    ``bad-exposure``, ``not-a-frame``)."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


@dataclass(frozen=True, slots=True)
class FrameLayout:
    """How a raw frame payload is laid out: row-major, no padding."""

    encoding: str
    width_px: int
    height_px: int

    @property
    def channels(self) -> int:
        return FRAME_CHANNELS[self.encoding]

    @property
    def bytes_per_pixel(self) -> int:
        """Channels times the bytes of one (2 for mono16, else 1)."""
        return FRAME_BYTES_PER_PIXEL[self.encoding]

    @property
    def step_bytes(self) -> int:
        """Bytes per row."""
        return self.width_px * self.bytes_per_pixel

    @property
    def size_bytes(self) -> int:
        return self.step_bytes * self.height_px

    @classmethod
    def checked(cls, encoding: str, width_px: int, height_px: int) -> FrameLayout:
        """The layout, or FrameError for an encoding or size no raw frame has."""
        if encoding not in FRAME_CHANNELS:
            raise FrameError("bad-encoding", f"encoding {encoding!r}")
        if width_px <= 0 or height_px <= 0:
            raise FrameError("bad-size", f"size {width_px}x{height_px}")
        return cls(encoding, width_px, height_px)

    def check_payload(self, payload_bytes: int, what: str = "frame") -> None:
        """FrameError unless a payload of ``payload_bytes`` holds exactly this frame."""
        if payload_bytes != self.size_bytes:
            raise FrameError(
                "bad-payload-size",
                f"{what}: payload is {payload_bytes} bytes, metadata says "
                f"{self.width_px}x{self.height_px} {self.encoding} = {self.size_bytes}",
            )


def metadata_kind(metadata: bytes) -> str | None:
    """The ``kind`` attribute of a metadata document, or None if it cannot be read."""
    try:
        kind = parse_untrusted(metadata).get("kind")
    except FramegateError:
        return None
    return str(kind) if kind is not None else None


def read_frame_layout(metadata: bytes, payload_bytes: int | None = None) -> FrameLayout:
    """The layout a ``frame`` element's metadata names (a hardened parse of three fields,
    about a tenth of a full read: for a consumer that trusts a framegate producer's schema
    check and needs only the size); with ``payload_bytes``, also checked against the
    payload. FrameError says what is wrong."""
    try:
        root = parse_untrusted(metadata)
    except FramegateError as exc:
        raise FrameError("not-a-frame", f"unreadable metadata: {exc}") from None
    if root.get("kind") != "frame":
        raise FrameError("not-a-frame", f"metadata of kind {root.get('kind')!r}, not frame")
    try:
        width = int(field_text(root, "width_px") or 0)
        height = int(field_text(root, "height_px") or 0)
    except ValueError:
        raise FrameError("bad-size", "width_px or height_px is no integer") from None
    layout = FrameLayout.checked(str(field_text(root, "encoding")), width, height)
    if payload_bytes is not None:
        layout.check_payload(payload_bytes)
    return layout


def frame_layout(metadata: bytes, payload_bytes: int | None = None) -> FrameLayout | None:
    """``read_frame_layout``, or None if the element is not a raw frame that can be shown
    (with ``payload_bytes``: one its payload accounts for exactly, so a mislabelled payload
    is never drawn as an image)."""
    try:
        return read_frame_layout(metadata, payload_bytes)
    except FrameError:
        return None
