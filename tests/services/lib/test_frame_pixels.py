"""A frame's payload as the array a handler gets, and as OpenCV's gray, BGR(A) and JPEG input."""

from __future__ import annotations

import numpy as np
import pytest

from services.lib.frame_layout import FrameError, FrameLayout
from services.lib.frame_pixels import bgr8, frame_array, gray8, opencv_order
from services.lib.messages import decode_image, frame_metadata, read_frame_metadata
from services.lib.quality import Exposure

# One pure blue pixel and one pure red pixel, in each encoding's channel order.
BLUE_RED = {
    "bgr8": [[[255, 0, 0], [0, 0, 255]]],
    "rgb8": [[[0, 0, 255], [255, 0, 0]]],
    "bgra8": [[[255, 0, 0, 7], [0, 0, 255, 7]]],
    "rgba8": [[[0, 0, 255, 7], [255, 0, 0, 7]]],
}


@pytest.mark.parametrize(
    ("encoding", "shape"),
    [("mono8", (5, 6)), ("bgr8", (5, 6, 3)), ("rgb8", (5, 6, 3)), ("bgra8", (5, 6, 4)),
     ("rgba8", (5, 6, 4))],
)  # fmt: skip
def test_a_payload_is_a_read_only_view_of_its_encodings_shape(
    encoding: str, shape: tuple[int, ...]
) -> None:
    payload = bytes(range(int(np.prod(shape))))
    image = frame_array(payload, FrameLayout(encoding, 6, 5))
    assert image.shape == shape and image.dtype == np.uint8
    assert image.tobytes() == payload and not image.flags.writeable
    with pytest.raises(FrameError, match="payload is 29 bytes"):
        frame_array(payload[:29], FrameLayout(encoding, 6, 5))


def test_a_mono16_payload_is_little_endian_uint16() -> None:
    image = frame_array(bytes([0x34, 0x12, 0xFF, 0x0F]), FrameLayout("mono16", 2, 1))
    assert image.dtype == np.dtype("<u2") and image.shape == (1, 2)
    assert image.tolist() == [[0x1234, 0x0FFF]]


def test_mono16_becomes_8_bit_scaled_by_its_brightest_pixel() -> None:
    twelve_bit = np.array([[0, 1024, 2048, 4095]], np.uint16)  # a 12-bit sensor's range
    assert gray8(twelve_bit, "mono16").tolist() == [[0, 64, 128, 255]]
    assert gray8(twelve_bit).tolist() == [[0, 64, 128, 255]]  # uint16 reads as mono16
    assert gray8(np.zeros((2, 2), np.uint16), "mono16").tolist() == [[0, 0], [0, 0]]
    assert bgr8(twelve_bit, "mono16").tolist() == [[0, 64, 128, 255]]  # a JPEG's
    assert opencv_order(twelve_bit, "mono16") is twelve_bit  # a PNG keeps all 16 bits


def test_an_array_of_another_type_than_its_encoding_is_refused() -> None:
    with pytest.raises(FrameError, match="a mono16 image is uint16, not uint8"):
        gray8(np.zeros((2, 2), np.uint8), "mono16")
    with pytest.raises(FrameError, match="a mono8 image is uint8, not uint16"):
        gray8(np.zeros((2, 2), np.uint16), "mono8")


@pytest.mark.parametrize("encoding", sorted(BLUE_RED))
def test_gray_weighs_each_colour_by_the_order_the_encoding_names(encoding: str) -> None:
    image = np.array(BLUE_RED[encoding], dtype=np.uint8)
    # BT.601: blue weighs 0.114, red 0.299; alpha is no brightness.
    assert gray8(image, encoding).tolist() == [[29, 76]]


def test_without_an_encoding_an_array_is_read_in_opencvs_own_order() -> None:
    assert gray8(np.array(BLUE_RED["bgra8"], dtype=np.uint8)).tolist() == [[29, 76]]
    assert gray8(np.array(BLUE_RED["bgr8"], dtype=np.uint8)).tolist() == [[29, 76]]
    mono = np.arange(6, dtype=np.uint8).reshape(2, 3)
    assert gray8(mono).tolist() == mono.tolist()


def test_an_image_of_another_shape_than_its_encoding_is_refused() -> None:
    with pytest.raises(FrameError, match=r"a bgra8 image cannot have shape \(1, 2, 3\)"):
        gray8(np.zeros((1, 2, 3), np.uint8), "bgra8")
    with pytest.raises(FrameError, match="encoding 'yuv422'"):
        gray8(np.zeros((1, 2), np.uint8), "yuv422")
    with pytest.raises(FrameError, match=r"shape \(1, 2, 2\) is no frame: give its encoding"):
        gray8(np.zeros((1, 2, 2), np.uint8))


@pytest.mark.parametrize("encoding", sorted(BLUE_RED))
def test_png_input_is_bgr_order_with_alpha_kept_and_jpeg_input_drops_alpha(encoding: str) -> None:
    image = np.array(BLUE_RED[encoding], dtype=np.uint8)
    alpha = [7] if encoding.endswith("a8") else []
    assert opencv_order(image, encoding).tolist() == [[[255, 0, 0, *alpha], [0, 0, 255, *alpha]]]
    assert bgr8(image, encoding).tolist() == [[[255, 0, 0], [0, 0, 255]]]


def test_a_bgra8_opencv_image_becomes_a_bgra8_frame_a_handler_reads_as_h_w_4() -> None:
    image = np.zeros((5, 6, 4), np.uint8)
    image[..., 3] = 255
    metadata = frame_metadata(1, Exposure(10, 5), image, None)
    meta = read_frame_metadata(metadata)
    assert meta.encoding == "bgra8"
    decoded = decode_image(image.tobytes(), meta)
    assert decoded.shape == (5, 6, 4) and np.array_equal(decoded, image)


def test_a_uint16_opencv_image_becomes_a_mono16_frame_a_handler_reads_as_uint16() -> None:
    image = (np.arange(30, dtype=np.uint16) * 2000).reshape(5, 6)
    meta = read_frame_metadata(frame_metadata(1, Exposure(10, 5), image, None))
    assert meta.encoding == "mono16"
    decoded = decode_image(image.astype("<u2").tobytes(), meta)
    assert decoded.dtype == np.uint16 and decoded.shape == (5, 6)
    assert np.array_equal(decoded, image)
