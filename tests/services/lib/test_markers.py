"""The ArUco detector reads markers in every encoding a frame can have."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.lib.markers import DICTIONARY_ID, detect_markers


def marker_gray(marker_id: int = 1) -> np.ndarray:
    """A marker, 120 px a side, on a white margin of 40 px: 200 x 200 mono8."""
    dictionary = cv2.aruco.getPredefinedDictionary(DICTIONARY_ID)
    marker = cv2.aruco.generateImageMarker(dictionary, marker_id, 120)
    return np.pad(marker, 40, constant_values=255)


def in_encoding(gray: np.ndarray, encoding: str) -> np.ndarray:
    """The gray image as a frame of ``encoding``: dark cells dark blue, light cells pale
    yellow (so the channels differ), alpha 0 (an alpha that means nothing to brightness)."""
    light = gray > 127
    red = np.where(light, 250, 10).astype(np.uint8)
    green = np.where(light, 240, 10).astype(np.uint8)
    blue = np.where(light, 150, 90).astype(np.uint8)
    channels = {"bgr8": (blue, green, red), "rgb8": (red, green, blue)}
    channels["bgra8"] = (*channels["bgr8"], np.zeros_like(gray))
    channels["rgba8"] = (*channels["rgb8"], np.zeros_like(gray))
    return np.dstack(channels[encoding])


@pytest.mark.parametrize("encoding", ["bgr8", "rgb8", "bgra8", "rgba8"])
def test_a_marker_is_found_in_a_colour_frame_of_each_encoding(encoding: str) -> None:
    image = in_encoding(marker_gray(1), encoding)
    [found] = detect_markers(image, encoding)
    assert found.marker_id == 1 and found.size_px == pytest.approx(120, abs=2)


def test_a_four_channel_image_without_an_encoding_is_read_as_bgra() -> None:
    [found] = detect_markers(in_encoding(marker_gray(2), "bgra8"))
    assert found.marker_id == 2


@pytest.mark.parametrize("bits", [10, 12, 16])
def test_a_marker_is_found_in_a_mono16_frame_whatever_bits_its_sensor_fills(bits: int) -> None:
    """A 10- or 12-bit sensor published as mono16 fills only the low bits: ``>> 8`` would
    leave its image 4 or 16 gray levels (the 10-bit marker is then lost); scaled by the
    brightest pixel it reads as 8 bits."""
    gray = marker_gray(1).astype(np.uint16)
    top = 2**bits - 1
    image = np.where(gray > 127, top * 9 // 10, top // 20).astype(np.uint16)
    image[0, 0] = top  # one pixel at full scale
    if bits == 10:
        assert detect_markers((image >> 8).astype(np.uint8), "mono8") == []  # why not >> 8
    [found] = detect_markers(image, "mono16")
    assert found.marker_id == 1
    [found] = detect_markers(image)  # a uint16 array is mono16
    assert found.marker_id == 1


def test_a_mono8_frame_is_read_as_it_is() -> None:
    [found] = detect_markers(marker_gray(0), "mono8")
    assert (found.marker_id, found.name) == (0, "large")
