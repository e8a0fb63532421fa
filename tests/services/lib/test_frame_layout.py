"""A frame's layout: the bytes each encoding's payload holds, and the XSD that agrees."""

from __future__ import annotations

import re

import pytest

from middleware import validate_metadata
from schemas import SCHEMA_DIR
from services.lib.frame_layout import (
    FRAME_CHANNELS,
    FRAME_SAMPLE_BYTES,
    FrameError,
    FrameLayout,
    read_frame_layout,
)
from services.lib.messages import frame_metadata_of, read_frame_metadata
from services.lib.quality import Exposure


@pytest.mark.parametrize(
    ("encoding", "channels", "bytes_per_pixel"),
    [("mono8", 1, 1), ("mono16", 1, 2), ("bgr8", 3, 3), ("rgb8", 3, 3), ("bgra8", 4, 4),
     ("rgba8", 4, 4)],
)  # fmt: skip
def test_each_encoding_lays_out_its_bytes_per_pixel(
    encoding: str, channels: int, bytes_per_pixel: int
) -> None:
    layout = FrameLayout.checked(encoding, 6, 5)
    assert (layout.channels, layout.bytes_per_pixel) == (channels, bytes_per_pixel)
    assert (layout.step_bytes, layout.size_bytes) == (6 * bytes_per_pixel, 30 * bytes_per_pixel)
    layout.check_payload(30 * bytes_per_pixel)
    with pytest.raises(FrameError, match=f"6x5 {encoding} = {30 * bytes_per_pixel}"):
        layout.check_payload(30 * channels + 1)


def test_every_encoding_has_its_channels_and_their_bytes() -> None:
    assert set(FRAME_SAMPLE_BYTES) == set(FRAME_CHANNELS)


def test_frame_xsd_allows_exactly_the_encodings_frame_layout_knows() -> None:
    text = (SCHEMA_DIR / "frame.xsd").read_text()
    assert set(re.findall(r'<xs:enumeration value="([^"]+)"/>', text)) == set(FRAME_CHANNELS)


@pytest.mark.parametrize(
    ("encoding", "bytes_per_pixel"), [("bgra8", 4), ("rgba8", 4), ("mono16", 2)]
)
def test_new_encodings_pass_the_schema_and_read_back(encoding: str, bytes_per_pixel: int) -> None:
    metadata = frame_metadata_of(3, Exposure(10, 5), encoding, 8, 4, None)
    validate_metadata(metadata, "frame")
    assert read_frame_metadata(metadata).encoding == encoding
    assert read_frame_layout(metadata, 8 * 4 * bytes_per_pixel) == FrameLayout(encoding, 8, 4)
    with pytest.raises(FrameError, match="payload is 32 bytes"):
        read_frame_layout(metadata, 8 * 4)


@pytest.mark.parametrize("encoding", ["yuv422", "bayer_rggb8", "argb8", "16UC1", "mono12"])
def test_encodings_framegate_has_no_layout_for_are_refused(encoding: str) -> None:
    with pytest.raises(FrameError, match=f"encoding '{encoding}'") as refused:
        FrameLayout.checked(encoding, 8, 4)
    assert refused.value.reason == "bad-encoding"
