"""A peer's queryable that takes each query and never ends it: whoever asks one session
in particular (a subscription's producer) has its answer when that session's has come,
not at the query's timeout (a producer in its own process, real Zenoh)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import pytest
import zenoh

from middleware import NetworkConfig, Node, ServiceInfo
from middleware._wire import Keys
from tests.conftest import NodeProcess
from tests.helpers.raw_zenoh import first_seen, open_session
from tests.helpers.timing import scaled, wait_until

pytestmark = pytest.mark.integration

KEYS = Keys("framegate")
# Each call's timeout: held, a call took it whole; half of it detects a hang and leaves
# room for a machine ten times slower than the 1-2 s the calls take now.
TIMEOUT_S = scaled(60)


@dataclass
class _Scene:
    cam: NodeProcess
    client: Node
    held: list[zenoh.Query] = field(default_factory=list)
    reached: int = 0


@contextmanager
def _beside_a_held_queryable(endpoint: str, key: str) -> Iterator[_Scene]:
    """A producer process offering ``cam/images``, a client node, and a peer whose queryable
    on ``key`` takes each query and never ends it. At the end: the peer must have taken a
    query, or the test proves nothing."""
    cam = NodeProcess("cam", ["--listen", endpoint])
    try:
        assert cam.call("offer", buffer="images")["ok"]
        with (
            open_session(endpoint) as rogue,
            Node(network=NetworkConfig(connect=(endpoint,))) as client,
        ):
            scene = _Scene(cam, client)
            queryable = rogue.declare_queryable(key, zenoh.handlers.Callback(scene.held.append))
            try:
                yield scene
            finally:
                scene.reached = len(scene.held)
                queryable.undeclare()
                scene.held.clear()
    finally:
        cam.close()
    assert scene.reached, "the rogue's queryable never saw the query: the test proves nothing"


def _producer_session(scene: _Scene, t: int) -> str:
    """Subscribe, take the element ``t`` put, and name the producer's session."""
    sub = scene.client.subscribe("cam/images", queue_size=2, wait_s=scaled(10))
    assert sub.wait_registered(scaled(10))
    assert scene.cam.call("put", buffer="images", t=t)["ok"]
    sub.take(timeout_s=scaled(10))
    assert sub.producer_session is not None
    return sub.producer_session


def _live(scene: _Scene) -> None:
    wait_until(lambda: "cam" in scene.client.live_services(), 60, "the service's token")


def _timed_answer(ask: Callable[[Callable[[Any], None]], None]) -> tuple[Any, float]:
    """Start an asynchronous ask with a callback; its answer and how long it took (asked
    through ``first_seen``: a call made before the peer's queryable was known to the client
    never met it, 1 run in ~10 under load)."""
    answers: list[tuple[Any, float]] = []
    began = time.monotonic()
    ask(lambda answer: answers.append((answer, time.monotonic() - began)))
    answer, took_s = wait_until(lambda: answers, 60, "the answer")[0]
    return answer, took_s


def test_a_clock_sample_of_the_producer_comes_when_its_answer_does(endpoint: str) -> None:
    """``ask_service_info(session=)`` (a mediator's clock samples of camera and gyro)
    delivered when the query ended: beside a peer holding ``@info/camera`` queries open,
    every sample came at the timeout (1 s), and a restarted mediator skipped 17 frames
    clock-unmeasured (none without the peer). Now it comes with the producer's answer."""
    with _beside_a_held_queryable(endpoint, KEYS.info("cam")) as scene:
        session = _producer_session(scene, 1)
        (info, took_s), _ = first_seen(
            lambda: _timed_answer(
                lambda done: scene.client.ask_service_info(
                    "cam", done, timeout_s=TIMEOUT_S, session=session
                )
            ),
            scene.held,
            "a clock sample's query",
        )
        began = time.monotonic()
        scene.client.service_info("cam", session=session, timeout_s=TIMEOUT_S)
        waited_s = time.monotonic() - began  # the same, waiting (``info``, ``ls``)
    assert isinstance(info, ServiceInfo) and info.service == "cam"
    # Before: TIMEOUT_S each. Hang detectors, not speed bounds.
    assert took_s < TIMEOUT_S / 2, f"{took_s:.1f} s"
    assert waited_s < TIMEOUT_S / 2, f"{waited_s:.1f} s"


def test_a_range_asked_of_the_producer_comes_when_its_answer_does(endpoint: str) -> None:
    """``ask_query(session=)`` (a restarted mediator's look-up of the frames it missed)
    delivered when the query ended: beside a peer holding the buffer's data queries open,
    at the query's timeout. Now with the producer's end mark."""
    with _beside_a_held_queryable(endpoint, KEYS.data("cam", "images")) as scene:
        session = _producer_session(scene, 5)
        (found, took_s), _ = first_seen(
            lambda: _timed_answer(
                lambda done: scene.client.ask_query(
                    "cam/images", done, time_range="[1..10]", timeout_s=TIMEOUT_S, session=session
                )
            ),
            scene.held,
            "a range query",
        )
    assert isinstance(found, list) and [e.timestamp_ns for e in found] == [5], found
    assert took_s < TIMEOUT_S / 2, f"{took_s:.1f} s"  # before: TIMEOUT_S; a hang detector


def test_a_query_naming_no_session_comes_with_the_owners_answer(endpoint: str) -> None:
    """``query`` and ``latest`` without ``session`` (``framegate query``, the backfill of
    ``echo`` and ``record``, ``view``'s frame look-up) waited for every queryable on the
    key: beside a peer holding the buffer's data queries open, each took its timeout. Now
    the session that answers as the service is asked for, and its end mark ends each."""
    with _beside_a_held_queryable(endpoint, KEYS.data("cam", "images")) as scene:
        assert scene.cam.call("put", buffer="images", t=5)["ok"]
        _live(scene)
        client = scene.client
        found, query_s = first_seen(
            lambda: client.query("cam/images", last=1, timeout_s=TIMEOUT_S), scene.held, "a query"
        )
        began = time.monotonic()
        newest = client.latest("cam/images", 1, timeout_s=TIMEOUT_S)
        latest_s = time.monotonic() - began
    assert [e.timestamp_ns for e in found] == [5], found
    assert [e.timestamp_ns for e in newest] == [5], newest
    # Before: TIMEOUT_S each. Hang detectors, not speed bounds.
    assert query_s < TIMEOUT_S / 2, f"{query_s:.1f} s"
    assert latest_s < TIMEOUT_S / 2, f"{latest_s:.1f} s"


def test_the_services_listed_come_when_every_live_one_has_answered(endpoint: str) -> None:
    """``services()`` (``ls``, ``launch --status``, ``view``) waited for every queryable on
    ``@info/*``: beside a peer holding those queries open, it took its timeout. Now it ends
    once each live service (holding its token) has answered, and a moment after."""
    with _beside_a_held_queryable(endpoint, KEYS.info("*")) as scene:
        _live(scene)
        client = scene.client
        listed, took_s = first_seen(
            lambda: client.services(timeout_s=TIMEOUT_S), scene.held, "a query"
        )
    assert [s.service for s in listed] == ["cam"], listed
    assert took_s < TIMEOUT_S / 2, f"{took_s:.1f} s"  # before: TIMEOUT_S; a hang detector


def test_a_description_asked_of_no_session_comes_with_the_first_answer(endpoint: str) -> None:
    """``service_info`` without ``session`` (``framegate info``, and the look-up of the
    service before ``query``, ``echo`` and ``record``) waited for every queryable on
    ``@info/<service>``: beside a peer holding those queries open, it took its timeout."""
    with _beside_a_held_queryable(endpoint, KEYS.info("cam")) as scene:
        _live(scene)
        client = scene.client
        info, took_s = first_seen(
            lambda: client.service_info("cam", timeout_s=TIMEOUT_S, unambiguous=True),
            scene.held,
            "a query",
        )
    assert info.service == "cam" and [b.buffer for b in info.buffers] == ["images"]
    assert took_s < TIMEOUT_S / 2, f"{took_s:.1f} s"  # before: TIMEOUT_S; a hang detector
