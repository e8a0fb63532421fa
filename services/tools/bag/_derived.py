"""Foxglove channels derived from buffers: what a viewer draws and plots (format 1).

Besides the lossless ``/service/buffer`` channel, a buffer of a known kind gets derived
channels under its topic. ``framegate record`` writes them into the MCAP file and
``framegate view`` streams the same topics live, so one Foxglove layout serves both:

======================  ====================================  ==============================
kind                    topic                                 message
======================  ====================================  ==============================
``frame`` (raw)         ``/service/buffer/image``             ``foxglove.RawImage`` (live:
                                                              or ``CompressedImage``, JPEG)
``decision``            ``/service/buffer/annotations``       ``foxglove.ImageAnnotations``:
                                                              a green (accepted) or red
                                                              border and "q, blur, load"
                                                              text on the decided frame
``decision``            ``/service/buffer/verdict``           JSON ``{q, load, blur_px,
                                                              accepted, ...}`` for Plot
``detections``          ``/service/buffer/annotations``       ``foxglove.ImageAnnotations``:
                                                              each marker's outline and id
``gyro``                ``/service/buffer/rates``             JSON per sample ``{x_rad_s,
                                                              y_rad_s, z_rad_s, norm_rad_s}``
any (live only)         ``/service/buffer/metadata``          JSON of the metadata fields
======================  ====================================  ==============================

Annotations carry the timestamp of the frame they belong to (a decision's
``frame_timestamp_ns``, a detection's key), which is how Foxglove's Image panel pairs them
with the image; their log time is that timestamp too. Everything here is pure: metadata and
payload in, encoded messages out, no I/O.

NumPy, the Foxglove SDK and the message records are imported on first use, not with this
module: ``record`` writes through it and must not wait for them before it starts recording.
"""

from __future__ import annotations

import json
import math
from collections.abc import Container
from dataclasses import dataclass
from functools import cache
from typing import TYPE_CHECKING, Any

from middleware import DataObject, FramegateError, parse_untrusted, validate_metadata

if TYPE_CHECKING:
    from foxglove.messages import (
        Color,
        CompressedImage,
        ImageAnnotations,
        RawImage,
        Timestamp,
    )

    from services.lib.messages import DecisionRecord

from services.lib.frame_layout import FrameLayout, frame_layout

from ._format import BagError, image_topic

PROTOBUF = "protobuf"
JSON = "json"

# Colours as (r, g, b, a), made into Foxglove colours when drawn.
GREEN = (0.1, 0.85, 0.2, 1.0)
RED = (0.95, 0.15, 0.1, 1.0)
MARKER = (1.0, 0.8, 0.0, 1.0)
SHADE = (0.0, 0.0, 0.0, 0.6)
BORDER_PX = 8.0
FONT_PX = 28.0
_NS = "{urn:framegate:1}"


@dataclass(frozen=True, slots=True)
class DerivedTopic:
    """One derived channel: its topic and how its messages are encoded."""

    topic: str
    schema_name: str | None  # None: schemaless JSON
    message_encoding: str
    role: str

    @property
    def schema_data(self) -> bytes:
        """The schema's bytes (a protobuf FileDescriptorSet), empty for schemaless JSON."""
        return _schemas()[self.schema_name].data if self.schema_name else b""

    @property
    def schema_encoding(self) -> str:
        return _schemas()[self.schema_name].encoding if self.schema_name else ""


@dataclass(frozen=True, slots=True)
class DerivedMessage:
    """One message on a derived channel, ready for an MCAP writer or a live server."""

    topic: str
    log_time_ns: int
    data: bytes


@dataclass(frozen=True, slots=True)
class Marker:
    """One detected marker: its id and its four corners (x, y in pixels, OpenCV's order)."""

    marker_id: int
    corners_px: tuple[tuple[float, float], ...]


@cache
def _schemas() -> dict[str, Any]:
    """The Foxglove schemas by name."""
    from foxglove.messages import CompressedImage, ImageAnnotations, RawImage

    return {
        m.get_schema().name: m.get_schema()
        for m in (RawImage, CompressedImage, ImageAnnotations)  # type: ignore[attr-defined]
    }


def _colour(rgba: tuple[float, float, float, float]) -> Color:
    from foxglove.messages import Color

    r, g, b, a = rgba
    return Color(r=r, g=g, b=b, a=a)


def annotations_topic(service: str, buffer: str) -> str:
    return f"/{service}/{buffer}/annotations"


def verdict_topic(service: str, buffer: str) -> str:
    return f"/{service}/{buffer}/verdict"


def rates_topic(service: str, buffer: str) -> str:
    return f"/{service}/{buffer}/rates"


def metadata_topic(service: str, buffer: str) -> str:
    return f"/{service}/{buffer}/metadata"


def derived_topics(
    service: str, buffer: str, kind: str, *, images: str | None = None, metadata: bool = False
) -> tuple[DerivedTopic, ...]:
    """The derived channels of a buffer of ``kind``.

    ``images``: ``"raw"`` or ``"jpeg"`` adds the frame image channel (the recorder writes its
    own JSON RawImage channel, so it passes None); ``metadata`` adds the metadata JSON channel.
    """
    out: list[DerivedTopic] = []
    if kind == "frame" and images is not None:
        name = "foxglove.CompressedImage" if images == "jpeg" else "foxglove.RawImage"
        out.append(DerivedTopic(image_topic(service, buffer), name, PROTOBUF, "image"))
    if kind in ("decision", "detections"):
        out.append(
            DerivedTopic(
                annotations_topic(service, buffer),
                "foxglove.ImageAnnotations",
                PROTOBUF,
                "annotations",
            )
        )
    if kind == "decision":
        out.append(DerivedTopic(verdict_topic(service, buffer), None, JSON, "verdict"))
    if kind == "gyro":
        out.append(DerivedTopic(rates_topic(service, buffer), None, JSON, "rates"))
    if metadata:
        out.append(DerivedTopic(metadata_topic(service, buffer), None, JSON, "metadata"))
    return tuple(out)


def _stamp(timestamp_ns: int) -> Timestamp:
    from foxglove.messages import Timestamp

    sec, nsec = divmod(timestamp_ns, 1_000_000_000)
    return Timestamp(sec, nsec)


def _json(body: Any) -> bytes:
    return json.dumps(body, separators=(",", ":"), allow_nan=False).encode("utf-8")


def _finite(value: float | None) -> float | None:
    return value if value is not None and math.isfinite(value) else None


def verdict_json(record: DecisionRecord) -> dict[str, Any]:
    """What Plot and Raw Messages show of one decision."""
    return {
        "frame_timestamp_ns": record.frame_timestamp_ns,
        "frame_id": record.frame_id,
        "q": _finite(record.quality),
        "load": record.load,
        "blur_px": _finite(record.blur_px),
        "accepted": record.accepted,
        "reason": record.reason,
        "policy": record.policy,
    }


def verdict_text(record: DecisionRecord) -> str:
    q = "-" if _finite(record.quality) is None else f"{record.quality:.2f}"
    blur = "-" if _finite(record.blur_px) is None else f"{record.blur_px:.1f} px"
    word = "ACCEPT" if record.accepted else "REJECT"
    return f"{word}  q {q}  blur {blur}  load {record.load:.2f}"


def verdict_annotations(
    record: DecisionRecord, size_px: tuple[int, int] | None
) -> ImageAnnotations:
    """A green (accepted) or red (rejected) border with the verdict's numbers as text.

    ``size_px`` (width, height) of the decided frame; without it only the text is drawn.
    """
    from foxglove.messages import (
        ImageAnnotations,
        Point2,
        PointsAnnotation,
        PointsAnnotationType,
        TextAnnotation,
    )

    stamp = _stamp(record.frame_timestamp_ns)
    colour = _colour(GREEN if record.accepted else RED)
    points = []
    if size_px is not None:
        w, h, inset = float(size_px[0]), float(size_px[1]), BORDER_PX / 2
        corners = [(inset, inset), (w - inset, inset), (w - inset, h - inset), (inset, h - inset)]
        points.append(
            PointsAnnotation(
                timestamp=stamp,
                type=PointsAnnotationType.LineLoop,
                points=[Point2(x=x, y=y) for x, y in corners],
                outline_color=colour,
                thickness=BORDER_PX,
            )
        )
    text = TextAnnotation(
        timestamp=stamp,
        position=Point2(x=2 * BORDER_PX, y=2 * BORDER_PX + FONT_PX),
        text=verdict_text(record),
        font_size=FONT_PX,
        text_color=colour,
        background_color=_colour(SHADE),
    )
    return ImageAnnotations(timestamp=stamp, points=points, texts=[text])


def read_markers(metadata: bytes) -> list[Marker]:
    """The markers of ``detections`` metadata (validated against its schema)."""
    root = validate_metadata(metadata, "detections")
    markers = []
    for node in root.iter(f"{_NS}marker"):
        values = [float(v) for v in (node.findtext(f"{_NS}corners_px") or "").split()]
        corners = tuple((values[i], values[i + 1]) for i in range(0, len(values) - 1, 2))
        markers.append(Marker(int(node.findtext(f"{_NS}id") or 0), corners))
    return markers


def detection_annotations(timestamp_ns: int, markers: list[Marker]) -> ImageAnnotations:
    """Each marker's outline and its id, on the frame with key ``timestamp_ns``."""
    from foxglove.messages import (
        ImageAnnotations,
        Point2,
        PointsAnnotation,
        PointsAnnotationType,
        TextAnnotation,
    )

    stamp = _stamp(timestamp_ns)
    marker_colour, shade = _colour(MARKER), _colour(SHADE)
    outlines, labels = [], []
    for marker in markers:
        outlines.append(
            PointsAnnotation(
                timestamp=stamp,
                type=PointsAnnotationType.LineLoop,
                points=[Point2(x=x, y=y) for x, y in marker.corners_px],
                outline_color=marker_colour,
                thickness=4.0,
            )
        )
        x, y = marker.corners_px[0] if marker.corners_px else (0.0, 0.0)
        labels.append(
            TextAnnotation(
                timestamp=stamp,
                position=Point2(x=x, y=y - 6.0),
                text=f"id {marker.marker_id}",
                font_size=FONT_PX,
                text_color=marker_colour,
                background_color=shade,
            )
        )
    return ImageAnnotations(timestamp=stamp, points=outlines, texts=labels)


def gyro_rates(payload: bytes) -> list[tuple[int, dict[str, float]]]:
    """(sample time, rates) of each sample in a gyro batch's payload; SchemaError if garbled."""
    import numpy as np

    from services.lib.quality import GyroSamples

    samples = GyroSamples.from_bytes(payload)
    norms = np.linalg.norm(samples.rates_rad_s, axis=1) if len(samples) else np.empty(0)
    return [
        (t, {"x_rad_s": x, "y_rad_s": y, "z_rad_s": z, "norm_rad_s": n})
        for t, (x, y, z), n in zip(
            samples.t_ns.tolist(), samples.rates_rad_s.tolist(), norms.tolist(), strict=True
        )
    ]


def _value(text: str) -> Any:
    """A field's text as JSON: integer, finite float, boolean, list of numbers, or string."""
    for convert in (int, float):
        try:
            value = convert(text)
        except ValueError:
            continue
        return value if not isinstance(value, float) or math.isfinite(value) else text
    words = text.split()
    if len(words) > 1:
        values = [_value(w) for w in words]
        if all(isinstance(v, int | float) for v in values):
            return values
    return {"true": True, "false": False}.get(text, text)


def _element_json(node: Any) -> Any:
    children = [c for c in node if isinstance(c.tag, str)]
    if not children:
        return _value((node.text or "").strip())
    grouped: dict[str, list[Any]] = {}
    for child in children:
        grouped.setdefault(child.tag.rpartition("}")[2], []).append(_element_json(child))
    # A repeated field (a detection's markers) becomes a list.
    return {name: values if len(values) > 1 else values[0] for name, values in grouped.items()}


def metadata_json(metadata: bytes) -> dict[str, Any]:
    """The metadata document as JSON: attributes, then fields (numbers parsed)."""
    root = parse_untrusted(metadata)
    body = _element_json(root)
    head = {"kind": root.get("kind"), "timestamp_ns": _value(root.get("timestamp_ns") or "")}
    return head | (body if isinstance(body, dict) else {})


def raw_image(element: DataObject, layout: FrameLayout, frame_id: str) -> RawImage:
    from foxglove.messages import RawImage

    return RawImage(
        timestamp=_stamp(element.timestamp_ns),
        frame_id=frame_id,
        width=layout.width_px,
        height=layout.height_px,
        encoding=layout.encoding,
        step=layout.step_bytes,
        data=element.payload,
    )


def jpeg_image(
    element: DataObject, layout: FrameLayout, frame_id: str, quality: int
) -> CompressedImage:
    import cv2  # only --jpeg needs OpenCV
    from foxglove.messages import CompressedImage

    from services.lib.frame_pixels import bgr8, frame_array

    # OpenCV writes gray or BGR, and a JPEG has no alpha: an rgb8 frame is swapped first,
    # a bgra8 or rgba8 frame loses its alpha.
    bgr = bgr8(frame_array(element.payload, layout), layout.encoding)
    ok, encoded = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise BagError(f"frame {element.timestamp_ns}: OpenCV could not encode it as JPEG")
    return CompressedImage(
        timestamp=_stamp(element.timestamp_ns),
        frame_id=frame_id,
        data=encoded.tobytes(),
        format="jpeg",
    )


@dataclass
class Deriver:
    """Turns elements of one buffer into derived messages; remembers the last frame size.

    ``wanted`` limits the work to topics someone listens to (a live viewer with no client
    on a topic skips building its messages); None builds all.
    """

    service: str
    buffer: str
    kind: str
    images: str | None = None
    metadata: bool = False
    jpeg_quality: int = 80

    def __post_init__(self) -> None:
        self.topics = derived_topics(
            self.service, self.buffer, self.kind, images=self.images, metadata=self.metadata
        )

    def derive(
        self,
        element: DataObject,
        *,
        frame_size_px: tuple[int, int] | None = None,
        wanted: Container[str] | None = None,
    ) -> list[DerivedMessage]:
        """The derived messages of one element; malformed metadata yields none."""
        out: list[DerivedMessage] = []
        for topic in self.topics:
            if wanted is not None and topic.topic not in wanted:
                continue
            try:
                out.extend(self._one(topic, element, frame_size_px))
            except (FramegateError, ValueError):
                continue  # a malformed element gets no drawing; the lossless channel keeps it
        return out

    def _one(
        self, topic: DerivedTopic, element: DataObject, size_px: tuple[int, int] | None
    ) -> list[DerivedMessage]:
        t = element.timestamp_ns
        if topic.role == "image":
            layout = frame_layout(element.metadata, len(element.payload))
            if layout is None:
                return []
            if self.images == "jpeg":
                jpeg = jpeg_image(element, layout, self.service, self.jpeg_quality)
                return [DerivedMessage(topic.topic, t, jpeg.encode())]
            return [
                DerivedMessage(topic.topic, t, raw_image(element, layout, self.service).encode())
            ]
        from services.lib.messages import DecisionRecord

        if topic.role == "annotations" and self.kind == "decision":
            record = DecisionRecord.from_metadata(element.metadata)
            drawn = verdict_annotations(record, size_px)
            return [DerivedMessage(topic.topic, record.frame_timestamp_ns, drawn.encode())]
        if topic.role == "annotations":
            drawn = detection_annotations(t, read_markers(element.metadata))
            return [DerivedMessage(topic.topic, t, drawn.encode())]
        if topic.role == "verdict":
            record = DecisionRecord.from_metadata(element.metadata)
            return [DerivedMessage(topic.topic, t, _json(verdict_json(record)))]
        if topic.role == "rates":
            return [
                DerivedMessage(topic.topic, ts, _json({"timestamp_ns": ts} | rates))
                for ts, rates in gyro_rates(element.payload)
            ]
        return [DerivedMessage(topic.topic, t, _json(metadata_json(element.metadata)))]
