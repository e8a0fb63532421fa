"""How framegate lays buffers out in an MCAP file (format version 1).

For each recorded buffer ``service/buffer``:

* channel ``/service/buffer``: the lossless record. Message encoding ``msgpack``; schema
  ``framegate.Element`` (schema encoding ``x-framegate``; its data is this description in
  words). Each message is a msgpack map ``{"t": timestamp_ns (int), "p": payload (bin),
  "m": metadata XML (bin)}``: byte for byte what the buffer held. Channel metadata:
  ``framegate.format`` ("1"), ``framegate.service``, ``framegate.buffer``,
  ``framegate.kind`` and ``framegate.retention`` (JSON of ``middleware.Retention``), which
  is what ``play`` needs to offer the buffer again.
* for kind ``frame`` with a raw encoding (mono8, mono16, bgr8, rgb8, bgra8, rgba8): channel
  ``/service/buffer/image``, message encoding ``json``, schema ``foxglove.RawImage``
  (``jsonschema``), so Foxglove's Image panel shows the frames (RawImage takes these
  encoding names as they are, mono16 little-endian as framegate stores it, and ``step`` =
  width x bytes per pixel). It is derived data
  (``framegate.role`` = ``image``); ``play`` ignores it.
* for kinds ``decision``, ``detections`` and ``gyro``: the derived Foxglove channels of
  ``_derived`` (``/service/buffer/annotations``, ``/verdict``, ``/rates``), with
  ``framegate.role`` naming what they are; ``play`` ignores them too.

Every message has log_time = publish_time = the element's ``timestamp_ns``.
"""

from __future__ import annotations

import base64
import json
from dataclasses import asdict
from typing import Any

import msgpack

from middleware import DataObject, FramegateError, Retention
from services.lib.frame_layout import FrameLayout

FORMAT_VERSION = "1"
PROFILE = ""  # no MCAP profile fits (ros1/ros2 do not); the empty profile is the spec's default

ELEMENT_SCHEMA_NAME = "framegate.Element"
ELEMENT_SCHEMA_ENCODING = "x-framegate"
ELEMENT_MESSAGE_ENCODING = "msgpack"
ELEMENT_SCHEMA_TEXT = (
    "framegate buffer element, format 1. Message: msgpack map "
    '{"t": timestamp_ns (int, ns since the Unix epoch), "p": payload (bin), '
    '"m": metadata XML in namespace urn:framegate:1 (bin)}. '
    "Channel metadata: framegate.service, framegate.buffer, framegate.kind, "
    "framegate.retention (JSON), framegate.format."
)

IMAGE_SCHEMA_NAME = "foxglove.RawImage"
IMAGE_SCHEMA_ENCODING = "jsonschema"
IMAGE_MESSAGE_ENCODING = "json"
IMAGE_SCHEMA: dict[str, Any] = {
    "title": "foxglove.RawImage",
    "description": "A raw image",
    "type": "object",
    "properties": {
        "timestamp": {
            "type": "object",
            "title": "time",
            "properties": {
                "sec": {"type": "integer", "minimum": 0},
                "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999},
            },
        },
        "frame_id": {"type": "string"},
        "width": {"type": "integer", "minimum": 0},
        "height": {"type": "integer", "minimum": 0},
        "encoding": {"type": "string"},
        "step": {"type": "integer", "minimum": 0},
        "data": {"type": "string", "contentEncoding": "base64"},
    },
}

# Channel metadata keys.
KEY_FORMAT = "framegate.format"
KEY_SERVICE = "framegate.service"
KEY_BUFFER = "framegate.buffer"
KEY_KIND = "framegate.kind"
KEY_RETENTION = "framegate.retention"
KEY_ROLE = "framegate.role"
KEY_SOURCE = "framegate.source"


class BagError(FramegateError):
    """An MCAP file cannot be written or read as a framegate recording."""


def element_topic(service: str, buffer: str) -> str:
    return f"/{service}/{buffer}"


def image_topic(service: str, buffer: str) -> str:
    return f"/{service}/{buffer}/image"


def channel_metadata(service: str, buffer: str, kind: str, retention: Retention) -> dict[str, str]:
    return {
        KEY_FORMAT: FORMAT_VERSION,
        KEY_SERVICE: service,
        KEY_BUFFER: buffer,
        KEY_KIND: kind,
        KEY_RETENTION: json.dumps(asdict(retention), sort_keys=True),
    }


def retention_from_json(text: str, where: str) -> Retention:
    try:
        return Retention(**json.loads(text))
    except (ValueError, TypeError) as exc:
        raise BagError(f"{where}: bad {KEY_RETENTION} {text!r}: {exc}") from exc


def encode_element(element: DataObject) -> bytes:
    body = {"t": element.timestamp_ns, "p": element.payload, "m": element.metadata}
    return bytes(msgpack.packb(body, use_bin_type=True))


def decode_element(data: bytes, where: str) -> DataObject:
    """The element a ``framegate.Element`` message holds; BagError if it is not one."""
    try:
        body = msgpack.unpackb(data, raw=False)
        timestamp, payload, metadata = body["t"], body["p"], body["m"]
    except (ValueError, KeyError, TypeError, msgpack.UnpackException) as exc:
        raise BagError(f"{where}: message is not a framegate element: {exc}") from exc
    if not isinstance(timestamp, int) or not isinstance(payload, bytes):
        raise BagError(f"{where}: message is not a framegate element (bad t or p)")
    if not isinstance(metadata, bytes):
        raise BagError(f"{where}: message is not a framegate element (bad m)")
    return DataObject(timestamp, payload, metadata)


def encode_raw_image(element: DataObject, layout: FrameLayout, frame_id: str) -> bytes:
    """A ``foxglove.RawImage`` JSON message showing a raw frame."""
    sec, nsec = divmod(element.timestamp_ns, 1_000_000_000)
    body = {
        "timestamp": {"sec": sec, "nsec": nsec},
        "frame_id": frame_id,
        "width": layout.width_px,
        "height": layout.height_px,
        "encoding": layout.encoding,
        "step": layout.step_bytes,
        "data": base64.b64encode(element.payload).decode("ascii"),
    }
    return json.dumps(body, separators=(",", ":")).encode("utf-8")
