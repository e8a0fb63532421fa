"""Hardened XML parsing and XSD validation of metadata.

Metadata arrives from the network, so it is treated as hostile: no DTD (hence no entity
expansion, no XXE, no billion laughs), no network access, bounded size and depth. The
document must then pass the common envelope and its kind's XSD from ``schemas/``.

Values are read the way the XSD saw them. Every field of a framegate kind is a number, a
token or a list, whose XSD whitespace rule is *collapse* (tabs and newlines become spaces,
runs become one, the ends are trimmed), so ``<encoding> mono8 </encoding>`` is valid and
means ``mono8``. ``validate_metadata`` therefore collapses the text of a validated tree in
place (except ``generic`` content, which is free-form), and ``field_text`` collapses what it
returns. Comments and processing instructions are dropped while parsing (a comment inside a
value joins the text around it, as the XSD saw it); prefixes are only names for the
namespace, so ``<fg:metadata xmlns:fg="urn:framegate:1">`` reads like the default form.
"""

from __future__ import annotations

import re
import threading
from dataclasses import dataclass
from functools import cache
from typing import Any

from lxml import etree

import schemas

from ._errors import SchemaError

NAMESPACE = schemas.NAMESPACE
_NS = "{" + NAMESPACE + "}"
# XML Schema's whitespace: space, tab, newline, carriage return (not NBSP or other Unicode).
_XSD_WHITESPACE = re.compile(r"[ \t\n\r]+")


def collapse_whitespace(text: str) -> str:
    """XSD's ``collapse`` whitespace rule: runs of XML whitespace become one space, ends trimmed."""
    return _XSD_WHITESPACE.sub(" ", text).strip(" ")


@dataclass(frozen=True, slots=True)
class XmlLimits:
    """Bounds on untrusted metadata documents."""

    max_bytes: int = 64 * 1024
    max_depth: int = 32
    max_elements: int = 10_000


DEFAULT_LIMITS = XmlLimits()

# lxml parsers are not thread-safe; one per thread.
_local = threading.local()


def _parser() -> etree.XMLParser:
    parser = getattr(_local, "parser", None)
    if parser is None:
        parser = etree.XMLParser(
            resolve_entities=False,
            no_network=True,
            load_dtd=False,
            dtd_validation=False,
            huge_tree=False,
            remove_comments=True,
            remove_pis=True,
        )
        _local.parser = parser
    return parser


def parse_untrusted(data: bytes | str, limits: XmlLimits = DEFAULT_LIMITS) -> Any:
    """Parse an untrusted XML document and return its root element.

    Raises SchemaError naming the problem: too large, a DTD or entity, invalid UTF-8,
    malformed XML, too deep or too many elements.
    """
    raw = data.encode("utf-8") if isinstance(data, str) else bytes(data)
    if len(raw) > limits.max_bytes:
        raise SchemaError(
            f"metadata is {len(raw)} bytes, over the limit of {limits.max_bytes}; "
            "keep metadata small and put bulk data in the payload"
        )
    # Refuse DTDs outright: entities (XXE, billion laughs) can only be declared in one.
    if b"<!DOCTYPE" in raw or b"<!ENTITY" in raw:
        raise SchemaError("metadata contains a DTD or entity declaration, which is not allowed")
    try:
        raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SchemaError(f"metadata is not valid UTF-8 (byte {exc.start})") from exc
    try:
        root = etree.fromstring(raw, _parser())
    except etree.XMLSyntaxError as exc:
        raise SchemaError(f"metadata is not well-formed XML: {exc}") from exc
    if root.getroottree().docinfo.internalDTD is not None:
        raise SchemaError("metadata contains a DTD, which is not allowed")
    # Both walks are skipped when the bytes alone rule the limit out: an element takes at
    # least 4 bytes (``<a/>``) and every level of nesting its own ``<``.
    if len(raw) > 4 * limits.max_elements:
        for count, _element in enumerate(root.iter(), start=1):
            if count > limits.max_elements:
                raise SchemaError(f"metadata has more than {limits.max_elements} elements")
    if raw.count(b"<") > limits.max_depth:
        _check_depth(root, limits.max_depth)
    return root


def _check_depth(root: Any, max_depth: int) -> None:
    stack = [(root, 1)]
    while stack:
        element, depth = stack.pop()
        if depth > max_depth:
            raise SchemaError(f"metadata is nested deeper than {max_depth} levels")
        stack.extend((child, depth + 1) for child in element)


# libxml2 is not safe to enter from two threads at once for one schema: neither parsing an
# XSD (its built-in types are set up by the first parse: two first parses at once failed with
# "xmlSchemaPValAttrNodeValue, the given type is not a built-in type") nor validating with a
# shared XMLSchema. One lock for both; re-entrant because validating loads the schema.
_schema_lock = threading.RLock()


def _schema(name: str) -> etree.XMLSchema:
    with _schema_lock:
        return _load_schema(name)


@cache
def _load_schema(name: str) -> etree.XMLSchema:
    path = schemas.schema_path(name)
    if not path.is_file():
        raise SchemaError(
            f"unknown metadata kind {name!r}; known kinds: {', '.join(schemas.kinds())}"
        )
    # Our own files, but parsed with the same no-network rule; xs:include is local.
    parser = etree.XMLParser(no_network=True, resolve_entities=False)
    return etree.XMLSchema(etree.parse(str(path), parser))


def _validate(name: str, root: Any) -> None:
    with _schema_lock:
        schema = _schema(name)
        ok = schema.validate(root)
        if not ok:
            error = schema.error_log.last_error  # type: ignore[attr-defined]
            raise SchemaError(f"metadata fails {name}.xsd at line {error.line}: {error.message}")


def validate_metadata(
    data: bytes | str, kind: str | None = None, limits: XmlLimits = DEFAULT_LIMITS
) -> Any:
    """Parse untrusted metadata, check the envelope and its kind's XSD; return the root.

    If ``kind`` is given the document must declare that kind.
    """
    root = parse_untrusted(data, limits)
    if root.tag != _NS + "metadata":
        raise SchemaError(f"metadata root must be <metadata xmlns={NAMESPACE!r}>, got {root.tag!r}")
    _validate("envelope", root)
    declared = collapse_whitespace(root.get("kind") or "")
    if kind is not None and declared != kind:
        raise SchemaError(f"metadata declares kind {declared!r} but this buffer holds {kind!r}")
    _validate(declared, root)
    if declared != "generic":
        _collapse_tree(root)
    return root


def _collapse_tree(root: Any) -> None:
    """Make every attribute and leaf text of a validated tree read as the XSD saw it."""
    for element in root.iter():
        for name, value in element.attrib.items():
            if _needs_collapse(value):
                element.set(name, collapse_whitespace(value))
        text = element.text
        if text is not None and len(element) == 0 and _needs_collapse(text):
            element.text = collapse_whitespace(text)


# Text that the collapse rule changes: XML whitespace other than single inner spaces.
_NEEDS_COLLAPSE = re.compile(r"[\t\n\r]|  |^ | $")


def _needs_collapse(text: str) -> bool:
    return _NEEDS_COLLAPSE.search(text) is not None


def metadata_timestamp_ns(root: Any) -> int:
    """The ``timestamp_ns`` attribute of a validated metadata root."""
    return int(root.get("timestamp_ns"))


def make_metadata(kind: str, timestamp_ns: int, fields: dict[str, Any] | None = None) -> bytes:
    """Build a metadata document: ``<metadata kind= timestamp_ns=>`` with one child per field.

    Values that are dicts become nested elements; lists become space-separated text.
    The result is not validated here; ``validate_metadata`` does that.
    """
    root = etree.Element(_NS + "metadata", nsmap={None: NAMESPACE})  # type: ignore[dict-item]
    root.set("kind", kind)
    root.set("timestamp_ns", str(int(timestamp_ns)))
    _add_fields(root, fields or {})
    return bytes(etree.tostring(root, xml_declaration=False, encoding="utf-8"))


def _add_fields(parent: Any, fields: dict[str, Any]) -> None:
    for name, value in fields.items():
        if name.startswith("@"):
            parent.set(name[1:], str(value))
            continue
        if isinstance(value, list | tuple) and all(isinstance(v, dict) for v in value):
            # A list of dicts is a repeated element (none for an empty list).
            for item in value:
                _add_fields(etree.SubElement(parent, _NS + name), item)
            continue
        child = etree.SubElement(parent, _NS + name)
        if isinstance(value, dict):
            _add_fields(child, value)
        elif isinstance(value, list | tuple):
            child.text = " ".join(_text(v) for v in value)
        else:
            child.text = _text(value)


def _text(value: Any) -> str:
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def field_text(root: Any, path: str) -> str | None:
    """Text of a child element by slash-separated local names (namespace added), or None.

    The text is whitespace-collapsed as the XSD saw it (`` mono8 `` reads ``mono8``).
    """
    element = root
    for part in path.split("/"):
        element = element.find(_NS + part)
        if element is None:
            return None
    return collapse_whitespace(str(element.text)) if element.text is not None else ""
