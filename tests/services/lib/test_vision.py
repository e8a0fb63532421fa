"""What a handler returns becomes the element its buffer's kind says, or a clear error."""

from __future__ import annotations

import numpy as np
import pytest

from middleware import SchemaError, validate_metadata
from services.lib.messages import frame_metadata, read_detections, read_frame_metadata
from services.lib.quality import Exposure
from services.lib.vision import Box, Output, ResultKind, encode_result, gray8


class _Unprintable:
    def __str__(self) -> str:
        raise RuntimeError("no text")


class _Plain:
    """An object with neither __str__ nor __repr__: its text is "<_Plain object at 0x...>"."""


FRAME = read_frame_metadata(
    frame_metadata(7, Exposure(1_000_000, 30_000_000), np.zeros((4, 6), np.uint8), None)
)


def test_boxes_become_detections_with_their_labels_corners_and_scores() -> None:
    boxes = [Box.from_xywh(3, 1, 2, 10, 20, score=0.5), Box(1, ((0, 0), (1, 0), (1, 1), (0, 1)))]
    encoded = encode_result(boxes, ResultKind.DETECTIONS, FRAME, "mediator/images", 1234)
    assert encoded is not None and encoded.boxes == 2 and encoded.payload == b""
    assert read_detections(encoded.metadata) == (7, [3, 1])
    root = validate_metadata(encoded.metadata, "detections")
    assert root.get("timestamp_ns") == str(FRAME.timestamp_ns)
    assert b"<score>0.5</score>" in encoded.metadata
    assert b"<corners_px>1.0 2.0 11.0 2.0 11.0 22.0 1.0 22.0</corners_px>" in encoded.metadata


def test_no_boxes_is_an_element_and_none_is_no_element() -> None:
    empty = encode_result([], ResultKind.DETECTIONS, FRAME, "x/y", 0)
    assert empty is not None and read_detections(empty.metadata) == (7, [])
    assert encode_result(None, ResultKind.DETECTIONS, FRAME, "x/y", 0) is None


def test_an_output_becomes_a_generic_element_with_the_frame_fields() -> None:
    encoded = encode_result(Output(b"abc", {"mean": 1.5}), ResultKind.GENERIC, FRAME, "a/b", 5)
    assert encoded is not None and encoded.payload == b"abc"
    validate_metadata(encoded.metadata, "generic")
    assert b"<frame_id>7</frame_id>" in encoded.metadata and b"<mean>1.5</mean>" in encoded.metadata
    raw = encode_result(b"xyz", ResultKind.GENERIC, FRAME, "a/b", 5)
    assert raw is not None and raw.payload == b"xyz"


def test_numpy_values_in_output_fields_are_written_as_their_values() -> None:
    # str() of an array past 1,000 values is its summary, "[   0    1    2 ... 1999]": a
    # handler's vector was stored cut short, in brackets, and a NumPy bool as "True".
    fields = {
        "vector": np.arange(2000),
        "pose": np.eye(2, dtype=np.float32),
        "found": np.bool_(True),
        "score": np.float32(0.5),
        "nested": {"count": np.int64(3), "pair": (np.int16(1), np.float64(2.5))},
    }
    encoded = encode_result(Output(b"", fields), ResultKind.GENERIC, FRAME, "a/b", 5)
    assert encoded is not None
    root = validate_metadata(encoded.metadata, "generic")
    text = {e.tag.split("}")[1]: e.text for e in root.iter() if e.text}
    assert text["vector"] == " ".join(str(i) for i in range(2000))
    assert text["pose"] == "1.0 0.0 0.0 1.0"
    assert (text["found"], text["score"]) == ("true", "0.5")
    assert (text["count"], text["pair"]) == ("3", "1 2.5")


def test_nested_lists_are_flat_as_arrays_are_and_a_none_field_is_left_out() -> None:
    """A polygon as a list of pairs was written "[1, 2] [3, 4]" (each inner list's repr),
    the same as a NumPy array "1 2 3 4"; a None field was written "None"."""
    fields = {"poly": [[1, 2], (3, 4)], "pose": {"ok": None, "x": 1.5}, "track": None}
    encoded = encode_result(Output(b"", fields), ResultKind.GENERIC, FRAME, "a/b", 5)
    assert encoded is not None
    root = validate_metadata(encoded.metadata, "generic")
    text = {e.tag.split("}")[1]: e.text for e in root.iter()}
    assert text["poly"] == "1 2 3 4" and text["x"] == "1.5"
    assert "track" not in text and "ok" not in text


@pytest.mark.parametrize(
    ("result", "kind", "match"),
    [
        (Output(b""), ResultKind.DETECTIONS, "returns a list of Box or None, not Output"),
        ([1, 2], ResultKind.DETECTIONS, "holds Box records, not int"),
        ([Box(0, ((0, 0),) * 4)] * 1001, ResultKind.DETECTIONS, "at most 1000"),
        (
            [Box(0, ((0, 0),) * 4)],
            ResultKind.GENERIC,
            "returns Output, bytes, a dict or None, not list",
        ),
        (Output(b"", {"bad name": 1}), ResultKind.GENERIC, "cannot be written as XML"),
        (Output(b"", {"frame_id": 1}), ResultKind.GENERIC, "set by the runner"),
        (Output("text", {}), ResultKind.GENERIC, "payload must be bytes"),  # type: ignore[arg-type]
        # Any fields a handler makes up: a clear error each, never another exception.
        (Output(b"x", [1, 2]), ResultKind.GENERIC, "must be a mapping"),  # type: ignore[arg-type]
        (Output(b"x", None), ResultKind.GENERIC, "must be a mapping"),  # type: ignore[arg-type]
        (Output(b"x", {1: 2}), ResultKind.GENERIC, "XML element names, not 1"),  # type: ignore[dict-item]
        (Output(b"x", {"@kind": "evil"}), ResultKind.GENERIC, "not '@kind'"),
        (Output(b"x", {"v": _Unprintable()}), ResultKind.GENERIC, "RuntimeError converting"),
        # Values with no text of their own were stored as their repr: refused, named.
        (
            Output(b"x", {"raw": b"\x00\x01"}),
            ResultKind.GENERIC,
            "'raw' holds a value of type bytes",
        ),
        (Output(b"x", {"ids": {1, 2}}), ResultKind.GENERIC, "'ids' holds a value of type set"),
        (Output(b"x", {"d": {"v": [1, None]}}), ResultKind.GENERIC, "'d/v' holds None in a list"),
        (Output(b"x", {"o": _Plain()}), ResultKind.GENERIC, "type _Plain, which has no text"),
    ],
)
def test_a_result_that_does_not_fit_is_a_schema_error(
    result: object, kind: ResultKind, match: str
) -> None:
    with pytest.raises(SchemaError, match=match):
        encode_result(result, kind, FRAME, "a/b", 0)


@pytest.mark.parametrize(
    ("label", "corners", "score", "match"),
    [
        (-1, ((0, 0),) * 4, None, "label must be an int >= 0"),
        (True, ((0, 0),) * 4, None, "label must be an int >= 0"),
        (0, ((0, 0),) * 3, None, "4 \\(x, y\\) corners"),
        (0, ((0, float("nan")),) * 4, None, "finite"),
        (0, ((0, 0),) * 4, float("inf"), "score must be finite"),
    ],
)
def test_a_bad_box_is_refused_where_it_is_made(
    label: int, corners: tuple[tuple[float, float], ...], score: float | None, match: str
) -> None:
    with pytest.raises(SchemaError, match=match):
        Box(label, corners, score)


def test_a_handler_gets_gray_from_any_encoding_through_the_vision_module() -> None:
    rgba = np.array([[[255, 0, 0, 0]]], np.uint8)  # red, transparent
    assert gray8(rgba, "rgba8").tolist() == [[76]]
    assert gray8(rgba[..., :3], "rgb8").tolist() == [[76]]
