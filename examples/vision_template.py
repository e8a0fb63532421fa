"""Your own vision code behind the mediator: multi-scale template matching with OpenCV.

``find_marker`` looks for the board's large ArUco marker (id 0 of ``DICT_4X4_50``) by
matching its picture at 8 sizes over the whole frame (``cv2.matchTemplate``): real work,
about 1.5 frame periods per frame at 15 fps on an otherwise idle 2-core machine, no
emulated delay. Run it behind the mediator (from the repository root)::

    framegate launch examples/vision.yaml          # camera, gyro, mediator, this handler
    framegate info vision/detections               # its results and skips
    framegate query vision/detections --last 5 --json   # each with its processing_ns
    framegate info mediator/images                 # its queue: the mediator's load

or by hand, beside a camera, gyro and mediator::

    framegate run vision --handler examples.vision_template:find_marker

Run this file to time the handler on a synthetic frame and see that it finds the marker::

    python examples/vision_template.py
"""

from __future__ import annotations

import argparse
import signal
import time

import cv2
import numpy as np
import numpy.typing as npt

from services.lib.quality import Exposure
from services.lib.vision import Box, FrameMeta, gray8

MARKER_ID = 0
# Marker sides tried, in pixels (with its white margin): from far away to close up.
SIDES_PX = tuple(int(s) for s in np.geomspace(28, 320, 8))
# Normalised correlation below this is "not found".
MIN_SCORE = 0.6
# The marker's picture: 6x6 cells drawn 10 px each, in a white margin of 1 cell.
_CELL_PX = 10


def _templates() -> list[tuple[int, npt.NDArray[np.uint8]]]:
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    marker = cv2.aruco.generateImageMarker(dictionary, MARKER_ID, 6 * _CELL_PX)
    framed = cv2.copyMakeBorder(
        marker, _CELL_PX, _CELL_PX, _CELL_PX, _CELL_PX, cv2.BORDER_CONSTANT, value=255
    )
    return [
        (side, np.asarray(cv2.resize(framed, (side, side), interpolation=cv2.INTER_AREA), np.uint8))
        for side in SIDES_PX
    ]


TEMPLATES = _templates()


def find_marker(image: np.ndarray, frame: FrameMeta) -> list[Box]:
    """The best match of the marker over all sizes, as one box (or none below MIN_SCORE)."""
    gray = gray8(image, frame.encoding)  # whatever the camera sends: mono8/16, BGR, RGBA...
    best: tuple[float, int, int, int] | None = None
    for side, template in TEMPLATES:
        if side > min(gray.shape):
            continue
        scores = cv2.matchTemplate(gray, template, cv2.TM_CCOEFF_NORMED)
        _low, score, _at_low, (x, y) = cv2.minMaxLoc(scores)
        if best is None or score > best[0]:
            best = (float(score), int(x), int(y), side)
    if best is None or best[0] < MIN_SCORE:
        return []
    score, x, y, side = best
    margin = side / 8  # the white margin is 1 cell of 8
    return [
        Box.from_xywh(
            MARKER_ID, x + margin, y + margin, side - 2 * margin, side - 2 * margin, score
        )
    ]


def positive(text: str) -> int:
    """A flag's count: an integer >= 1 (``0`` would time nothing and divide by zero)."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}")
    return value


def main(*, frames: int) -> int:
    """Time ``find_marker`` on a synthetic 1024x768 frame with the marker at a known place."""
    rng = np.random.default_rng(1)
    image = np.clip(rng.normal(160, 12, (768, 1024)), 0, 255).astype(np.uint8)
    side, template = TEMPLATES[4]
    image[300 : 300 + side, 500 : 500 + side] = template
    frame = FrameMeta(0, 0, Exposure(0, 30_000_000), "mono8", 1024, 768, None)
    print(f"timing find_marker on {frames} frames (Ctrl-C stops it) ...", flush=True)
    find_marker(image, frame)  # first call: OpenCV allocates its buffers
    started = time.perf_counter()
    for _ in range(frames):
        found = find_marker(image, frame)
    per_frame_ms = (time.perf_counter() - started) / frames * 1e3
    periods = per_frame_ms / (1000 / 15)
    print(f"find_marker: {per_frame_ms:.0f} ms per frame = {periods:.1f} frame periods at 15 fps")
    for box in found:
        print(f"found marker {box.label} at {box.corners_px[0]} (score {box.score:.2f})")
    return 0 if found else 1


if __name__ == "__main__":
    # Ctrl-C stops it even when its parent ignores SIGINT (a job a script put in the
    # background starts that way, and Python then never raises KeyboardInterrupt).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    parser = argparse.ArgumentParser(
        prog="vision_template", description=__doc__.splitlines()[0].replace("``", "")
    )
    parser.add_argument("--frames", type=positive, default=10, help="frames to time (default 10)")
    frames = parser.parse_args().frames
    try:
        code = main(frames=frames)
    except KeyboardInterrupt:  # Ctrl-C: the way to stop a long timing early
        code = 0
    raise SystemExit(code)
