"""echo and pub as real subprocesses; ls and info name who holds each subscription."""

from __future__ import annotations

import json
import socket
import time

import pytest

from middleware import NetworkConfig, Node, SubscriptionMode, validate_metadata
from services.cli._fields import decode_metadata, typed
from services.cli.pub import KINDS, next_due
from tests.conftest import wait_until
from tests.helpers.timing import scaled
from tests.services.cli.conftest import DISCOVERY_TIMEOUT_S, Cli, LineReader, put_frame

SECOND = 1_000_000_000


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_pub_makes_schema_valid_elements_of_every_kind(kind: str) -> None:
    t = time.time_ns()
    payload, metadata = KINDS[kind](3, t, 100.0)
    validate_metadata(metadata, kind)
    got_kind, fields = decode_metadata(metadata)
    assert got_kind == kind and isinstance(payload, bytes)
    assert all(not isinstance(v, str) or not v.lstrip("-").isdigit() for v in fields.values())


def test_typed_gives_numbers_their_json_type() -> None:
    assert typed("12") == 12 and typed("-3") == -3
    assert typed("0.5") == 0.5 and typed("1e-3") == 0.001
    assert typed("true") is True and typed("1 2.5") == [1, 2.5]
    assert typed("nan") == "nan" and typed("mono8") == "mono8"


@pytest.mark.integration
def test_echo_prints_typed_fields_of_what_pub_publishes(cli: Cli, endpoint: str) -> None:
    # echo starts first and waits for pub's whole start-up (seconds on a loaded machine).
    echo = cli.start("echo", "t/x", "--json", "--count", "3", "--timeout", str(scaled(60)))
    reader = LineReader(echo)
    pub = cli.start(
        "pub", "t/x", "--kind", "frame", "--count", "3", "--rate", "20",
        "--wait-subscribers", "1", "--timeout", str(DISCOVERY_TIMEOUT_S),
        "--listen", endpoint, connect=False,
    )  # fmt: skip
    rows = [reader.json_until(lambda r: True, DISCOVERY_TIMEOUT_S * 3) for _ in range(3)]
    assert echo.wait(timeout=scaled(60)) == 0
    assert pub.wait(timeout=scaled(60)) == 0, pub.stderr.read()
    assert [r["fields"]["frame_id"] for r in rows] == [0, 1, 2]
    first = rows[0]
    assert first["kind"] == "frame" and first["fields"]["width_px"] == 64
    assert isinstance(first["fields"]["exposure_ns"], int)
    assert first["payload_bytes"] == 64 * 48 and first["payload"].startswith("3072 bytes, 64x48")


@pytest.mark.integration
def test_an_echo_started_before_pub_gets_its_first_element(cli: Cli, endpoint: str) -> None:
    """As with ``ros2 topic pub``: the echo subscribes only once the buffer is offered, and
    missed element 0 (then waited for ever for its last) unless pub was told to wait."""
    echo = cli.start("echo", "t/first", "--json", "--count", "3", "--timeout", str(scaled(60)))
    reader = LineReader(echo)
    pub = cli.start(
        "pub", "t/first", "--kind", "frame", "--count", "3", "--rate", "20",
        "--listen", endpoint, connect=False,
    )  # fmt: skip
    rows = [reader.json_until(lambda r: True, DISCOVERY_TIMEOUT_S * 3) for _ in range(3)]
    assert echo.wait(timeout=scaled(60)) == 0
    assert pub.wait(timeout=scaled(60)) == 0, pub.stderr.read()
    assert [r["fields"]["frame_id"] for r in rows] == [0, 1, 2], rows


@pytest.mark.integration
def test_pub_json_prints_one_object_per_element_then_done(cli: Cli, endpoint: str) -> None:
    pub = cli.start(
        "pub", "t/j", "--kind", "generic", "--count", "2", "--rate", "50", "--linger", "0",
        "--json", "--listen", endpoint, connect=False,
    )  # fmt: skip
    out, err = pub.communicate(timeout=scaled(60))
    assert pub.returncode == 0, err
    rows = [json.loads(line) for line in out.splitlines()]
    assert [r["event"] for r in rows] == ["published", "published", "done"], out
    # Numbered as the elements' own index field, from 0.
    assert [r["index"] for r in rows[:2]] == [0, 1] and rows[2]["published"] == 2
    assert all(isinstance(r["timestamp_ns"], int) for r in rows[:2])


@pytest.mark.integration
def test_echo_field_prints_one_value_per_element(service: Node, cli: Cli) -> None:
    images = service.offer("images", kind="frame")
    echo = cli.start("echo", "cam/images", "--field", "frame_id", "--count", "2")
    # Several fields, in the order asked (a repeated --field kept only the last one).
    both = cli.start(
        "echo", "cam/images", "--field", "width_px", "--field", "frame_id", "--count", "2"
    )

    def subscribed() -> bool:
        return len(images.subscriptions()) == 2

    wait_until(subscribed, DISCOVERY_TIMEOUT_S * 3, "echo's subscriptions")
    base = time.time_ns()
    put_frame(images, base, 7)
    put_frame(images, base + 1000, 8)
    out, err = echo.communicate(timeout=scaled(60))
    assert echo.returncode == 0, err
    assert out.split() == ["7", "8"]
    out, err = both.communicate(timeout=scaled(60))
    assert both.returncode == 0, err
    width = out.split()[0]
    assert out.splitlines() == [f"{width} 7", f"{width} 8"] and width.isdigit()


@pytest.mark.integration
def test_echo_names_a_missing_field(service: Node, cli: Cli) -> None:
    images = service.offer("images", kind="frame")
    echo = cli.start("echo", "cam/images", "--field", "frame_ide")
    wait_until(lambda: bool(images.subscriptions()), DISCOVERY_TIMEOUT_S * 3, "echo")
    put_frame(images, time.time_ns(), 1)
    _out, err = echo.communicate(timeout=scaled(60))
    assert echo.returncode == 1
    assert "no field 'frame_ide' (did you mean frame_id?)" in err, err
    assert "Traceback" not in err


@pytest.mark.integration
def test_ls_and_info_show_the_node_and_host_of_each_subscription(
    service: Node, cli: Cli, endpoint: str
) -> None:
    images = service.offer("images", kind="frame")
    with Node("watcher", NetworkConfig(connect=(endpoint,))) as watcher:
        watcher.subscribe("cam/images", queue_size=3, mode=SubscriptionMode.OBSERVE)
        assert images.wait_for_subscribers(1, timeout_s=scaled(10))
        listing, info, data = cli.run_many(
            [("ls",), ("info", "cam/images"), ("info", "cam/images", "--json")]
        )
    host = socket.gethostname()
    assert listing.returncode == 0, listing.describe()
    assert f"subscribers watcher@{host} observe 0/3" in listing.stdout, listing.stdout
    assert f"watcher@{host}" in info.stdout, info.stdout
    [sub] = data.json()["subscriptions"]
    assert (sub["node"], sub["host"]) == ("watcher", host)
    # Every line a person reads fits 100 columns.
    assert max(len(line) for line in listing.stdout.splitlines()) <= 100, listing.stdout
    # Services of this host share its clock: no offset warning however the round trip went.
    assert "CLOCK OFFSET" not in listing.stdout and "clock of" not in listing.stderr


def test_pub_keeps_a_fixed_schedule_that_a_put_s_own_time_does_not_slow() -> None:
    # 200 Hz: each put and its line took 1 ms; the next is still due 5 ms after the last.
    due, wait_s = next_due(10.0, 0.005, now=10.001)
    assert due == pytest.approx(10.005) and wait_s == pytest.approx(0.004)
    # Already past due (a slow put): at once, and the schedule stays where it was.
    due, wait_s = next_due(10.0, 0.005, now=10.008)
    assert due == pytest.approx(10.005) and wait_s == 0.0
    # More than a period behind (the process did not run): afresh from now, no burst.
    due, wait_s = next_due(10.0, 0.005, now=10.5)
    assert due == 10.5 and wait_s == 0.0


@pytest.mark.integration
def test_echo_of_a_buffer_put_once_says_why_it_printed_nothing(service: Node, cli: Cli) -> None:
    """`framegate echo camera/info` (put once, at the camera's start) printed nothing, with
    no word, as if the buffer were empty; `ros2 topic echo` of a camera_info shows it."""
    info = service.offer("info", kind="frame")
    put_frame(info, time.time_ns(), 1)
    result = cli.run("echo", "cam/info", "--duration", "1")
    assert result.returncode == 0, result.describe()
    assert result.stdout == ""
    assert result.stderr.splitlines()[-1] == (
        "note: no new element of cam/info came; echo shows what is put from now on "
        "(framegate query cam/info --last 1 shows its newest)"
    ), result.describe()
