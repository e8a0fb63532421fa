"""The producer's metadata check by document shape agrees with full XSD validation."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import schemas
from middleware import SchemaError, make_metadata, register_kind
from middleware._shapes import MAX_SHAPES, ShapeChecker, counter_slots
from middleware._xml import DEFAULT_LIMITS, metadata_timestamp_ns, validate_metadata

T0 = 1_700_000_000_000_000_000

CAMERA = {
    "width_px": 640,
    "height_px": 480,
    "fx_px": 500.0,
    "fy_px": 500.0,
    "cx_px": 320.0,
    "cy_px": 240.0,
}


def gyro_doc(t: int) -> bytes:
    fields = {"count": 1, "first_ns": t, "last_ns": t, "rate_hz": 1000.0, "layout": "i8,f8,f8,f8"}
    return make_metadata("gyro", t, fields)


def frame_doc(t: int, frame_id: int = 7) -> bytes:
    fields = {
        "frame_id": frame_id,
        "exposure_start_ns": t,
        "exposure_ns": 5_000_000,
        "encoding": "mono8",
        "width_px": 640,
        "height_px": 480,
    }
    return make_metadata("frame", t, fields)


def full(raw: bytes, kind: str) -> int | str:
    try:
        return metadata_timestamp_ns(validate_metadata(raw, kind, DEFAULT_LIMITS))
    except SchemaError:
        return "refused"


def by_shape(checker: ShapeChecker, raw: bytes) -> int | str:
    try:
        return checker.timestamp_ns(raw)
    except SchemaError:
        return "refused"


def test_counter_slots_are_the_fields_typed_as_plain_counters() -> None:
    gyro = counter_slots("gyro")
    frame = counter_slots("frame")
    assert gyro is not None and frame is not None
    assert gyro.attributes == {"timestamp_ns"}
    assert gyro.elements == {"first_ns", "last_ns"}
    # exposure_ns must be >= 1 (PositiveLong) and width a PixelCount: not counters.
    assert frame.elements == {"frame_id", "exposure_start_ns"}


def test_a_document_of_a_known_shape_skips_the_full_check() -> None:
    checker = ShapeChecker("gyro", DEFAULT_LIMITS)
    assert checker.timestamp_ns(gyro_doc(T0)) == T0
    assert checker.hits == 0
    assert checker.timestamp_ns(gyro_doc(T0 + 1_000_000)) == T0 + 1_000_000
    assert checker.hits == 1


def test_frames_of_one_camera_share_a_shape() -> None:
    checker = ShapeChecker("frame", DEFAULT_LIMITS)
    for i in range(5):
        assert (
            checker.timestamp_ns(frame_doc(T0 + i * 33_000_000, frame_id=i)) == T0 + i * 33_000_000
        )
    assert checker.hits == 4


_VALUES = st.one_of(
    st.integers(min_value=-(2**64), max_value=2**64).map(lambda i: str(i).encode()),
    st.sampled_from([b"", b" 5", b"5 ", b"007", b"+5", b"NaN", b"INF", b"1e3", b"5.0", b"\t9"]),
    st.text(alphabet="0123456789 -+.eE", max_size=22).map(str.encode),
)


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(["gyro", "frame"]), st.lists(_VALUES, min_size=4, max_size=4))
def test_by_shape_and_in_full_agree_on_any_slot_values(kind: str, values: list[bytes]) -> None:
    """Whatever a peer writes into the counter slots of a remembered shape, the shape check
    accepts exactly what the XSD accepts and reads the same timestamp."""
    checker = ShapeChecker(kind, DEFAULT_LIMITS)
    base = gyro_doc(T0) if kind == "gyro" else frame_doc(T0)
    assert checker.timestamp_ns(base) == T0
    pattern = checker._pattern
    assert pattern is not None
    pieces = pattern.split(base)
    slots = len(pieces[2::3])
    pieces[2::3] = values[:slots]
    raw = b"".join(pieces)
    assert by_shape(checker, raw) == full(raw, kind)


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(["gyro", "frame"]), st.data())
def test_a_document_like_the_last_one_is_judged_as_in_full(kind: str, data: st.DataObject) -> None:
    """A document of the last one's length whose slot values differ (the path that skips
    the split): whatever the values, it is accepted exactly when the XSD accepts it."""
    checker = ShapeChecker(kind, DEFAULT_LIMITS)
    base = gyro_doc(T0) if kind == "gyro" else frame_doc(T0)
    checker.timestamp_ns(base)
    checker.timestamp_ns(base)  # by shape: now the last document
    pattern = checker._pattern
    assert pattern is not None
    pieces = pattern.split(base)
    for index in range(2, len(pieces), 3):
        size = len(pieces[index])
        alphabet = data.draw(st.sampled_from(["0123456789", "123456789", '0123456789 -+.eE<"']))
        pieces[index] = data.draw(
            st.text(alphabet=alphabet, min_size=size, max_size=size).map(str.encode)
        )
    raw = b"".join(pieces)
    assert len(raw) == len(base)
    assert by_shape(checker, raw) == full(raw, kind)
    # The batch path (``timestamps_ns``) judges it alike.
    batch = ShapeChecker(kind, DEFAULT_LIMITS)
    batch.timestamp_ns(base)
    batch.timestamp_ns(base)
    try:
        assert batch.timestamps_ns([base, raw]) == [T0, full(raw, kind)]
    except SchemaError:
        assert full(raw, kind) == "refused"


def test_a_batch_of_documents_like_the_last_one_skips_the_split() -> None:
    checker = ShapeChecker("gyro", DEFAULT_LIMITS)
    docs = [gyro_doc(T0 + i) for i in range(64)]
    assert checker.timestamps_ns(docs) == [T0 + i for i in range(64)]
    hits = checker.hits
    assert checker.timestamps_ns(docs) == [T0 + i for i in range(64)]
    assert checker.hits == hits + 64


def test_a_document_like_the_last_one_skips_the_split() -> None:
    checker = ShapeChecker("gyro", DEFAULT_LIMITS)
    for i in range(3):
        assert checker.timestamp_ns(gyro_doc(T0 + i)) == T0 + i
    assert checker.hits == 2
    assert checker._last is not None  # the second one: the third was read by it
    # Text outside the value spans differs: cut and judged in full, never by the last one.
    changed = gyro_doc(T0 + 3).replace(b"i8,f8", b"i8,f4")
    assert by_shape(checker, changed) == full(changed, "gyro")


@pytest.mark.parametrize(
    "raw",
    [
        b'<metadata xmlns="urn:framegate:1" kind="gyro" timestamp_ns="5"><!-- c --><count>1'
        b"</count><first_ns>5</first_ns><last_ns>5</last_ns><rate_hz>1.0</rate_hz>"
        b"<layout>i8,f8,f8,f8</layout></metadata>",
        b"<metadata xmlns='urn:framegate:1' kind='gyro' timestamp_ns='5'><count>1"
        b"</count><first_ns>5</first_ns><last_ns>5</last_ns><rate_hz>1.0</rate_hz>"
        b"<layout>i8,f8,f8,f8</layout></metadata>",
        b'<metadata xmlns="urn:framegate:1" kind="gyro" timestamp_ns="5"><count>1'
        b"</count><first_ns><![CDATA[5]]></first_ns><last_ns>5</last_ns><rate_hz>1.0</rate_hz>"
        b"<layout>i8,f8,f8,f8</layout></metadata>",
        b'<metadata xmlns="urn:framegate:1" kind="gyro" timestamp_ns="&#53;"><count>1'
        b"</count><first_ns>5</first_ns><last_ns>5</last_ns><rate_hz>1.0</rate_hz>"
        b"<layout>i8,f8,f8,f8</layout></metadata>",
    ],
    ids=["comment", "apostrophes", "cdata", "char-reference"],
)
def test_documents_not_in_plain_form_are_checked_in_full_every_time(raw: bytes) -> None:
    checker = ShapeChecker("gyro", DEFAULT_LIMITS)
    for _ in range(3):
        assert by_shape(checker, raw) == full(raw, "gyro") == 5
    assert checker.hits == 0


def test_a_nul_byte_cannot_stand_in_for_a_slot() -> None:
    checker = ShapeChecker("gyro", DEFAULT_LIMITS)
    checker.timestamp_ns(gyro_doc(T0))
    forged = gyro_doc(T0).replace(f"<first_ns>{T0}".encode(), b"<first_ns>\x00")
    with pytest.raises(SchemaError):
        checker.timestamp_ns(forged)


def test_a_timestamp_attribute_in_skipped_content_is_not_the_key() -> None:
    checker = ShapeChecker("generic", DEFAULT_LIMITS)
    raw = (
        b'<metadata xmlns="urn:framegate:1" kind="generic" timestamp_ns="10">'
        b'<x timestamp_ns="99"/></metadata>'
    )
    assert checker.timestamp_ns(raw) == 10
    assert checker.timestamp_ns(raw.replace(b'"99"', b'"98"').replace(b'"10"', b'"11"')) == 11
    assert checker.hits == 1


def test_shapes_are_bounded() -> None:
    checker = ShapeChecker("generic", DEFAULT_LIMITS)
    for i in range(MAX_SHAPES + 20):
        checker.timestamp_ns(make_metadata("generic", T0 + i, {f"f{i}": i}))
    assert len(checker._shapes) == MAX_SHAPES


def _custom_kind(tmp_path: Path, name: str, body: str) -> str:
    xsd = tmp_path / f"{name}.xsd"
    shutil.copy(schemas.SCHEMA_DIR / "common.xsd", tmp_path / "common.xsd")
    xsd.write_text(
        '<xs:schema xmlns:xs="http://www.w3.org/2001/XMLSchema" targetNamespace="urn:framegate:1"'
        ' xmlns="urn:framegate:1" elementFormDefault="qualified">'
        f'<xs:include schemaLocation="common.xsd"/>{body}</xs:schema>'
    )
    register_kind(name, xsd)
    return name


_ROOT = (
    '<xs:element name="metadata"><xs:complexType><xs:sequence>{content}</xs:sequence>'
    '<xs:attribute name="kind" type="xs:NCName" use="required"/>'
    '<xs:attribute name="timestamp_ns" type="TimestampNs" use="required"/>'
    "{extra}</xs:complexType></xs:element>"
)


def test_schemas_where_values_can_matter_beyond_their_type_are_never_fast_pathed(
    tmp_path: Path,
) -> None:
    unique = _ROOT.format(
        content='<xs:element name="a" type="TimestampNs"/>'
        '<xs:element name="b" type="TimestampNs"/>',
        extra="",
    ).replace(
        "</xs:element>",
        '<xs:unique name="u"><xs:selector xpath="."/><xs:field xpath="@timestamp_ns"/>'
        "</xs:unique></xs:element>",
        1,
    )
    lax = _ROOT.format(content='<xs:any processContents="lax" minOccurs="0"/>', extra="")
    assert counter_slots(_custom_kind(tmp_path, "shape_unique", unique)) is None
    assert counter_slots(_custom_kind(tmp_path, "shape_lax", lax)) is None


def test_a_bounded_counter_is_not_a_slot(tmp_path: Path) -> None:
    body = (
        '<xs:simpleType name="Small"><xs:restriction base="xs:long">'
        '<xs:minInclusive value="0"/><xs:maxInclusive value="9"/></xs:restriction></xs:simpleType>'
        + _ROOT.format(content='<xs:element name="n" type="Small"/>', extra="")
    )
    kind = _custom_kind(tmp_path, "shape_bounded", body)
    slots = counter_slots(kind)
    assert slots is not None and slots.elements == frozenset()
    checker = ShapeChecker(kind, DEFAULT_LIMITS)
    ok = make_metadata(kind, 5, {"n": 5})
    assert checker.timestamp_ns(ok) == 5
    with pytest.raises(SchemaError):
        checker.timestamp_ns(make_metadata(kind, 6, {"n": 50}))
