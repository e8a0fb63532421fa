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
