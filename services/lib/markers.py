"""The marker board of the paper's evaluation (§5.2) and the ArUco detector that reads it.

Three square ArUco markers (``DICT_4X4_50``) of different sizes on one white board. The
simulator paints this board on its wall; the detector service reads it back with
:func:`detect_markers`, so both sides share one definition of ids, names and sizes.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import cv2
import numpy as np

from services.lib.frame_pixels import gray8

__all__ = [
    "BOARD_HEIGHT_M",
    "BOARD_MARKERS",
    "BOARD_REFLECTANCE",
    "BOARD_WIDTH_M",
    "DICTIONARY_ID",
    "MARKER_BLACK_REFLECTANCE",
    "BoardMarker",
    "MarkerDetection",
    "detect_markers",
    "marker_bits",
    "marker_by_id",
]

DICTIONARY_ID = cv2.aruco.DICT_4X4_50
"""The ArUco dictionary of every marker on the board (4x4 data bits, 50 ids)."""


@dataclass(frozen=True, slots=True)
class BoardMarker:
    """One marker on the board.

    ``size_m`` is the side of the black square including its one-cell border (ArUco's
    meaning of marker size). The centre is in board coordinates as seen when facing the
    board: ``centre_x_m`` from the board's left edge, ``centre_y_m`` up from its bottom edge.
    """

    name: str
    marker_id: int
    size_m: float
    centre_x_m: float
    centre_y_m: float


BOARD_WIDTH_M = 0.90
BOARD_HEIGHT_M = 1.25

# Sizes from the paper's setup; the large marker sits on top so that it is the one that leaves
# the top of a slightly down-tilted camera's view first when the robot comes close.
BOARD_MARKERS: tuple[BoardMarker, ...] = (
    BoardMarker("large", 0, 0.56, 0.45, 0.85),
    BoardMarker("medium", 1, 0.26, 0.25, 0.25),
    BoardMarker("small", 2, 0.115, 0.65, 0.25),
)

# Matte white board and printed black, as reflectances in [0, 1].
BOARD_REFLECTANCE = 0.85
MARKER_BLACK_REFLECTANCE = 0.05


def marker_by_id(marker_id: int) -> BoardMarker | None:
    """The board marker with this id, or None for an id that is not on the board."""
    for marker in BOARD_MARKERS:
        if marker.marker_id == marker_id:
            return marker
    return None


def marker_bits(marker_id: int) -> np.ndarray:
    """The marker's cells including its border: a 6x6 bool array, True = white."""
    dictionary = cv2.aruco.getPredefinedDictionary(DICTIONARY_ID)
    cells = cv2.aruco.generateImageMarker(dictionary, marker_id, 6, borderBits=1)
    return np.asarray(cells) > 127


@dataclass(frozen=True, slots=True)
class MarkerDetection:
    """One decoded marker in an image.

    ``corners_px`` are the four corners (x, y) in ArUco's order (clockwise from the marker's
    top-left); ``size_px`` is the mean side length. ``name`` is None for an id not on the board.
    """

    marker_id: int
    name: str | None
    corners_px: tuple[tuple[float, float], ...]
    centre_px: tuple[float, float]
    size_px: float


# cv2 objects are not documented as thread-safe; each thread gets its own detector.
_local = threading.local()


def _detector() -> cv2.aruco.ArucoDetector:
    detector = getattr(_local, "detector", None)
    if detector is None:
        dictionary = cv2.aruco.getPredefinedDictionary(DICTIONARY_ID)
        detector = cv2.aruco.ArucoDetector(dictionary, cv2.aruco.DetectorParameters())
        _local.detector = detector
    return detector


def detect_markers(image: np.ndarray, encoding: str | None = None) -> list[MarkerDetection]:
    """Decode the ArUco markers in an image of a frame, sorted by id.

    ``encoding`` is the frame's (any of ``FRAME_CHANNELS``): the detector reads one 8-bit
    channel, made by ``gray8`` from the colours in the order the encoding names (alpha is
    ignored) or from mono16 scaled by the frame's brightest pixel (``frame_pixels`` says
    why not ``>> 8``). None reads a 2-D array as mono8 (mono16 if it is uint16), 3
    channels as bgr8, 4 as bgra8.

    Default OpenCV detector parameters: the point is to measure how blur affects an
    ordinary detector, not to tune one.
    """
    gray = gray8(image, encoding)
    corners, ids, _rejected = _detector().detectMarkers(gray)
    if ids is None:
        return []
    found = []
    for quad, marker_id in zip(corners, ids.ravel(), strict=True):
        points = np.asarray(quad, dtype=float).reshape(4, 2)
        sides = np.linalg.norm(points - np.roll(points, 1, axis=0), axis=1)
        board_marker = marker_by_id(int(marker_id))
        found.append(
            MarkerDetection(
                marker_id=int(marker_id),
                name=board_marker.name if board_marker else None,
                corners_px=tuple((float(x), float(y)) for x, y in points),
                centre_px=(float(points[:, 0].mean()), float(points[:, 1].mean())),
                size_px=float(sides.mean()),
            )
        )
    return sorted(found, key=lambda d: (d.marker_id, d.centre_px))
