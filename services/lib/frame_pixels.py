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

from services.lib.frame_layout import FRAME_CHANNELS, FRAME_SAMPLE_BYTES, FrameError, FrameLayout

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


# The array type of one channel sample: mono16 is little-endian (frame.xsd).
_DTYPES: dict[int, np.dtype[Any]] = {1: np.dtype(np.uint8), 2: np.dtype("<u2")}


def frame_array(payload: bytes, layout: FrameLayout) -> npt.NDArray[Any]:
    """The payload as a read-only array view (no copy): ``(height, width)`` for one
    channel, ``(height, width, channels)`` otherwise; ``uint8``, ``uint16`` for mono16.
    FrameError if the payload does not hold the frame ``layout`` describes."""
    layout.check_payload(len(payload))
    shape: tuple[int, ...] = (layout.height_px, layout.width_px)
    if layout.channels > 1:
        shape += (layout.channels,)
    dtype = _DTYPES[FRAME_SAMPLE_BYTES[layout.encoding]]
    return np.frombuffer(payload, dtype=dtype).reshape(shape)


def _encoding_of(image: npt.NDArray[Any], encoding: str | None) -> str:
    """``encoding``, or for None the one an OpenCV image of this shape has (mono8, mono16
    for a uint16 one, bgr8, bgra8); FrameError for an encoding framegate has no frame of,
    or an image that is not one of its."""
    if encoding is None:
        channels = 1 if image.ndim == 2 else int(image.shape[-1]) if image.ndim == 3 else 0
        if channels not in (1, 3, 4):
            raise FrameError(
                "bad-size",
                f"an image of shape {image.shape} is no frame: give its encoding, or an "
                "(h, w), (h, w, 3) or (h, w, 4) array",
            )
        wide = channels == 1 and image.dtype == np.uint16
        encoding = "mono16" if wide else {1: "mono8", 3: "bgr8", 4: "bgra8"}[channels]
    if encoding not in FRAME_CHANNELS:
        raise FrameError("bad-encoding", f"encoding {encoding!r} of an image {image.shape}")
    channels = FRAME_CHANNELS[encoding]
    if image.ndim != (2 if channels == 1 else 3) or (channels > 1 and image.shape[2] != channels):
        raise FrameError("bad-size", f"a {encoding} image cannot have shape {image.shape}")
    dtype = _DTYPES[FRAME_SAMPLE_BYTES[encoding]]
    if image.dtype != dtype:
        raise FrameError("bad-encoding", f"a {encoding} image is {dtype}, not {image.dtype}")
    return encoding


def _mono16_to_8(image: npt.NDArray[Any]) -> npt.NDArray[np.uint8]:
    """A mono16 image scaled so that its brightest pixel is 255.

    Scaled by the frame's maximum, not shifted by 8 bits: a 10- or 12-bit sensor published
    as mono16 (the common case for IR and machine-vision cameras) fills only the low bits,
    and ``>> 8`` would leave it 4 or 16 gray levels (a 10-bit frame's markers are then
    below the ArUco detector's threshold constant and lost: test_markers). The scale
    varies from frame to frame, which the detector's adaptive threshold (a local mean) does
    not mind; one hot pixel at full scale makes it ``>> 8``, never worse."""
    import cv2

    peak = int(image.max()) if image.size else 0
    if peak == 0:
        return np.zeros(image.shape, np.uint8)
    return np.asarray(cv2.convertScaleAbs(image, alpha=255.0 / peak), dtype=np.uint8)


def gray8(image: npt.NDArray[Any], encoding: str | None = None) -> npt.NDArray[np.uint8]:
    """The image as one 8-bit channel ``(height, width)``: what a detector that reads
    brightness takes (the ArUco detector). ``encoding`` is the frame's; None reads a
    2-D array as mono8 (mono16 if it is uint16), 3 channels as bgr8, 4 as bgra8 (OpenCV's
    own orders). A mono16 image is scaled by its brightest pixel (``_mono16_to_8``)."""
    import cv2  # here: see the module's docstring

    name = _encoding_of(image, encoding)
    if name == "mono8":
        return np.asarray(image, dtype=np.uint8)
    if name == "mono16":
        return _mono16_to_8(image)
    return np.asarray(cv2.cvtColor(image, getattr(cv2, _TO_GRAY[name])), dtype=np.uint8)


def opencv_order(image: npt.NDArray[Any], encoding: str | None = None) -> npt.NDArray[Any]:
    """The image with its channels in OpenCV's order (gray, BGR or BGRA), nothing else
    changed: what ``cv2.imencode(".png", ...)`` writes losslessly (alpha and 16 bits
    included)."""
    import cv2

    name = _encoding_of(image, encoding)
    if name in _TO_BGR_ORDER:
        return np.asarray(cv2.cvtColor(image, getattr(cv2, _TO_BGR_ORDER[name])))
    return image


def bgr8(image: npt.NDArray[Any], encoding: str | None = None) -> npt.NDArray[np.uint8]:
    """The image as 8-bit gray or BGR without alpha: what a JPEG holds (mono16 scaled as
    :func:`gray8` scales it)."""
    import cv2

    name = _encoding_of(image, encoding)
    if name == "mono16":
        return _mono16_to_8(image)
    if name in _TO_BGR:
        return np.asarray(cv2.cvtColor(image, getattr(cv2, _TO_BGR[name])), dtype=np.uint8)
    return np.asarray(image, dtype=np.uint8)
