"""Metadata validation for a producer's hot path: the full XSD check once per document shape.

A camera's or a gyro's metadata documents differ from one element to the next only in a few
counters and timestamps: ``<metadata kind="gyro" timestamp_ns="…"><first_ns>…</first_ns>``.
Parsing and validating each one (lxml, ~10 µs) is most of the per-element cost of a small
element, so ``ShapeChecker`` validates a document in full once and remembers its *shape*:
the bytes with the values of its *counter slots* cut out. A later document of the same shape
is valid exactly when each of its slot values is, and a slot's value is checked with one
regular expression and one comparison.

Why that is exact. A counter slot is an attribute or a leaf element whose every declaration
in the kind's schema set (the kind's XSD and everything it includes, and the envelope) has a
*counter type*: a named simple type that is ``xs:long`` restricted by ``minInclusive 0``
and nothing else, so that it accepts every integer 0 .. 2**63-1 (``TimestampNs``,
``NonNegativeLong``). Two documents of one shape differ only in such values; the fast path
accepts only canonical digit strings in that range, which every counter type accepts, so
the second document is valid if the first was. Schemas where a value can matter beyond its
type are never fast-pathed: identity constraints (``xs:unique``/``xs:key``/``xs:keyref``,
which compare values across slots), ``lax`` or ``strict`` wildcards, imports and
redefinitions, fixed or default values on a slot. Documents are fast-pathed only in a plain
form the regular expressions read unambiguously: no comment, CDATA, DTD, processing
instruction, entity or character reference, apostrophe or ``xsi:`` attribute; anything else
is validated in full every time (correct, only slower).

Shapes are bounded (``MAX_SHAPES`` per checker, the oldest forgotten first) and only small
documents are remembered, so a peer cannot grow a producer's memory with new shapes.

The last document accepted by its shape is kept too, with where its slot values lie. A
producer's next document almost always has the same length and differs only inside those
spans (a timestamp keeps its digit count for years), and such a document has the same shape
without cutting it: its text outside the spans is the last one's, and an opener cannot reach
into a span (it ends with ``="`` or ``>``, the byte just before a span, and a span holds only
digits), so the split finds the same openers at the same places. One regular expression made
from the last document (its text between the spans, literally, and a counter of each span's
width) then checks such a document in one match instead of a split, a join and a dictionary
look-up of the whole document.
"""

from __future__ import annotations

import re
import threading
from collections import OrderedDict
from dataclasses import dataclass
from functools import cache
from pathlib import Path

from lxml import etree

import schemas

from ._xml import XmlLimits, metadata_timestamp_ns, validate_metadata

# Shapes one checker remembers, and the largest document it remembers one of.
MAX_SHAPES = 64
MAX_SHAPE_BYTES = 4096

_XS = "{http://www.w3.org/2001/XMLSchema}"
_TS_MAX = 2**63 - 1
_CANONICAL = re.compile(rb"(?:0|[1-9][0-9]{0,18})\Z")
# What the plain form excludes (``_plain``): markup declarations, PIs, references, apostrophes
# (an attribute value in apostrophes could hide a slot-like string), NUL (it stands for a
# value in a shape; XML never contains it), xsi: attributes.
# Constructs that let a value matter beyond its type, or bring in declarations we do not read.
_UNSAFE_XSD = {"unique", "key", "keyref", "import", "redefine", "override", "assert"}


@dataclass(frozen=True, slots=True)
class _Slots:
    """The counter slots of one kind: attribute names and leaf element names."""

    attributes: frozenset[str]
    elements: frozenset[str]

    def pattern(self) -> re.Pattern[bytes]:
        """Two groups, a slot's opener and its value: ``split`` gives part, opener, value, ..."""
        attributes = b"|".join(re.escape(n.encode()) for n in sorted(self.attributes))
        openers = [rb"[ \t\r\n](?:" + attributes + rb')="']
        if self.elements:
            elements = b"|".join(re.escape(n.encode()) for n in sorted(self.elements))
            openers.append(rb"<(?:" + elements + rb")>")
        return re.compile(rb"(" + b"|".join(openers) + rb')([^"<]*)')


class ShapeChecker:
    """Validates metadata of one kind and returns its ``timestamp_ns``; remembers shapes.

    Threads: any thread may call ``timestamp_ns``; ``_lock`` guards the shape table only
    (validation runs outside it).
    """

    def __init__(self, kind: str, limits: XmlLimits) -> None:
        self.kind = kind
        self._limits = limits
        self._max_bytes = min(MAX_SHAPE_BYTES, limits.max_bytes)
        slots = counter_slots(kind)
        self._pattern = slots.pattern() if slots is not None else None
        # shape -> index of the root's timestamp_ns among the document's slot values
        self._shapes: OrderedDict[bytes, int] = OrderedDict()
        self._lock = threading.Lock()
        self.hits = 0
        # The last document accepted by shape: (it, its value spans, the root slot's index);
        # replaced whole, so a reader on another thread sees one consistent tuple.
        self._last: tuple[bytes, tuple[tuple[int, int], ...], int] | None = None
        # ``_last`` as later documents are compared with it (``_like_of_last``).
        self._like: tuple[object, _Like | None] = (None, None)

    def timestamp_ns(self, raw: bytes) -> int:
        """Check ``raw`` (UTF-8 metadata) in full or by its shape; its ``timestamp_ns``.

        Raises SchemaError like ``validate_metadata``.
        """
        like = self._like_of_last()
        if like is not None and like.pattern.fullmatch(raw) is not None:
            self.hits += 1  # a statistic: a lost increment between threads is harmless
            begin, end = like.root
            return int(raw[begin:end])
        cut = self._cut(raw)
        if cut is not None:
            shape, values, pieces = cut
            with self._lock:
                root_slot = self._shapes.get(shape)
                if root_slot is not None:
                    self.hits += 1
            if root_slot is not None:
                self._last = (raw, _spans(pieces), root_slot)
                return int(values[root_slot])
        root = validate_metadata(raw, self.kind, self._limits)
        declared = metadata_timestamp_ns(root)
        if cut is not None:
            self._remember(raw, cut[0], declared)
        return declared

    def timestamps_ns(self, raws: list[bytes]) -> list[int]:
        """``timestamp_ns`` of each document of a batch: one match per document like the
        last one accepted (see ``_Like``), ``timestamp_ns`` for any other."""
        out: list[int] = []
        append = out.append
        like = self._like_of_last()
        hits = 0
        for raw in raws:
            if like is not None and like.pattern.fullmatch(raw) is not None:
                begin, end = like.root
                append(int(raw[begin:end]))
                hits += 1
                continue
            append(self.timestamp_ns(raw))  # may make another document the last one
            like = self._like_of_last()
        self.hits += hits
        return out

    def _like_of_last(self) -> _Like | None:
        """``_Like`` of the last document accepted by shape, made once per such document
        (kept beside it: a producer's documents are almost all like its last one)."""
        last = self._last
        made_for, like = self._like
        if made_for is not last:
            like = _Like.of(last) if last is not None else None
            self._like = (last, like)  # replaced whole: another thread sees one pair
        return like

    def _cut(self, raw: bytes) -> tuple[bytes, list[bytes], list[bytes]] | None:
        """(shape, slot values, split pieces) of a plain, small document whose slots all
        hold canonical counters; None otherwise (then it is validated in full)."""
        if self._pattern is None or len(raw) > self._max_bytes or not _plain(raw):
            return None
        pieces = self._pattern.split(raw)
        values = pieces[2::3]
        if not values or not _all_counters(values):
            return None
        holes = list(pieces)
        holes[2::3] = [b"\x00"] * len(values)
        return b"".join(holes), values, pieces

    def _remember(self, raw: bytes, shape: bytes, declared: int) -> None:
        # Which slot is the root's timestamp_ns: the one inside the root's start tag (a
        # plain document starts with it, and its first ">" ends it or lies in it).
        assert self._pattern is not None
        root_end = raw.index(b">")
        pieces = self._pattern.split(raw)
        offset = 0
        for index in range(len(pieces) // 3):
            before, opener, value = pieces[3 * index : 3 * index + 3]
            offset += len(before) + len(opener)
            if offset > root_end:
                return
            if opener[1:] == b'timestamp_ns="' and int(value) == declared:
                with self._lock:
                    self._shapes[shape] = index
                    self._shapes.move_to_end(shape)
                    while len(self._shapes) > MAX_SHAPES:
                        self._shapes.popitem(last=False)
                return
            offset += len(value)


@dataclass(frozen=True, slots=True)
class _Like:
    """The last accepted document as others are compared with it: ``pattern`` matches
    exactly the documents of its length whose text outside its value spans is its own and
    whose every span holds a canonical counter of the span's width (no leading zero; a
    19-digit one below 9e18, so within 2**63-1 without a comparison: one that starts with 9
    takes the cut path, which compares): one match in C per document instead of a loop of
    slices and checks in Python. ``root``: the span of the root's timestamp."""

    pattern: re.Pattern[bytes]
    root: tuple[int, int]

    @classmethod
    def of(cls, last: tuple[bytes, tuple[tuple[int, int], ...], int]) -> _Like:
        text, spans, root_slot = last
        parts: list[bytes] = []
        start = 0
        for begin, end in spans:
            parts.append(re.escape(text[start:begin]))
            parts.append(_counter_of_width(end - begin))
            start = end
        parts.append(re.escape(text[start:]))
        return cls(re.compile(b"".join(parts)), spans[root_slot])


def _counter_of_width(width: int) -> bytes:
    """A canonical counter of exactly ``width`` digits (``_CANONICAL``, below 9e18)."""
    if width == 1:
        return rb"[0-9]"
    if width < 19:
        return rb"[1-9][0-9]{%d}" % (width - 1)
    if width == 19:
        return rb"[1-8][0-9]{18}"
    return rb"(?!)"  # wider than any counter: never matches


def _spans(pieces: list[bytes]) -> tuple[tuple[int, int], ...]:
    """Where the slot values of a split document lie: (start, end) each."""
    spans = []
    offset = 0
    for index in range(len(pieces) // 3):
        before, opener, value = pieces[3 * index : 3 * index + 3]
        offset += len(before) + len(opener)
        spans.append((offset, offset + len(value)))
        offset += len(value)
    return tuple(spans)


def _plain(raw: bytes) -> bool:
    # Spelled out: a generator over _NOT_PLAIN costs more than the six searches.
    return not (
        b"<!" in raw
        or b"<?" in raw
        or b"&" in raw
        or b"'" in raw
        or b"\x00" in raw
        or b"XMLSchema-instance" in raw
    )


def _all_counters(values: list[bytes]) -> bool:
    for value in values:
        if _CANONICAL.match(value) is None or (len(value) == 19 and int(value) > _TS_MAX):
            return False
    return True


@cache
def counter_slots(kind: str) -> _Slots | None:
    """The counter slots of ``kind``, or None when its schemas cannot be fast-pathed."""
    try:
        documents = _schema_set(schemas.schema_path(kind)) + _schema_set(
            schemas.schema_path("envelope")
        )
    except (OSError, etree.XMLSyntaxError):
        return None
    counters: set[str] = set()
    for doc in documents:
        for node in doc.iter(_XS + "*"):
            local = etree.QName(node).localname
            if local in _UNSAFE_XSD:
                return None
            if local in {"any", "anyAttribute"} and node.get("processContents") != "skip":
                return None
            if local == "simpleType" and node.get("name") and _is_counter_type(node):
                counters.add(str(node.get("name")))
    names: dict[tuple[str, str], set[bool]] = {}
    for doc in documents:
        for node in doc.iter(_XS + "element", _XS + "attribute"):
            name = node.get("name")
            if name is None:
                continue  # a ref= uses a declaration that is checked on its own
            kind_of = "attribute" if node.tag == _XS + "attribute" else "element"
            type_name = (node.get("type") or "").rpartition(":")[2]
            ok = type_name in counters and node.get("fixed") is None and node.get("default") is None
            names.setdefault((kind_of, name), set()).add(ok)
    slots = {key for key, oks in names.items() if oks == {True}}
    if ("attribute", "timestamp_ns") not in slots:
        return None  # the root's key is not a plain counter here: nothing to remember by
    return _Slots(
        attributes=frozenset(n for k, n in slots if k == "attribute"),
        elements=frozenset(n for k, n in slots if k == "element"),
    )


def _is_counter_type(node: etree._Element) -> bool:
    """``<xs:simpleType><xs:restriction base="xs:long"><xs:minInclusive value="0"/>`` exactly."""
    children = [c for c in node if isinstance(c.tag, str)]
    if len(children) != 1 or children[0].tag != _XS + "restriction":
        return False
    restriction = children[0]
    if (restriction.get("base") or "").rpartition(":")[2] != "long":
        return False
    facets = [c for c in restriction if isinstance(c.tag, str)]
    return (
        len(facets) == 1
        and facets[0].tag == _XS + "minInclusive"
        and (facets[0].get("value") or "").strip() == "0"
    )


def _schema_set(path: Path) -> list[etree._Element]:
    """``path`` and every schema it includes, transitively, each once."""
    parser = etree.XMLParser(no_network=True, resolve_entities=False, remove_comments=True)
    seen: dict[Path, etree._Element] = {}
    todo = [path.resolve()]
    while todo:
        current = todo.pop()
        if current in seen:
            continue
        root = etree.parse(str(current), parser).getroot()
        seen[current] = root
        for include in root.iter(_XS + "include"):
            location = include.get("schemaLocation")
            if location is None:
                raise OSError(f"{current}: include without schemaLocation")
            todo.append((current.parent / location).resolve())
    return list(seen.values())
