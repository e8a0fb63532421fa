"""A peer's queryable that takes each query and never ends it: whoever asks one session
in particular (a subscription's producer) has its answer when that session's has come,
not at the query's timeout (a producer in its own process, real Zenoh)."""

from __future__ import annotations

import time

import pytest
import zenoh

from middleware import NetworkConfig, Node, ServiceInfo
from middleware._wire import Keys
from tests.conftest import NodeProcess
from tests.helpers.raw_zenoh import first_seen, open_session
from tests.helpers.timing import scaled, wait_until

pytestmark = pytest.mark.integration


def test_a_clock_sample_of_the_producer_comes_when_its_answer_does(endpoint: str) -> None:
    """``ask_service_info(session=)`` (a mediator's clock samples of camera and gyro)
    delivered when the query ended: beside a peer holding ``@info/camera`` queries open,
    every sample came at the timeout (1 s), and a restarted mediator skipped 17 frames
    clock-unmeasured (none without the peer). Now it comes with the producer's answer."""
    cam = NodeProcess("cam", ["--listen", endpoint])
    held: list[zenoh.Query] = []
    try:
        assert cam.call("offer", buffer="images")["ok"]
        with (
            open_session(endpoint) as rogue,
            Node(network=NetworkConfig(connect=(endpoint,))) as client,
        ):
            queryable = rogue.declare_queryable(
                Keys("framegate").info("cam"), zenoh.handlers.Callback(held.append)
            )
            try:
                sub = client.subscribe("cam/images", queue_size=2, wait_s=scaled(10))
                assert sub.wait_registered(scaled(10))
                assert cam.call("put", buffer="images", t=1)["ok"]
                sub.take(timeout_s=scaled(10))
                session = sub.producer_session
                assert session is not None
                timeout_s = scaled(20)
                answers: list[tuple[ServiceInfo | None, float]] = []
                began = time.monotonic()
                client.ask_service_info(
                    "cam",
                    lambda info: answers.append((info, time.monotonic() - began)),
                    timeout_s=timeout_s,
                    session=session,
                )
                (info, took_s), *_ = wait_until(lambda: answers, 60, "the answer")
                began = time.monotonic()
                client.service_info("cam", session=session, timeout_s=timeout_s)
                waited_s = time.monotonic() - began  # the same, waiting (``info``, ``ls``)
                reached = len(held)
            finally:
                queryable.undeclare()
                held.clear()
    finally:
        cam.close()
    assert reached, "the rogue's queryable never saw the query: the test proves nothing"
    assert isinstance(info, ServiceInfo) and info.service == "cam"
    # Before: timeout_s each. Hang detectors, not speed bounds.
    assert took_s < timeout_s / 2, f"{took_s:.1f} s"
    assert waited_s < timeout_s / 2, f"{waited_s:.1f} s"


def test_a_range_asked_of_the_producer_comes_when_its_answer_does(endpoint: str) -> None:
    """``ask_query(session=)`` (a restarted mediator's look-up of the frames it missed)
    delivered when the query ended: beside a peer holding the buffer's data queries open,
    at the query's timeout. Now with the producer's end mark."""
    cam = NodeProcess("cam", ["--listen", endpoint])
    held: list[zenoh.Query] = []
    try:
        assert cam.call("offer", buffer="images")["ok"]
        with (
            open_session(endpoint) as rogue,
            Node(network=NetworkConfig(connect=(endpoint,))) as client,
        ):
            queryable = rogue.declare_queryable(
                Keys("framegate").data("cam", "images"), zenoh.handlers.Callback(held.append)
            )
            try:
                sub = client.subscribe("cam/images", queue_size=2, wait_s=scaled(10))
                assert sub.wait_registered(scaled(10))
                assert cam.call("put", buffer="images", t=5)["ok"]
                sub.take(timeout_s=scaled(10))
                timeout_s = scaled(20)
                answers: list[tuple[object, float]] = []
                began = time.monotonic()
                client.ask_query(
                    "cam/images",
                    lambda found: answers.append((found, time.monotonic() - began)),
                    time_range="[1..10]",
                    timeout_s=timeout_s,
                    session=sub.producer_session,
                )
                (found, took_s), *_ = wait_until(lambda: answers, 60, "the answer")
                reached = len(held)
            finally:
                queryable.undeclare()
                held.clear()
    finally:
        cam.close()
    assert reached, "the rogue's queryable never saw the query: the test proves nothing"
    assert isinstance(found, list) and [e.timestamp_ns for e in found] == [5], found
    assert took_s < timeout_s / 2, f"{took_s:.1f} s"  # before: timeout_s; a hang detector


def test_a_query_naming_no_session_comes_with_the_owners_answer(endpoint: str) -> None:
    """``query`` and ``latest`` without ``session`` (``framegate query``, the backfill of
    ``echo`` and ``record``, ``view``'s frame look-up) waited for every queryable on the
    key: beside a peer holding the buffer's data queries open, each took its timeout. Now
    the session that answers as the service is asked for, and its end mark ends each."""
    cam = NodeProcess("cam", ["--listen", endpoint])
    held: list[zenoh.Query] = []
    try:
        assert cam.call("offer", buffer="images")["ok"]
        assert cam.call("put", buffer="images", t=5)["ok"]
        with (
            open_session(endpoint) as rogue,
            Node(network=NetworkConfig(connect=(endpoint,))) as client,
        ):
            queryable = rogue.declare_queryable(
                Keys("framegate").data("cam", "images"), zenoh.handlers.Callback(held.append)
            )
            try:
                wait_until(lambda: "cam" in client.live_services(), 60, "the service's token")
                timeout_s = scaled(20)
                found, query_s = first_seen(
                    lambda: client.query("cam/images", last=1, timeout_s=timeout_s), held, "a query"
                )
                began = time.monotonic()
                newest = client.latest("cam/images", 1, timeout_s=timeout_s)
                latest_s = time.monotonic() - began
                reached = len(held)
            finally:
                queryable.undeclare()
                held.clear()
    finally:
        cam.close()
    assert reached, "the rogue's queryable never saw the query: the test proves nothing"
    assert [e.timestamp_ns for e in found] == [5], found
    assert [e.timestamp_ns for e in newest] == [5], newest
    # Before: timeout_s each. Hang detectors, not speed bounds.
    assert query_s < timeout_s / 2, f"{query_s:.1f} s"
    assert latest_s < timeout_s / 2, f"{latest_s:.1f} s"


def test_the_services_listed_come_when_every_live_one_has_answered(endpoint: str) -> None:
    """``services()`` (``ls``, ``launch --status``, ``view``) waited for every queryable on
    ``@info/*``: beside a peer holding those queries open, it took its timeout. Now it ends
    once each live service (holding its token) has answered, and a moment after."""
    cam = NodeProcess("cam", ["--listen", endpoint])
    held: list[zenoh.Query] = []
    try:
        assert cam.call("offer", buffer="images")["ok"]
        with (
            open_session(endpoint) as rogue,
            Node(network=NetworkConfig(connect=(endpoint,))) as client,
        ):
            queryable = rogue.declare_queryable(
                Keys("framegate").info("*"), zenoh.handlers.Callback(held.append)
            )
            try:
                wait_until(lambda: "cam" in client.live_services(), 60, "the service's token")
                timeout_s = scaled(20)
                listed, took_s = first_seen(
                    lambda: client.services(timeout_s=timeout_s), held, "a query"
                )
                reached = len(held)
            finally:
                queryable.undeclare()
                held.clear()
    finally:
        cam.close()
    assert reached, "the rogue's queryable never saw the query: the test proves nothing"
    assert [s.service for s in listed] == ["cam"], listed
    assert took_s < timeout_s / 2, f"{took_s:.1f} s"  # before: timeout_s; a hang detector


def test_a_description_asked_of_no_session_comes_with_the_first_answer(endpoint: str) -> None:
    """``service_info`` without ``session`` (``framegate info``, and the look-up of the
    service before ``query``, ``echo`` and ``record``) waited for every queryable on
    ``@info/<service>``: beside a peer holding those queries open, it took its timeout."""
    cam = NodeProcess("cam", ["--listen", endpoint])
    held: list[zenoh.Query] = []
    try:
        assert cam.call("offer", buffer="images")["ok"]
        with (
            open_session(endpoint) as rogue,
            Node(network=NetworkConfig(connect=(endpoint,))) as client,
        ):
            queryable = rogue.declare_queryable(
                Keys("framegate").info("cam"), zenoh.handlers.Callback(held.append)
            )
            try:
                wait_until(lambda: "cam" in client.live_services(), 60, "the service's token")
                timeout_s = scaled(20)
                info, took_s = first_seen(
                    lambda: client.service_info("cam", timeout_s=timeout_s, unambiguous=True),
                    held,
                    "a query",
                )
                reached = len(held)
            finally:
                queryable.undeclare()
                held.clear()
    finally:
        cam.close()
    assert reached, "the rogue's queryable never saw the query: the test proves nothing"
    assert info.service == "cam" and [b.buffer for b in info.buffers] == ["images"]
    assert took_s < timeout_s / 2, f"{took_s:.1f} s"  # before: timeout_s; a hang detector
