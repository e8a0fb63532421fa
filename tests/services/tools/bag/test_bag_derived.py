"""The derived Foxglove channels: pure builders, no sockets, no files."""

from __future__ import annotations

import json
from typing import Any

import cv2
import numpy as np
from foxglove.messages import PointsAnnotationType
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from middleware import DataObject
from services.lib.frame_layout import FrameLayout
from services.lib.messages import DecisionRecord, detections_metadata, frame_metadata, gyro_metadata
from services.lib.quality import Exposure, GyroSamples
from services.tools.bag import (
    Deriver,
    derived_topics,
    metadata_json,
    read_markers,
    verdict_annotations,
)
from services.tools.bag._derived import jpeg_image

T = 1_700_000_000_123_456_789


def _decision(accepted: bool, quality: float | None = 0.8) -> DecisionRecord:
    return DecisionRecord(T, 5, 1.2, quality, 0.5, accepted, "quality", "paper", 5.0, 1000)


def test_each_kind_gets_its_derived_topics() -> None:
    def topics(kind: str, **kw: object) -> list[str]:
        return [t.topic for t in derived_topics("s", "b", kind, **kw)]  # type: ignore[arg-type]

    assert topics("decision") == ["/s/b/annotations", "/s/b/verdict"]
    assert topics("detections") == ["/s/b/annotations"]
    assert topics("gyro") == ["/s/b/rates"]
    assert topics("frame") == []  # the recorder writes its own image channel
    assert topics("frame", images="raw", metadata=True) == ["/s/b/image", "/s/b/metadata"]
    assert derived_topics("s", "b", "frame", images="jpeg")[0].schema_name == (
        "foxglove.CompressedImage"
    )
    assert topics("generic") == []


def _decoded(message: Any) -> Any:
    """A foxglove-sdk message read back through its own advertised protobuf schema."""
    schema = type(message).get_schema()
    pool = descriptor_pool.DescriptorPool()
    for proto in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
        pool.Add(proto)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
    return cls.FromString(message.encode())


def test_verdict_is_a_coloured_border_on_the_decided_frame_with_its_numbers() -> None:
    accepted = _decoded(verdict_annotations(_decision(True), (640, 480)))
    rejected = _decoded(verdict_annotations(_decision(False), (640, 480)))
    (border,) = accepted.points
    assert border.type == PointsAnnotationType.LineLoop.value
    assert [(p.x, p.y) for p in border.points] == [(4, 4), (636, 4), (636, 476), (4, 476)]
    green, red = accepted.texts[0].text_color, rejected.texts[0].text_color
    assert border.outline_color == green and rejected.points[0].outline_color == red
    assert green.g > 0.5 > green.r and red.r > 0.5 > red.g
    assert accepted.timestamp.seconds * 10**9 + accepted.timestamp.nanos == T
    assert accepted.texts[0].text == "ACCEPT  q 0.80  blur 1.2 px  load 0.50"
    assert rejected.texts[0].text.startswith("REJECT")


def test_verdict_messages_are_stamped_with_the_frame_and_the_plot_with_the_decision() -> None:
    annotations, plot = Deriver("m", "decisions", "decision").derive(
        DataObject(T + 7, b"", _decision(True).metadata(T + 7)), frame_size_px=(640, 480)
    )
    assert annotations.topic == "/m/decisions/annotations" and annotations.log_time_ns == T
    assert plot.topic == "/m/decisions/verdict" and plot.log_time_ns == T + 7
    assert json.loads(plot.data) | {"reason": "-"} == {
        "frame_timestamp_ns": T, "frame_id": 5, "q": 0.8, "load": 0.5, "blur_px": 1.2,
        "accepted": True, "reason": "-", "policy": "paper",
    }  # fmt: skip


def test_without_a_known_frame_size_only_the_text_is_drawn() -> None:
    drawn = _decoded(verdict_annotations(_decision(True), None))
    assert list(drawn.points) == [] and drawn.texts[0].text.startswith("ACCEPT")


def test_a_decision_without_quality_says_so() -> None:
    drawn = _decoded(verdict_annotations(_decision(False, quality=None), None))
    assert drawn.texts[0].text.startswith("REJECT  q -  ")


def test_markers_are_read_with_their_corners() -> None:
    corners = [1.0, 2.0, 3.0, 2.0, 3.0, 4.0, 1.0, 4.0]
    md = detections_metadata(T, 3, "camera/images", 100, [(7, corners), (9, corners)])
    markers = read_markers(md)
    assert [m.marker_id for m in markers] == [7, 9]
    assert markers[0].corners_px == ((1.0, 2.0), (3.0, 2.0), (3.0, 4.0), (1.0, 4.0))
    (drawn,) = Deriver("d", "detections", "detections").derive(DataObject(T, b"", md))
    assert drawn.log_time_ns == T and b"id 7" in drawn.data and b"id 9" in drawn.data


def test_gyro_batch_becomes_one_plot_point_per_sample() -> None:
    samples = GyroSamples(np.array([T - 1000, T]), np.array([[0.0, 3.0, 4.0], [1.0, 0.0, 0.0]]))
    data = DataObject(T, samples.to_bytes(), gyro_metadata(samples))
    points = Deriver("g", "rates", "gyro").derive(data)
    assert [p.log_time_ns for p in points] == [T - 1000, T]
    assert json.loads(points[0].data)["norm_rad_s"] == 5.0


def test_metadata_becomes_json_with_numbers_and_lists() -> None:
    md = detections_metadata(T, 3, "camera/images", 100, [(7, [1.5] * 8), (8, [2.0] * 8)])
    body = metadata_json(md)
    assert body["kind"] == "detections" and body["timestamp_ns"] == T
    assert body["frame_id"] == 3 and body["source"] == "camera/images"
    assert [m["id"] for m in body["marker"]] == [7, 8]
    assert body["marker"][0]["corners_px"] == [1.5] * 8


def test_malformed_metadata_yields_no_drawing_rather_than_an_error() -> None:
    assert Deriver("m", "decisions", "decision").derive(DataObject(T, b"", b"<oops")) == []


def _frame(encoding_channels: int) -> DataObject:
    shape = (6, 8) if encoding_channels == 1 else (6, 8, 3)
    image = np.arange(np.prod(shape), dtype=np.uint8).reshape(shape)
    return DataObject(T, image.tobytes(), frame_metadata(1, Exposure(T, 1000), image, None))


def test_only_wanted_topics_are_built() -> None:
    deriver = Deriver("c", "images", "frame", images="raw", metadata=True)
    frame = _frame(1)
    assert [m.topic for m in deriver.derive(frame, wanted={"/c/images/metadata"})] == [
        "/c/images/metadata"
    ]
    both = deriver.derive(frame)
    assert [m.topic for m in both] == ["/c/images/image", "/c/images/metadata"]
    assert frame.payload in both[0].data  # RawImage carries the pixels as they are


def test_jpeg_frames_decode_back_to_the_image_size() -> None:
    frame = _frame(3)
    jpeg = jpeg_image(frame, FrameLayout("bgr8", 8, 6), "camera", 90)
    start = jpeg.encode().index(b"\xff\xd8")
    decoded = cv2.imdecode(np.frombuffer(jpeg.encode()[start:], np.uint8), cv2.IMREAD_COLOR)
    assert decoded is not None and decoded.shape == (6, 8, 3)


def test_with_jpeg_the_image_channel_carries_a_compressed_image() -> None:
    deriver = Deriver("c", "images", "frame", images="jpeg", jpeg_quality=50)
    (image,) = deriver.derive(_frame(1), wanted={"/c/images/image"})
    assert image.topic == "/c/images/image" and b"\xff\xd8" in image.data and b"jpeg" in image.data
