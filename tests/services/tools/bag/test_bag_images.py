"""Frames as Foxglove images, in every encoding a frame can have: the recording's
``foxglove.RawImage`` channel, the viewer's RawImage and its JPEGs."""

from __future__ import annotations

import base64
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader

from middleware import DataObject, Retention
from services.lib.frame_layout import FRAME_BYTES_PER_PIXEL, FRAME_CHANNELS, FrameLayout
from services.lib.messages import frame_metadata_of
from services.lib.quality import Exposure
from services.tools.bag import BagWriter
from services.tools.bag._derived import jpeg_image, raw_image
from tests.services.tools.bag.test_bag_derived import _decoded

T = 1_700_000_000_123_456_789
W, H = 8, 6


def _frame(encoding: str) -> DataObject:
    size = W * H * FRAME_BYTES_PER_PIXEL[encoding]
    payload = (np.arange(size) % 251).astype(np.uint8).tobytes()
    return DataObject(T, payload, frame_metadata_of(1, Exposure(T, 5), encoding, W, H, None))


@pytest.mark.parametrize("encoding", sorted(FRAME_CHANNELS))
def test_a_recording_shows_each_frame_with_its_foxglove_encoding_and_step(
    tmp_path: Path, encoding: str
) -> None:
    frame = _frame(encoding)
    path = tmp_path / "a.mcap"
    with BagWriter(path) as writer:
        writer.add_buffer("zed", "images", kind="frame", retention=Retention())
        writer.write("zed/images", frame)
    with path.open("rb") as stream:
        [(schema, _channel, message)] = list(
            make_reader(stream).iter_messages(topics=["/zed/images/image"])
        )
    assert schema is not None and schema.name == "foxglove.RawImage"
    body = json.loads(message.data)
    # Foxglove's RawImage takes the ROS 2 names: mono8, mono16 (little-endian), bgr8, rgb8,
    # bgra8, rgba8 (its docs).
    assert (body["encoding"], body["width"], body["height"], body["step"]) == (
        encoding,
        W,
        H,
        W * FRAME_BYTES_PER_PIXEL[encoding],
    )
    assert base64.b64decode(body["data"]) == frame.payload


@pytest.mark.parametrize("encoding", ["bgra8", "rgba8", "mono16"])
def test_the_viewer_sends_new_encodings_frames_as_raw_images_of_their_encoding(
    encoding: str,
) -> None:
    image = _decoded(raw_image(_frame(encoding), FrameLayout(encoding, W, H), "zed"))
    step = W * FRAME_BYTES_PER_PIXEL[encoding]
    assert (image.encoding, image.width, image.step) == (encoding, W, step)


@pytest.mark.parametrize("encoding", ["bgra8", "rgba8"])
def test_a_four_channel_frame_becomes_a_colour_jpeg_without_its_alpha(encoding: str) -> None:
    pixel = [0, 0, 255, 0] if encoding == "bgra8" else [255, 0, 0, 0]  # red, transparent
    payload = np.tile(np.array(pixel, np.uint8), (H, W, 1)).tobytes()
    frame = DataObject(T, payload, frame_metadata_of(1, Exposure(T, 5), encoding, W, H, None))
    jpeg = jpeg_image(frame, FrameLayout(encoding, W, H), "zed", 95).encode()
    start = jpeg.index(b"\xff\xd8")
    decoded = cv2.imdecode(np.frombuffer(jpeg[start:], np.uint8), cv2.IMREAD_UNCHANGED)
    assert decoded is not None and decoded.shape == (H, W, 3)
    blue, green, red = decoded[H // 2, W // 2].tolist()
    assert red > 240 and blue < 15 and green < 15


def test_a_mono16_frame_becomes_a_gray_jpeg_scaled_to_its_brightest_pixel() -> None:
    samples = np.tile(np.array([0, 4095], "<u2"), (H, W // 2))  # a 12-bit sensor's extremes
    metadata = frame_metadata_of(1, Exposure(T, 5), "mono16", W, H, None)
    frame = DataObject(T, samples.tobytes(), metadata)
    jpeg = jpeg_image(frame, FrameLayout("mono16", W, H), "ir", 95).encode()
    start = jpeg.index(b"\xff\xd8")
    decoded = cv2.imdecode(np.frombuffer(jpeg[start:], np.uint8), cv2.IMREAD_UNCHANGED)
    assert decoded is not None and decoded.shape == (H, W) and decoded.dtype == np.uint8
    assert decoded.max() > 200  # 4095 is white, not 4095 >> 8 = 15
