"""Shifting a recorded element in time (``play --rebase`` and ``--loop``).

A buffer refuses an element whose metadata ``timestamp_ns`` differs from its key, so a
shifted element needs shifted metadata. Besides that attribute, every metadata field whose
XSD type is ``TimestampNs`` (e.g. a frame's ``exposure_start_ns``, a gyro batch's
``first_ns``/``last_ns``) moves with it; durations do not. Payloads are never touched (a
gyro batch's binary sample times stay as recorded).
"""

from __future__ import annotations

from functools import cache

from lxml import etree

import schemas
from middleware import DataObject, parse_untrusted

_XS = "{http://www.w3.org/2001/XMLSchema}"


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
        if etree.QName(node).localname in fields and node.text and node.text.strip().isdigit():
            node.text = str(int(node.text) + shift_ns)
    metadata = bytes(etree.tostring(root, encoding="utf-8", xml_declaration=False))
    return DataObject(timestamp, element.payload, metadata)
