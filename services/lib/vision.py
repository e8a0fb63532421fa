"""What a vision handler receives and returns (``framegate run vision --handler ...``).

A handler is any callable ``handler(image, frame) -> result``:

- ``image``: the frame as a read-only NumPy ``uint8`` array, ``(height, width)`` for mono8,
  ``(height, width, 3)`` for bgr8/rgb8, ``(height, width, 4)`` for bgra8/rgba8, channels in
  the order the encoding names (``frame.encoding``); a ``uint16`` array ``(height, width)``
  for mono16 (copy it before changing it). :func:`gray8` ``(image, frame.encoding)`` makes
  one 8-bit channel of any of them, as the marker detector reads it (mono16 scaled so that
  the frame's brightest pixel is 255);
- ``frame``: a :class:`FrameMeta`, everything the frame's metadata carries (``timestamp_ns``
  = exposure start, ``frame_id``, ``exposure``, ``encoding``, ``width_px``, ``height_px``,
  ``camera``: the intrinsics and IMU rotation when the camera sent them).

It returns one of:

- a list (or tuple) of :class:`Box` — what it found, possibly nothing: stored in a
  ``detections`` buffer, one element per frame, keyed by the frame's timestamp, so a
  frame where nothing was found is told apart from one never processed;
- an :class:`Output` — anything else (a payload and free-form fields): stored in a
  ``generic`` buffer; plain ``bytes`` is an ``Output`` with no fields, a ``dict`` (any
  mapping of field names) an ``Output`` with no payload;
- ``None`` — no result for this frame (counted ``no-result``).

The buffer's kind is chosen once, at start: from the handler's return annotation
(``-> list[Box]`` / ``-> Output``, ``bytes`` or ``dict``) or ``--kind``; unannotated
handlers are taken to return boxes. :func:`encode_result` turns a result into the element's
metadata and payload, and raises :class:`~middleware.SchemaError` for a result that does not
fit the buffer.
"""

from __future__ import annotations

import enum
import math
import operator
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from middleware import SchemaError, XmlLimits, make_metadata
from services.lib.frame_pixels import gray8
from services.lib.messages import FrameMeta, detections_metadata

__all__ = ["Box", "FrameMeta", "Output", "ResultKind", "encode_result", "gray8", "plain_result"]

# The most boxes one frame's element holds (detections.xsd says the same).
MAX_BOXES = 1000


class ResultKind(enum.Enum):
    """The kind of buffer a handler's results go to."""

    DETECTIONS = "detections"
    GENERIC = "generic"


@dataclass(frozen=True, slots=True)
class Box:
    """One thing found in a frame: a label and four corners (a quadrilateral, in pixels).

    ``label`` is the class or marker id; ``corners_px`` are (x, y) pairs in the image, in the
    order the detector gives them (OpenCV: clockwise from top-left); ``score`` is the
    detector's confidence, if it has one. An axis-aligned box: :meth:`from_xywh`.
    """

    label: int
    corners_px: tuple[tuple[float, float], ...]
    score: float | None = None

    def __post_init__(self) -> None:
        # Any integer type (a detector's class ids are often NumPy or torch integers),
        # stored as int; not a bool.
        try:
            label = operator.index(self.label)
        except TypeError:
            label = -1
        if isinstance(self.label, bool) or label < 0:
            raise SchemaError(f"Box label must be an int >= 0, got {self.label!r}")
        object.__setattr__(self, "label", label)
        if len(self.corners_px) != 4 or any(len(c) != 2 for c in self.corners_px):
            raise SchemaError(f"Box needs 4 (x, y) corners, got {self.corners_px!r}")
        numbers = [float(v) for corner in self.corners_px for v in corner]
        if not all(math.isfinite(v) for v in numbers):
            raise SchemaError(f"Box corners must be finite, got {self.corners_px!r}")
        if self.score is not None and not math.isfinite(float(self.score)):
            raise SchemaError(f"Box score must be finite, got {self.score!r}")

    @classmethod
    def from_xywh(
        cls, label: int, x_px: float, y_px: float, width_px: float, height_px: float,
        score: float | None = None,
    ) -> Box:  # fmt: skip
        """An axis-aligned box from its top-left corner and size."""
        x0, y0, x1, y1 = float(x_px), float(y_px), float(x_px + width_px), float(y_px + height_px)
        return cls(label, ((x0, y0), (x1, y0), (x1, y1), (x0, y1)), score)


@dataclass(frozen=True, slots=True)
class Output:
    """A result that is not boxes: a payload and fields for a ``generic`` buffer.

    ``fields`` become child elements of the metadata, as ``make_metadata`` writes them
    (names must be XML names; dicts nest; lists are space-separated text, nested lists and
    NumPy arrays flattened; a NumPy scalar is its value; a field that is None is left
    out). Bytes, sets and objects with no text of their own are refused (``bad-result``).
    """

    payload: bytes = b""
    fields: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class Encoded:
    """A result as the element to put: its payload, metadata and how many boxes it holds."""

    payload: bytes
    metadata: bytes
    boxes: int


def encode_result(
    result: object,
    kind: ResultKind,
    frame: FrameMeta,
    source: str,
    processing_ns: int,
    taken_ns: int | None = None,
) -> Encoded | None:
    """The element a handler's ``result`` for ``frame`` becomes in a ``kind`` buffer; None
    for ``None`` (no result). SchemaError names what is wrong with any other result.
    ``taken_ns``: when the runner took the frame up (detections only): with the frames'
    arrivals, what the detector did when, which ``processing_ns`` alone cannot say."""
    if result is None:
        return None
    try:
        encoded = _encode(result, kind, frame, source, processing_ns, taken_ns)
    except SchemaError:
        raise
    except Exception as exc:  # the handler's own objects: any float() or str() of them may raise
        raise SchemaError(
            f"the result cannot be written as metadata: {type(exc).__name__} "
            "converting one of its values"
        ) from exc
    if len(encoded.metadata) > METADATA_MAX_BYTES:
        what = f"{len(encoded.metadata)} bytes"
        if kind is ResultKind.DETECTIONS:  # boxes have no payload to move to
            what += f" for {encoded.boxes} boxes (about 200 bytes each: return fewer)"
        raise SchemaError(_too_long(what))
    return encoded


def plain_result(result: object, kind: ResultKind) -> object:
    """``result`` with every value of the handler's own converted to a plain one (a float,
    an int, text), so that :func:`encode_result` runs none of the handler's code: called on
    the handler's thread, where a stop reaches it (a ``__float__`` or ``__str__`` that
    blocks or raises ``SystemExit`` ran on the runner's loop). SchemaError as there."""
    if result is None:
        return None
    try:
        if kind is ResultKind.DETECTIONS:
            return [
                Box(
                    box.label,
                    tuple((float(x), float(y)) for x, y in box.corners_px),
                    None if box.score is None else float(box.score),
                )
                for box in _boxes(result)
            ]
        if isinstance(result, Mapping):  # a dict of fields: an Output without a payload
            result = Output(b"", result)
        if isinstance(result, Output):
            payload = result.payload
            if isinstance(payload, bytes | bytearray | memoryview):
                payload = bytes(payload)
            return Output(payload, _fields(result.fields))
        return bytes(result) if isinstance(result, bytearray | memoryview) else result
    except SchemaError:
        raise
    except BaseException as exc:  # the handler's own objects: any float() or str() may raise
        raise SchemaError(
            f"the result cannot be written as metadata: {type(exc).__name__} "
            "converting one of its values"
        ) from exc


# What a result's metadata may hold: what every reader of it accepts (``validate_metadata``).
METADATA_MAX_BYTES = XmlLimits().max_bytes


def _too_long(what: str) -> str:
    return (
        f"the result's metadata would be {what}, over the limit of {METADATA_MAX_BYTES} "
        "bytes (large data goes in an Output's payload, not its fields)"
    )


class _Budget:
    """The least text a result's fields take, counted while they are read, so that a
    handler's field of 10^7 values is refused before it is turned into text (it cost the
    runner's thread half a gigabyte and a minute per frame, then failed the size limit)."""

    def __init__(self) -> None:
        self.left = METADATA_MAX_BYTES

    def spend(self, n: int) -> None:
        self.left -= n
        if self.left < 0:
            raise SchemaError(_too_long(f"more than {METADATA_MAX_BYTES} bytes"))


def _encode(
    result: object,
    kind: ResultKind,
    frame: FrameMeta,
    source: str,
    processing_ns: int,
    taken_ns: int | None,
) -> Encoded:
    if kind is ResultKind.DETECTIONS:
        boxes = _boxes(result)
        metadata = detections_metadata(
            frame.timestamp_ns,
            frame.frame_id,
            source,
            max(0, processing_ns),
            [(box.label, [float(v) for corner in box.corners_px for v in corner]) for box in boxes],
            scores=[None if box.score is None else float(box.score) for box in boxes],
            taken_ns=taken_ns,
        )
        return Encoded(b"", metadata, len(boxes))
    head: dict[str, Any] = {
        "frame_id": frame.frame_id,
        "source": source,
        "processing_ns": max(0, processing_ns),
    }
    if isinstance(result, bytes | bytearray | memoryview):
        result = Output(bytes(result))
    if isinstance(result, Mapping):
        result = Output(b"", result)
    if not isinstance(result, Output):
        raise SchemaError(
            f"a handler for a generic buffer returns Output, bytes, a dict or None, not "
            f"{type(result).__name__}"
        )
    if not isinstance(result.payload, bytes | bytearray | memoryview):
        raise SchemaError(f"Output.payload must be bytes, not {type(result.payload).__name__}")
    fields = _fields(result.fields)
    clash = sorted(set(fields) & set(head))
    if clash:
        raise SchemaError(f"Output fields {clash} are set by the runner; rename them")
    try:
        metadata = make_metadata("generic", frame.timestamp_ns, {**head, **fields})
    except (ValueError, TypeError) as exc:  # lxml refuses a bad element name or value
        raise SchemaError(f"Output fields cannot be written as XML: {exc}") from exc
    return Encoded(bytes(result.payload), metadata, 0)


def _fields(fields: object) -> dict[str, Any]:
    """``Output.fields`` as element names to values; SchemaError for anything else (a name
    starting with ``@`` would be an attribute of the metadata's root: its kind or stamp)."""
    if not isinstance(fields, Mapping):
        raise SchemaError(f"Output.fields must be a mapping of names, not {type(fields).__name__}")
    for name in fields:
        if not isinstance(name, str) or not name or name.startswith("@"):
            raise SchemaError(f"Output field names are XML element names, not {name!r:.40}")
    return _plain_fields(fields, "", _Budget())


def _plain_fields(fields: Mapping[str, Any], path: str, budget: _Budget) -> dict[str, Any]:
    """A mapping's fields as :func:`_plain` values; a field that is None has no element."""
    plain: dict[str, Any] = {}
    for name, value in fields.items():
        if value is not None:
            budget.spend(2 * len(str(name)) + 5)  # <name></name>
            plain[name] = _plain(value, f"{path}{name}", budget)
    return plain


def _plain(value: object, name: str, budget: _Budget) -> object:
    """``value`` as the metadata writes it: NumPy arrays and scalars as Python values (``str``
    of an array is its summary, ``[0 1 2 ... 1999]`` past 1,000 values), nested lists flat as
    an array's values are (``str`` of an inner list is ``[1, 2]``, not its values).
    SchemaError for what has no text of its own: bytes (their repr, ``b'\\x00'``), a set (in
    no fixed order), None inside a list ("None"), an object without ``__str__`` (``<Foo
    object at 0x7f...>``)."""
    if isinstance(value, np.ndarray):
        budget.spend(2 * value.size)  # a digit and a space each, at least
        return value.ravel().tolist()
    if isinstance(value, np.generic):
        budget.spend(1)
        return value.item()
    if isinstance(value, Mapping):
        return _plain_fields(value, f"{name}/", budget)
    if isinstance(value, list | tuple):
        flat: list[object] = []
        for item in value:
            plain = _plain(item, name, budget)
            flat.extend(plain if isinstance(plain, list) else [plain])
        return flat
    if value is None or isinstance(value, bytes | bytearray | memoryview | set | frozenset):
        what = "None in a list" if value is None else f"a value of type {type(value).__name__}"
        raise SchemaError(
            f"Output field {name!r} holds {what}: fields hold text, numbers and booleans, "
            "lists and dicts of them (bytes go in the payload; a field left out is None)"
        )
    if type(value).__str__ is object.__str__ and type(value).__repr__ is object.__repr__:
        raise SchemaError(
            f"Output field {name!r} holds a value of type {type(value).__name__}, which has no "
            "text of its own (give it a __str__, or store its values)"
        )
    budget.spend(len(value) if isinstance(value, str) else 2)
    if type(value) in (str, int, float, bool):
        return value
    # As the metadata writes it (``make_metadata``), now: its writing calls no code of ours.
    return repr(value) if isinstance(value, float) else str(value)


def _boxes(result: object) -> Sequence[Box]:
    if isinstance(result, Output | bytes | bytearray | str) or not isinstance(result, Sequence):
        raise SchemaError(
            f"a handler for a detections buffer returns a list of Box or None, not "
            f"{type(result).__name__} (annotate it '-> Output' or run with --kind generic)"
        )
    if len(result) > MAX_BOXES:
        raise SchemaError(f"{len(result)} boxes in one frame; at most {MAX_BOXES} are stored")
    for item in result:
        if not isinstance(item, Box):
            raise SchemaError(f"a detections result holds Box records, not {type(item).__name__}")
    return result
