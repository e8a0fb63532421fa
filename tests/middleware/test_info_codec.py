"""The ``@info`` reply both ways: what a service encodes decodes to the same records, in the
wire's own spelling, and ``ls --json`` / ``info --json`` print the records' one JSON form."""

from __future__ import annotations

import dataclasses
import json

from middleware import (
    BufferInfo,
    BufferLimits,
    ClockStatus,
    Retention,
    Rewind,
    ServiceInfo,
    SubscriptionInfo,
    SubscriptionMode,
)
from middleware._info_codec import (
    BUFFER_DESCRIPTION_BYTES,
    SHOWN_TEXT,
    decode_service_info,
    encode_service_info,
    first_repeated,
)
from services.cli import info as info_cli
from services.cli import ls as ls_cli

CLOCK = ClockStatus(steps=2, last_step_ns=-20_000_000_000, lead_ns=19_000_000_000)


def _service() -> ServiceInfo:
    """A description with every field set to something other than its default."""
    subs = (
        SubscriptionInfo("s1", SubscriptionMode.FLOW, 4, 3, None, "mediator", "h1"),
        SubscriptionInfo("s2", SubscriptionMode.OBSERVE, 2, 2, None, "", "h2"),
    )
    buffer = BufferInfo(
        service="cam",
        buffer="images",
        kind="frame",
        retention=Retention(max_count=5, max_bytes=None, max_age_ns=9, max_payload_bytes=8),
        count=3,
        payload_bytes=100,
        oldest_ns=10,
        newest_ns=20,
        rate_hz=2.5,
        puts=7,
        refused=1,
        rejected=2,
        subscriptions=subs,
        skipped={"late": 3},
        refused_subscriptions=4,
        rewinds=(Rewind(5, 2, 6, 7, "restart"),),
        limits=BufferLimits(1, 2, 3, 4, 5, 6, holder_share="some", control_inbox_bytes=99),
        dropped_messages=8,
        bad_messages=9,
        foreign_acks=10,
        collapsed_tokens=13,
    )
    return ServiceInfo(
        service="cam",
        host="h",
        pid=12,
        clock_ns=1_000,
        buffers=(buffer, dataclasses.replace(buffer, buffer="other", limits=None)),
        clock_offset_ns=None,
        round_trip_ns=None,
        clock_steps=CLOCK.steps,
        clock_lead_ns=CLOCK.lead_ns,
        clock_last_step_ns=CLOCK.last_step_ns,
        threads=("MainThread", "fg-serve-cam"),
        listen=("tcp/127.0.0.1:7447",),
        dropped_queries=11,
    )


def _round_trip(info: ServiceInfo) -> ServiceInfo:
    raw = encode_service_info(info, CLOCK, instance="i", started_ns=1)
    return decode_service_info(raw, 990, 1_010, service="cam")


def test_every_field_of_a_description_survives_the_wire() -> None:
    """A field added to a record and not read back by the decoder fails here."""
    sent = _service()
    got = _round_trip(sent)
    # What the reader measures itself: the clock offset from its own ask and answer times.
    assert (got.clock_offset_ns, got.round_trip_ns) == (0, 20)
    assert dataclasses.replace(got, clock_offset_ns=None, round_trip_ns=None) == sent
    for field in dataclasses.fields(ServiceInfo):  # no default hid a field left unread
        if field.name not in ("clock_offset_ns", "round_trip_ns"):
            assert getattr(sent, field.name) != field.default, field.name
    for field in dataclasses.fields(BufferInfo):
        if field.default is not dataclasses.MISSING:
            assert getattr(sent.buffers[0], field.name) != field.default, field.name


def test_the_wire_spells_a_subscription_as_every_peer_reads_it() -> None:
    sent = _service()
    body = json.loads(encode_service_info(sent, CLOCK, instance="i", started_ns=1))
    assert body["clock"] == dataclasses.asdict(CLOCK)
    assert (body["instance"], body["started_ns"]) == ("i", 1)
    sub = body["buffers"][0]["subscriptions"][0]
    assert sub == {
        "id": "s1",
        "mode": "flow",
        "queue_size": 4,
        "queued": 3,
        "node": "mediator",
        "host": "h1",
        "fill": 0.75,
    }


def test_ls_and_info_print_the_records_json_form_plus_their_extras() -> None:
    sent = _service()
    form = sent.to_json()
    assert ls_cli.service_json(sent) == {**form, "clock_error_ns": None}
    shown = info_cli.buffer_json(sent.buffers[0])
    assert set(shown) - set(form["buffers"][0]) == {"name", "oldest", "newest"}
    assert shown["subscriptions"][0]["fill"] == 0.75
    assert shown["subscriptions"][0]["subscription_id"] == "s1"
    assert set(info_cli.service_json(sent)) == set(form) - {"buffers", "clock_ns"}


def test_info_shows_the_producers_control_counts_only_when_not_zero(capsys) -> None:
    sent = _service()
    quiet = dataclasses.replace(
        sent.buffers[0], dropped_messages=0, bad_messages=0, foreign_acks=0, collapsed_tokens=0
    )
    info_cli._print_buffer(sent, quiet)
    assert "\n  control " not in capsys.readouterr().out
    info_cli._print_buffer(sent, dataclasses.replace(quiet, foreign_acks=2, collapsed_tokens=5))
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("  control ")]
    assert lines == [
        "  control        2 acks of no live registration ignored, "
        "5 tokens withdrawn before they registered"
    ]
    info_cli._print_buffer(sent, quiet)  # the clock's last step, on the service's line
    assert "clock stepped 2x, last -20.0 s (lead +19.0 s)" in capsys.readouterr().out


def test_a_description_stays_readable_whatever_names_peers_declare() -> None:
    """Every slot of two buffers taken by tokens whose id, node and host are as long as a
    token allows, in four-byte characters: the description still fits what clients read
    (it was 5.9 MB, and ``ls``, ``info`` and a mediator's clock measurement lost the camera).
    """
    wide = "\U0001f600" * 330  # three of them fill a token's 1,024 characters
    subs = tuple(
        SubscriptionInfo(f"{i}{wide}", mode, 1, 0, None, f"n{i}{wide}", wide)
        for mode in SubscriptionMode
        for i in range(256)
    )
    buffer = dataclasses.replace(_service().buffers[0], subscriptions=subs)
    sent = dataclasses.replace(
        _service(), buffers=(buffer, dataclasses.replace(buffer, buffer="other"))
    )
    raw = encode_service_info(sent, CLOCK, instance="i", started_ns=1)
    assert len(raw) <= 2 * BUFFER_DESCRIPTION_BYTES + 64 * 1024
    got = decode_service_info(raw, 990, 1_010, service="cam")
    shown = got.buffers[1].subscriptions[-1]
    assert shown.subscription_id == "255" + wide[: SHOWN_TEXT - 3] + "\u2026"
    assert (shown.node, shown.host) == ("n255" + wide[: SHOWN_TEXT - 4] + "\u2026", shown.host)
    assert len(got.buffers[0].subscriptions) == 512


class _Name(str):
    """A name that counts the comparisons made with it."""

    compared = 0

    def __eq__(self, other: object) -> bool:
        _Name.compared += 1
        return str.__eq__(self, other)

    __hash__ = str.__hash__


def test_a_repeated_buffer_name_is_found_in_one_pass() -> None:
    # Issue 30: found with list.count per name, a peer's description of 13,707 buffers
    # naming its last one twice took 5.0 s to decode instead of 0.8 (quadratic).
    names = [_Name(f"b{i}") for i in range(4000)] + [_Name("b3999")]
    _Name.compared = 0
    assert first_repeated(names) == "b3999"
    assert _Name.compared <= 2 * len(names)  # one pass, not a count per name
    assert first_repeated(["a", "b"]) is None
