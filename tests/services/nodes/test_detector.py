"""The detector service's handler: ArUco markers as boxes, in the frame's own encoding."""

from __future__ import annotations

import pytest

from services.lib.quality import Exposure
from services.lib.vision import FrameMeta
from services.nodes.detector import detect_aruco
from tests.services.lib.test_markers import in_encoding, marker_gray


@pytest.mark.parametrize("encoding", ["rgb8", "bgra8", "rgba8"])
def test_the_handler_reads_the_frame_in_the_encoding_its_metadata_names(encoding: str) -> None:
    frame = FrameMeta(0, 0, Exposure(0, 1), encoding, 200, 200, None)
    [box] = detect_aruco(in_encoding(marker_gray(2), encoding), frame)
    assert box.label == 2
