from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

import schemas
from middleware import SchemaError, XmlLimits, make_metadata, parse_untrusted, validate_metadata

NS = 'xmlns="urn:framegate:1"'

XXE = f"""<?xml version="1.0"?>
<!DOCTYPE m [<!ENTITY xxe SYSTEM "file:///etc/passwd">]>
<metadata {NS} kind="generic" timestamp_ns="1">&xxe;</metadata>"""

BILLION_LAUGHS = f"""<?xml version="1.0"?>
<!DOCTYPE lolz [
 <!ENTITY lol "lol">
 <!ENTITY lol1 "&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;">
 <!ENTITY lol2 "&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;">
 <!ENTITY lol3 "&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;">
]>
<metadata {NS} kind="generic" timestamp_ns="1">&lol3;</metadata>"""


def test_every_kind_has_a_schema_that_compiles() -> None:
    assert {"camera", "frame", "generic", "gyro"} <= set(schemas.kinds())
    for kind in schemas.kinds():
        # An empty document of each kind fails its schema (or passes for generic),
        # but the schema itself must load.
        try:
            validate_metadata(make_metadata(kind, 1), kind)
        except SchemaError as exc:
            assert f"{kind}.xsd" in str(exc)


def test_xxe_is_refused_not_resolved() -> None:
    with pytest.raises(SchemaError, match="DTD or entity"):
        validate_metadata(XXE)


def test_billion_laughs_is_refused_not_expanded() -> None:
    with pytest.raises(SchemaError, match="DTD or entity"):
        validate_metadata(BILLION_LAUGHS)


def test_deep_nesting_is_refused() -> None:
    doc = f"<metadata {NS} kind='generic' timestamp_ns='1'>" + "<a>" * 40 + "</a>" * 40
    doc += "</metadata>"
    with pytest.raises(SchemaError, match="nested deeper than 32"):
        validate_metadata(doc)


def test_oversized_document_is_refused() -> None:
    doc = f"<metadata {NS} kind='generic' timestamp_ns='1' x='{'a' * 70_000}'/>"
    with pytest.raises(SchemaError, match="over the limit of 65536"):
        validate_metadata(doc)


def test_invalid_utf8_is_refused() -> None:
    with pytest.raises(SchemaError, match="not valid UTF-8"):
        validate_metadata(b"<metadata>\xff\xfe</metadata>")


def test_wrong_namespace_is_refused() -> None:
    with pytest.raises(SchemaError, match="root must be <metadata"):
        validate_metadata("<metadata kind='generic' timestamp_ns='1'/>")


def test_schema_violation_names_the_element() -> None:
    bad = make_metadata(
        "frame",
        5,
        {
            "frame_id": -1,
            "exposure_start_ns": 5,
            "exposure_ns": 1,
            "encoding": "mono8",
            "width_px": 2,
            "height_px": 2,
        },
    )
    with pytest.raises(SchemaError, match=r"frame\.xsd.*frame_id"):
        validate_metadata(bad, "frame")


def test_unknown_kind_lists_known_kinds() -> None:
    with pytest.raises(SchemaError, match="unknown metadata kind 'nope'; known kinds: camera"):
        validate_metadata(make_metadata("nope", 1))


def test_kind_mismatch_is_refused() -> None:
    with pytest.raises(SchemaError, match="declares kind 'generic' but this buffer holds 'frame'"):
        validate_metadata(make_metadata("generic", 1), "frame")


def test_valid_frame_metadata_passes() -> None:
    doc = make_metadata(
        "frame",
        5,
        {
            "frame_id": 1,
            "exposure_start_ns": 5,
            "exposure_ns": 60_000_000,
            "encoding": "mono8",
            "width_px": 2,
            "height_px": 2,
        },
    )
    assert validate_metadata(doc, "frame").get("timestamp_ns") == "5"


def test_element_count_limit() -> None:
    doc = f"<metadata {NS} kind='generic' timestamp_ns='1'>" + "<a/>" * 50 + "</metadata>"
    with pytest.raises(SchemaError, match="more than 10 elements"):
        parse_untrusted(doc, XmlLimits(max_elements=10))


@given(st.binary(max_size=300))
def test_arbitrary_bytes_parse_or_raise_schema_error(data: bytes) -> None:
    try:
        validate_metadata(data)
    except SchemaError:
        pass
