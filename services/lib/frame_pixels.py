"""A raw frame's pixels as NumPy: the array a payload is, and the images OpenCV takes.

``frame_layout`` says how many bytes a payload holds; this module says what array they
are, for every encoding of ``FRAME_CHANNELS``, so that a vision handler, the marker
detector, ``query --save`` and the viewer's JPEGs read a frame alike. OpenCV is imported in
the functions that need it: the mediator and the vision runner read arrays and start faster
without it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from services.lib.frame_layout import FRAME_CHANNELS, FrameError, FrameLayout

__all__ = ["bgr8", "frame_array", "gray8", "opencv_order"]

# Channel order to OpenCV's (B, G, R[, A]), for the encodings not already in it.
_TO_BGR_ORDER = {"rgb8": "COLOR_RGB2BGR", "rgba8": "COLOR_RGBA2BGRA"}
# To one 8-bit channel, as OpenCV weighs colours (ITU-R BT.601); alpha is left out.
_TO_GRAY = {
    "bgr8": "COLOR_BGR2GRAY",
    "rgb8": "COLOR_RGB2GRAY",
    "bgra8": "COLOR_BGRA2GRAY",
    "rgba8": "COLOR_RGBA2GRAY",
}
# To 8-bit BGR without alpha (what a JPEG holds).
_TO_BGR = {"rgb8": "COLOR_RGB2BGR", "bgra8": "COLOR_BGRA2BGR", "rgba8": "COLOR_RGBA2BGR"}


def frame_array(payload: bytes, layout: FrameLayout) -> npt.NDArray[Any]:
    """The payload as a read-only array view (no copy): ``(height, width)`` for one
    channel, ``(height, width, channels)`` otherwise, ``uint8``. FrameError if the payload
    does not hold the frame ``layout`` describes."""
    layout.check_payload(len(payload))
    shape: tuple[int, ...] = (layout.height_px, layout.width_px)
    if layout.channels > 1:
        shape += (layout.channels,)
    return np.frombuffer(payload, dtype=np.uint8).reshape(shape)


def _encoding_of(image: npt.NDArray[Any], encoding: str | None) -> str:
    """``encoding``, or for None the one an OpenCV image of this shape has (mono8, bgr8,
    bgra8); FrameError for an encoding framegate has no frame of, or a shape that is not
    one of its images."""
    if encoding is None:
        channels = 1 if image.ndim == 2 else int(image.shape[-1]) if image.ndim == 3 else 0
        if channels not in (1, 3, 4):
            raise FrameError(
                "bad-size",
                f"an image of shape {image.shape} is no frame: give its encoding, or an "
                "(h, w), (h, w, 3) or (h, w, 4) array",
            )
        encoding = {1: "mono8", 3: "bgr8", 4: "bgra8"}[channels]
    if encoding not in FRAME_CHANNELS:
        raise FrameError("bad-encoding", f"encoding {encoding!r} of an image {image.shape}")
    channels = FRAME_CHANNELS[encoding]
    if image.ndim != (2 if channels == 1 else 3) or (channels > 1 and image.shape[2] != channels):
        raise FrameError("bad-size", f"a {encoding} image cannot have shape {image.shape}")
    return encoding


def gray8(image: npt.NDArray[Any], encoding: str | None = None) -> npt.NDArray[np.uint8]:
    """The image as one 8-bit channel ``(height, width)``: what a detector that reads
    brightness takes (the ArUco detector). ``encoding`` is the frame's; None reads a
    2-D array as mono8, 3 channels as bgr8, 4 as bgra8 (OpenCV's own orders)."""
    import cv2  # here: see the module's docstring

    name = _encoding_of(image, encoding)
    if name == "mono8":
        return np.asarray(image, dtype=np.uint8)
    return np.asarray(cv2.cvtColor(image, getattr(cv2, _TO_GRAY[name])), dtype=np.uint8)


def opencv_order(image: npt.NDArray[Any], encoding: str | None = None) -> npt.NDArray[Any]:
    """The image with its channels in OpenCV's order (gray, BGR or BGRA), nothing else
    changed: what ``cv2.imencode(".png", ...)`` writes losslessly (alpha included)."""
    import cv2

    name = _encoding_of(image, encoding)
    if name in _TO_BGR_ORDER:
        return np.asarray(cv2.cvtColor(image, getattr(cv2, _TO_BGR_ORDER[name])))
    return image


def bgr8(image: npt.NDArray[Any], encoding: str | None = None) -> npt.NDArray[np.uint8]:
    """The image as 8-bit gray or BGR without alpha: what a JPEG holds."""
    import cv2

    name = _encoding_of(image, encoding)
    if name in _TO_BGR:
        return np.asarray(cv2.cvtColor(image, getattr(cv2, _TO_BGR[name])), dtype=np.uint8)
    return np.asarray(image, dtype=np.uint8)
