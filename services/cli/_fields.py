"""Metadata decoded for people and for JSON: typed fields and a payload summary.

Fields are the leaf elements under the metadata root, nested ones as dotted names
(``camera.fx_px``), repeated ones as lists. Values get their JSON type back: XML holds
text, but ``frame_id`` is a number to whoever reads ``--json``.
"""

from __future__ import annotations

import math
import re
from typing import Any

from middleware import FramegateError, parse_untrusted

_INT = re.compile(r"[+-]?\d+")
_FLOAT = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?")
# Bytes of the payload shown in a summary.
HEAD_BYTES = 16

Value = int | float | bool | str | list[Any]


def typed(text: str) -> Value:
    """``"12"`` → 12, ``"0.5"`` → 0.5, ``"true"`` → True, ``"1 2 3"`` → [1, 2, 3]; else the text.

    Non-finite numbers stay text (JSON has no NaN).
    """
    value = text.strip()
    if _INT.fullmatch(value):
        return int(value)
    if _FLOAT.fullmatch(value):
        number = float(value)
        return number if math.isfinite(number) else value
    if value in ("true", "false"):
        return value == "true"
    parts = value.split()
    if len(parts) > 1 and all(_INT.fullmatch(p) or _FLOAT.fullmatch(p) for p in parts):
        return [typed(p) for p in parts]
    return value


def _local(tag: Any) -> str:
    return str(tag).rsplit("}", 1)[-1]


def _collect(element: Any, prefix: str, out: dict[str, Any]) -> None:
    for child in element:
        if not isinstance(child.tag, str):
            continue  # a comment or processing instruction
        name = prefix + _local(child.tag)
        if len(child):
            nested: dict[str, Any] = {}
            _collect(child, "", nested)
            value: Any = nested
        else:
            value = typed(child.text or "")
        if name in out:  # a repeated element (detections' markers): a list
            previous = out[name]
            out[name] = [*previous, value] if isinstance(previous, list) else [previous, value]
        else:
            out[name] = value


def decode_metadata(metadata: bytes) -> tuple[str, dict[str, Any]]:
    """(kind, fields); ("?", {}) for metadata that does not parse."""
    try:
        root = parse_untrusted(metadata)
    except FramegateError:
        return "?", {}
    fields: dict[str, Any] = {}
    _collect(root, "", fields)
    return str(root.get("kind", "?")), fields


def field_value(fields: dict[str, Any], name: str) -> Any:
    """A field by name, nested ones by dotted path (``camera.fx_px``); KeyError if absent."""
    value: Any = fields
    for part in name.split("."):
        if not isinstance(value, dict) or part not in value:
            raise KeyError(name)
        value = value[part]
    return value


def flat_names(fields: dict[str, Any], prefix: str = "") -> list[str]:
    """Every field's dotted name, for a did-you-mean."""
    names = []
    for key, value in fields.items():
        names.append(prefix + key)
        if isinstance(value, dict):
            names += flat_names(value, prefix + key + ".")
    return names


def payload_summary(payload: bytes, kind: str, fields: dict[str, Any]) -> str:
    """Size, what the metadata says the bytes are, and the first bytes in hex."""
    parts = [f"{len(payload)} bytes"]
    if kind == "frame" and {"width_px", "height_px", "encoding"} <= fields.keys():
        parts.append(f"{fields['width_px']}x{fields['height_px']} {fields['encoding']}")
    head = payload[:HEAD_BYTES].hex(" ")
    if head:
        parts.append(head + (" ..." if len(payload) > HEAD_BYTES else ""))
    return ", ".join(parts)
