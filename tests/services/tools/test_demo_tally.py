"""The demo's marker tally beside a peer that answers its queries (any session may)."""

from __future__ import annotations

import time

import pytest
import zenoh

from middleware import DataObject, NetworkConfig, Node
from middleware._service import encode_answer_end
from middleware._wire import encode_element_attachment
from services.lib.markers import BOARD_MARKERS
from services.lib.messages import detections_metadata
from services.tools.demo import MarkerTally
from tests.conftest import wait_until
from tests.helpers.raw_zenoh import open_session
from tests.helpers.timing import scaled

pytestmark = pytest.mark.integration

HOUR_NS = 3600 * 1_000_000_000


def _detections(t: int, markers: list[int]) -> bytes:
    return detections_metadata(t, 1, "det", 0, [(m, [0.0] * 8) for m in markers])


def test_a_peers_element_an_hour_ahead_does_not_stop_the_tally(
    listen_net: NetworkConfig, connect_net: NetworkConfig, endpoint: str
) -> None:
    """The tally asked for everything after the newest detection it had counted: a peer's
    element stamped an hour ahead became that newest, and no later detection was counted
    (the demo's recognitions and gain stopped)."""
    marker = BOARD_MARKERS[0]
    with Node("det", listen_net) as service, Node(network=connect_net) as client:
        detections = service.offer("detections", kind="detections")
        t = time.time_ns()
        detections.put(t, b"", _detections(t, [marker.marker_id]))
        with open_session(endpoint) as rogue:
            asked: list[int] = []

            def reply(query: zenoh.Query) -> None:
                with query:
                    asked.append(1)
                    ahead = time.time_ns() + HOUR_NS
                    forged = DataObject(ahead, b"", _detections(ahead, []))
                    attachment = encode_element_attachment(forged)
                    query.reply(query.key_expr, b"", attachment=attachment)
                    query.reply(query.key_expr, b"", attachment=encode_answer_end(1))

            key = "framegate/det/detections"
            queryable = rogue.declare_queryable(key, zenoh.handlers.Callback(reply))
            try:
                tally = MarkerTally("det")
                wait_until(
                    lambda: (tally.update(client), asked)[1] and tally.total == 1,
                    scaled(30),
                    "the first detection counted, with the peer answering",
                )
                t = time.time_ns()
                detections.put(t, b"", _detections(t, [marker.marker_id]))

                def counted() -> bool:
                    tally.update(client)
                    return tally.total == 2

                wait_until(counted, scaled(30), "the second detection counted")
            finally:
                queryable.undeclare()
    assert tally.seen[marker.name] == 2
