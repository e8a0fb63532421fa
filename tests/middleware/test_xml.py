from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import schemas
from middleware import (
    SchemaError,
    XmlLimits,
    field_text,
    make_metadata,
    parse_untrusted,
    validate_metadata,
)
from tests.helpers.timing import scaled

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


@settings(deadline=None)  # no wall-clock bound per example
@given(
    depth=st.integers(1, 6),
    width=st.integers(0, 6),
    max_depth=st.integers(1, 8),
    max_elements=st.integers(1, 20),
    short_tags=st.booleans(),
)
def test_size_limits_hold_exactly_whatever_the_shortcut(
    depth: int, width: int, max_depth: int, max_elements: int, short_tags: bool
) -> None:
    # parse_untrusted skips its walks when the byte count rules a limit out: the limits
    # must still hold exactly, at and around the boundaries, with the shortest elements.
    leaf = "<a/>" if short_tags else "<abc></abc>"
    doc = "<r>" * depth + leaf * width + "</r>" * depth
    elements, levels = depth + width, depth + (1 if width else 0)
    limits = XmlLimits(max_depth=max_depth, max_elements=max_elements)
    if elements > max_elements or levels > max_depth:
        with pytest.raises(SchemaError, match=r"more than|nested deeper"):
            parse_untrusted(doc, limits)
    else:
        parse_untrusted(doc, limits)


@settings(deadline=None)  # no wall-clock bound per example
@given(st.binary(max_size=300))
def test_arbitrary_bytes_parse_or_raise_schema_error(data: bytes) -> None:
    try:
        validate_metadata(data)
    except SchemaError:
        pass


FRAME = {
    "frame_id": 1,
    "exposure_start_ns": 5,
    "exposure_ns": 60_000_000,
    "encoding": "mono8",
    "width_px": 2,
    "height_px": 2,
}
CAMERA = {
    "width_px": 2,
    "height_px": 2,
    "fx_px": 500.0,
    "fy_px": 500.0,
    "cx_px": 1.0,
    "cy_px": 1.0,
    "line_readout_ns": 0,
    "gyro_to_camera": [1, 0, 0, 0, 1, 0, 0, 0, 1],
    "gyro_time_offset_ns": 0,
}
GYRO = {"count": 1, "first_ns": 1, "last_ns": 1, "rate_hz": 200.0, "layout": "i8,f8,f8,f8"}
DECISION = {
    "frame_timestamp_ns": 5,
    "frame_id": 1,
    "blur_px": 1.5,
    "quality": 0.5,
    "load": 0.2,
    "accepted": True,
    "reason": "accepted",
    "policy": "immediate",
    "b0_px": 2.0,
    "latency_ns": 3,
}
SPACED_FRAME = (
    '<fg:metadata xmlns:fg="urn:framegate:1" kind=" frame " timestamp_ns=" 5 ">'
    "<fg:frame_id>\n 1\t</fg:frame_id><fg:exposure_start_ns>5</fg:exposure_start_ns>"
    "<fg:exposure_ns>6<!-- a comment -->0</fg:exposure_ns>"
    "<fg:encoding><![CDATA[ mono8 ]]></fg:encoding>"
    "<fg:width_px>&#32;2</fg:width_px><fg:height_px>2<?pi x?></fg:height_px></fg:metadata>"
)


def test_values_read_as_the_xsd_saw_them() -> None:
    # Whitespace, a comment inside a value, CDATA, a character reference, a prefix and a
    # processing instruction: all valid, and every reader sees the collapsed values.
    root = validate_metadata(SPACED_FRAME, "frame")
    fields = {name: field_text(root, name) for name in FRAME}
    assert fields == {**{k: str(v) for k, v in FRAME.items()}, "exposure_ns": "60"}
    assert root.get("kind") == "frame" and root.get("timestamp_ns") == "5"
    assert root.findtext("{urn:framegate:1}encoding") == "mono8"


def test_field_text_collapses_an_unvalidated_tree_too() -> None:
    root = parse_untrusted(SPACED_FRAME)
    assert field_text(root, "encoding") == "mono8"
    assert field_text(root, "frame_id") == "1"


def test_non_breaking_space_is_not_xml_whitespace() -> None:
    with pytest.raises(SchemaError, match=r"frame\.xsd.*encoding"):
        validate_metadata(make_metadata("frame", 5, {**FRAME, "encoding": "mono8\u00a0"}))


def test_generic_content_is_left_as_sent() -> None:
    root = validate_metadata(make_metadata("generic", 1, {"note": "  two  spaces "}), "generic")
    assert root.findtext("{urn:framegate:1}note") == "  two  spaces "


@pytest.mark.parametrize("value", ["NaN", "INF", "-INF", "1e400", "-1e999"])
@pytest.mark.parametrize(
    ("kind", "fields", "path"),
    [
        ("frame", {**FRAME, "camera": CAMERA}, ("camera", "fx_px")),
        ("frame", {**FRAME, "camera": CAMERA}, ("camera", "cy_px")),
        ("camera", {"camera": CAMERA}, ("camera", "gyro_to_camera")),
        ("gyro", GYRO, ("rate_hz",)),
        ("decision", DECISION, ("blur_px",)),
        ("decision", DECISION, ("quality",)),
        ("decision", DECISION, ("b0_px",)),
    ],
)
def test_non_finite_numbers_are_refused(
    kind: str, fields: dict[str, object], path: tuple[str, ...], value: str
) -> None:
    validate_metadata(make_metadata(kind, 5, fields), kind)  # the good one passes
    bad = _with(fields, path, value if path[-1] != "gyro_to_camera" else f"1 0 0 0 {value} 0 0 0 1")
    with pytest.raises(SchemaError, match=rf"{kind}\.xsd.*{path[-1]}"):
        validate_metadata(make_metadata(kind, 5, bad), kind)


@pytest.mark.parametrize(
    ("kind", "fields", "path", "value"),
    [
        ("frame", FRAME, ("exposure_ns",), 0),
        ("frame", FRAME, ("width_px",), 0),
        ("frame", FRAME, ("height_px",), 65_536),
        ("frame", FRAME, ("width_px",), 10**30),
        ("frame", {**FRAME, "camera": CAMERA}, ("camera", "fy_px"), 0.0),
        ("frame", {**FRAME, "camera": CAMERA}, ("camera", "fx_px"), "1e-400"),
        ("gyro", GYRO, ("count",), 10**12),
        ("gyro", GYRO, ("rate_hz",), -200.0),
        ("decision", DECISION, ("blur_px",), -1.0),
        ("decision", DECISION, ("load",), 1.5),
        ("camera", {"camera": CAMERA, "frame_period_ns": 1}, ("frame_period_ns",), 0),
    ],
)
def test_sizes_exposures_and_rates_that_cannot_be_are_refused(
    kind: str, fields: dict[str, object], path: tuple[str, ...], value: object
) -> None:
    validate_metadata(make_metadata(kind, 5, fields), kind)
    with pytest.raises(SchemaError, match=rf"{kind}\.xsd.*{path[-1]}"):
        validate_metadata(make_metadata(kind, 5, _with(fields, path, value)), kind)


@settings(deadline=None)  # no wall-clock bound per example
@given(st.floats(allow_nan=True, allow_infinity=True))
def test_a_focal_length_is_valid_exactly_when_finite_and_positive(fx_px: float) -> None:
    doc = make_metadata("camera", 5, {"camera": {**CAMERA, "fx_px": fx_px}})
    if math.isfinite(fx_px) and fx_px > 0:
        root = validate_metadata(doc, "camera")
        assert float(field_text(root, "camera/fx_px") or "nan") == fx_px
    else:
        with pytest.raises(SchemaError, match="fx_px"):
            validate_metadata(doc, "camera")


def _with(fields: dict[str, object], path: tuple[str, ...], value: object) -> dict[str, object]:
    if len(path) == 1:
        return {**fields, path[0]: value}
    inner = fields[path[0]]
    assert isinstance(inner, dict)
    return {**fields, path[0]: _with(inner, path[1:], value)}


_FIRST_LOADS_AT_ONCE = """
import threading
import schemas
from middleware._xml import _schema

kinds = [k for k in schemas.kinds() if k != "envelope"]
barrier = threading.Barrier(len(kinds))
errors = []

def load(kind):
    barrier.wait()
    try:
        _schema(kind)
    except Exception as exc:
        errors.append(repr(exc))

threads = [threading.Thread(target=load, args=(k,)) for k in kinds]
for t in threads:
    t.start()
for t in threads:
    t.join()
print(errors)
"""


def test_schemas_loaded_first_from_several_threads_at_once_all_compile() -> None:
    """libxml2 sets up its built-in XSD types on the first schema parse of a process; two
    first parses at once failed ("xmlSchemaPValAttrNodeValue, the given type is not a
    built-in type": a recorder's threads, in about one fresh process in four)."""
    import subprocess
    import sys

    from tests.conftest import REPO, child_env

    # One fresh process after another (at once they would rarely overlap their threads on
    # two cores); each failed with a chance of about one in five before the fix.
    for _ in range(16):
        run = subprocess.run(
            [sys.executable, "-c", _FIRST_LOADS_AT_ONCE],
            cwd=REPO,
            env=child_env(),
            capture_output=True,
            text=True,
            timeout=scaled(60),
        )
        assert run.stdout.strip() == "[]", run.stdout + run.stderr
