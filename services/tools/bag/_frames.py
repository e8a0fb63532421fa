"""Reading a ``frame`` element's image layout from its metadata (see ``schemas/frame.xsd``)."""

from __future__ import annotations

from dataclasses import dataclass

from middleware import FramegateError, field_text, parse_untrusted


def _channels() -> dict[str, int]:
    """Channels per raw encoding. Imported on first use: ``services.lib.messages`` brings
    NumPy, which ``record`` must not wait for before its recording starts."""
    from services.lib.messages import FRAME_CHANNELS

    return FRAME_CHANNELS


@dataclass(frozen=True, slots=True)
class FrameLayout:
    """How a raw frame payload is laid out: row-major, no padding."""

    encoding: str
    width_px: int
    height_px: int

    @property
    def channels(self) -> int:
        return _channels()[self.encoding]

    @property
    def step_bytes(self) -> int:
        """Bytes per row."""
        return self.width_px * self.channels

    @property
    def size_bytes(self) -> int:
        return self.step_bytes * self.height_px


def metadata_kind(metadata: bytes) -> str | None:
    """The ``kind`` attribute of a metadata document, or None if it cannot be read."""
    try:
        kind = parse_untrusted(metadata).get("kind")
    except FramegateError:
        return None
    return str(kind) if kind is not None else None


def frame_layout(metadata: bytes, payload_bytes: int | None = None) -> FrameLayout | None:
    """The layout of a ``frame`` element, or None if it is not a raw frame we can show.

    With ``payload_bytes`` the layout must also account for the payload exactly, so a
    mislabelled payload is never drawn as an image.
    """
    try:
        root = parse_untrusted(metadata)
    except FramegateError:
        return None
    if root.get("kind") != "frame":
        return None
    encoding = field_text(root, "encoding")
    width, height = field_text(root, "width_px"), field_text(root, "height_px")
    if encoding not in _channels() or width is None or height is None:
        return None
    try:
        layout = FrameLayout(encoding, int(width), int(height))
    except ValueError:
        return None
    if layout.width_px < 1 or layout.height_px < 1:
        return None
    if payload_bytes is not None and payload_bytes != layout.size_bytes:
        return None
    return layout
