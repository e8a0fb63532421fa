"""Shifting a recorded element in time (``play --rebase`` and ``--loop``).

A buffer refuses an element whose metadata ``timestamp_ns`` differs from its key, so a
shifted element needs shifted metadata. Besides that attribute, every metadata field whose
XSD type is ``TimestampNs`` (e.g. a frame's ``exposure_start_ns``, a gyro batch's
``first_ns``/``last_ns``) moves with it; durations do not. A gyro batch's payload holds
its samples' times too (``GYRO_DTYPE`` records), and consumers such as the mediator read
the samples from there, so they move by the same shift; the rates stay bit for bit. Other
kinds' payloads carry no times and are passed on as recorded, as is a gyro payload that is
no whole number of records (nothing in it can be read as a time; consumers refuse it).
"""

from __future__ import annotations

import re
from functools import cache

from lxml import etree

import schemas
from middleware import DataObject, SchemaError, parse_untrusted

_XS = "{http://www.w3.org/2001/XMLSchema}"
_INT64_MAX = 2**63 - 1
# A time a field may hold: ASCII digits, at most int64's 19 (``str.isdigit`` also takes
# superscripts, on which ``int`` raises, and a 5,000-digit run, past ``int``'s limit: a
# recording holding either ended ``play --rebase`` with a ValueError traceback). Anything
# else is left as it is, for the buffer to refuse as a counted skip.
_TIME_TEXT = re.compile(r"[0-9]{1,19}")


@cache
def timestamp_fields(kind: str) -> frozenset[str]:
    """Local names of the fields of ``kind`` typed ``TimestampNs`` in its XSD."""
    path = schemas.SCHEMA_DIR / f"{kind}.xsd"
    if not path.is_file():
        return frozenset()
    parser = etree.XMLParser(no_network=True, resolve_entities=False)
    tree = etree.parse(str(path), parser)
    return frozenset(
        str(el.get("name"))
        for el in tree.iter(_XS + "element")
        if el.get("name") and (el.get("type") or "").split(":")[-1] == "TimestampNs"
    )


def shift_element(element: DataObject, kind: str, shift_ns: int) -> DataObject:
    """The element ``shift_ns`` later, with its metadata's timestamps moved along."""
    if shift_ns == 0:
        return element
    root = parse_untrusted(element.metadata)
    timestamp = element.timestamp_ns + shift_ns
    root.set("timestamp_ns", str(timestamp))
    fields = timestamp_fields(kind)
    for node in root.iter():
        if not isinstance(node.tag, str) or node is root:
            continue
        if etree.QName(node).localname not in fields or node.text is None:
            continue
        if _TIME_TEXT.fullmatch(node.text.strip()):
            node.text = str(int(node.text) + shift_ns)
    metadata = bytes(etree.tostring(root, encoding="utf-8", xml_declaration=False))
    payload = shift_gyro_payload(element.payload, shift_ns) if kind == "gyro" else element.payload
    return DataObject(timestamp, payload, metadata)


def shift_gyro_payload(payload: bytes, shift_ns: int) -> bytes:
    """A gyro batch's payload with every sample time ``shift_ns`` later, rates untouched.

    A payload that is no whole number of records is returned as it is; SchemaError when a
    shifted time would leave the int64 range.
    """
    import numpy as np  # imported here: only a rebased or looped gyro buffer needs it

    from services.lib.quality import GYRO_DTYPE

    if shift_ns == 0 or not payload or len(payload) % GYRO_DTYPE.itemsize:
        return payload
    records = np.frombuffer(payload, dtype=GYRO_DTYPE).copy()
    times = records["t"]
    low, high = int(times.min()), int(times.max())
    if high + shift_ns > _INT64_MAX or low + shift_ns < -_INT64_MAX - 1:
        raise SchemaError(
            f"gyro sample times {low}..{high} ns shifted by {shift_ns} ns leave the int64 range"
        )
    records["t"] = times + np.int64(shift_ns)
    return records.tobytes()
