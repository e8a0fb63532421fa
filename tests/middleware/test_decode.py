"""The one bounded, typed decoder of replies read from the network (``@info``): hostile
answers are one QueryError each, whose message is one line, never another exception."""

from __future__ import annotations

import json
from typing import Any

import pytest

from middleware import QueryError
from middleware._decode import MAX_DEPTH, MAX_REPLY_BYTES, decode_json
from middleware._info_codec import decode_service_info


def _good() -> dict[str, Any]:
    return {
        "service": "cam",
        "host": "h",
        "pid": 1,
        "clock_ns": 5,
        "clock": {"steps": 0, "lead_ns": 0},
        "instance": "i",
        "started_ns": 1,
        "buffers": [
            {
                "service": "cam",
                "buffer": "images",
                "kind": "generic",
                "retention": {},
                "count": 0,
                "payload_bytes": 0,
                "oldest_ns": None,
                "newest_ns": None,
                "rate_hz": 0,
                "puts": 0,
                "refused": 0,
                "rejected": 0,
                "subscriptions": [{"id": "a", "mode": "flow", "queue_size": 2, "queued": 0}],
                "skipped": {"late": 3},
            }
        ],
    }


def _decode(body: Any) -> Any:
    raw = body if isinstance(body, bytes) else json.dumps(body).encode()
    return decode_service_info(raw, 0, 10, service="cam")


def test_a_valid_description_decodes_typed() -> None:
    info = _decode(_good())
    assert info.service == "cam" and info.buffers[0].subscriptions[0].queue_size == 2
    assert info.buffers[0].skipped == {"late": 3} and info.buffers[0].limits is None


def _without_subscriptions() -> dict[str, Any]:
    body = _good()
    del body["buffers"][0]["subscriptions"]
    return body


def _wrong_type() -> dict[str, Any]:
    body = _good()
    body["buffers"][0]["count"] = "many"
    return body


def _bool_pid() -> dict[str, Any]:
    body = _good()
    body["pid"] = True
    return body


def _listed_twice() -> dict[str, Any]:
    body = _good()
    body["buffers"].append(body["buffers"][0])
    return body


def _changed(path: str, value: Any) -> dict[str, Any]:
    """The good description with one field (``a.b.0.c``) set to ``value``."""
    body = _good()
    *parents, last = path.split(".")
    node: Any = body
    for part in parents:
        node = node[int(part)] if part.isdigit() else node[part]
    node[last] = value
    return body


@pytest.mark.parametrize(
    ("body", "says"),
    [
        # A number past 2^63 in a retention broke whatever formats it as a float later.
        (_changed("buffers.0.retention", {"max_bytes": 10**400}), "max_bytes"),
        (_changed("buffers.0.retention", {"max_age_ns": 2**63}), "max_age_ns"),
        # Invisible characters that reorder or hide what a terminal shows.
        (_changed("host", "a\u202egnp.exe"), "unprintable character \\(U\\+202E\\)"),
        (_changed("buffers.0.subscriptions.0.node", "x\u200by"), "U\\+200B"),
        # A reply that poses as another service than the one it answered for.
        (_changed("service", "camera"), "names itself 'camera'"),
        # A buffer no producer could offer (``ls`` showed it as ``cam/../../etc``).
        (_changed("buffers.0.buffer", "../../etc"), "is no buffer name"),
        # Another service's buffer: ``record --all`` recorded camera/images twice, and a
        # service field ``../..`` ended it with nothing recorded.
        (_changed("buffers.0.service", "camera"), "names another service, 'camera'"),
        (_changed("buffers.0.service", "../.."), "names another service"),
        (_listed_twice(), "lists buffer 'images' more than once"),
    ],
)
def test_a_sane_looking_but_false_reply_is_one_line_query_error(body: Any, says: str) -> None:
    with pytest.raises(QueryError, match=says) as caught:
        _decode(body)
    assert "\n" not in str(caught.value)


@pytest.mark.parametrize(
    ("body", "says"),
    [
        (_without_subscriptions(), "lacks 'subscriptions'"),
        (b'{"service": "\xff\xfe"}', "not UTF-8"),
        (b"[" * 100_000 + b"]" * 100_000, "nests 100000 levels"),
        (b"{" * (MAX_DEPTH + 1), f"nests {MAX_DEPTH + 1} levels"),
        (b" " * (MAX_REPLY_BYTES + 1), "exceeds"),
        (b"{not json", "not JSON"),
        (b"[]", "expected an object"),
        (_wrong_type(), "'count' is str, not int"),
        (_bool_pid(), "'pid' is bool, not int"),
    ],
)
def test_a_hostile_reply_is_one_line_query_error(body: Any, says: str) -> None:
    with pytest.raises(QueryError, match=says) as caught:
        _decode(body)
    assert "\n" not in str(caught.value)


def test_brackets_inside_strings_do_not_count_as_nesting() -> None:
    assert decode_json(json.dumps({"a": "[" * 1000}).encode(), "x") == {"a": "[" * 1000}
