"""A frame's metadata carries everything the estimate needs."""

from __future__ import annotations

import pytest

from middleware import SchemaError, make_metadata
from services.lib.camera_model import CameraModel
from services.lib.quality import Exposure, estimate_blur
from tests.services.lib.quality.quality_synth import camera, constant


def _frame_xml(cam: CameraModel) -> bytes:
    return make_metadata(
        "frame",
        100_000_000,
        {
            "frame_id": 3,
            "exposure_start_ns": 100_000_000,
            "exposure_ns": 60_000_000,
            "encoding": "mono8",
            "width_px": cam.width_px,
            "height_px": cam.height_px,
            "camera": cam.camera_fields(),
        },
    )


def test_a_frames_metadata_loads_camera_and_exposure() -> None:
    cam = camera(
        line_readout_ns=26_000,
        gyro_time_offset_ns=-1_500_000,
        gyro_to_camera=(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0),
    )
    xml = _frame_xml(cam)
    assert CameraModel.from_xml(xml) == cam
    exposure = Exposure.from_xml(xml)
    assert exposure == Exposure(100_000_000, 60_000_000)
    assert exposure.end_ns == 160_000_000
    result = estimate_blur(constant((0.0, 1.0, 0.0)), exposure, CameraModel.from_xml(xml))
    assert result.blur_px > 0


def test_a_camera_document_is_not_a_frame() -> None:
    with pytest.raises(SchemaError, match="declares kind 'camera'"):
        Exposure.from_xml(camera().to_xml())


def test_a_negative_exposure_is_refused() -> None:
    with pytest.raises(ValueError, match="duration_ns must be >= 0"):
        Exposure(0, -1)
