"""Nothing missed without a count: a running bridge (real Zenoh sessions) and ROS 2 camera
publishers played with plain Zenoh as rmw_zenoh makes them. Every sequence number of a
publisher that starts after the bridge is either stored or counted as lost in transport; a
publisher that was there before the bridge is counted from its first sample seen."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator

import pytest
import zenoh

from middleware import FramegateError, NetworkConfig, Node
from services.nodes.ros2._bridge import run
from services.nodes.ros2._cdr import Codec
from services.nodes.ros2._config import Ros2Config
from tests.conftest import wait_until
from tests.helpers.timing import scaled
from tests.services.nodes.ros2.ros_graph import TOPIC, Driver, Lines, ros_router, zenoh_config

pytestmark = pytest.mark.integration


@pytest.fixture
def router() -> Iterator[tuple[zenoh.Session, str]]:
    with ros_router() as found:
        yield found


def test_a_publisher_started_after_the_bridge_has_every_number_stored_or_counted(
    router: tuple[zenoh.Session, str], endpoint: str
) -> None:
    session, ros_endpoint = router
    codec = Codec("jazzy")
    before = Driver(session, codec, "old_driver")  # there before the bridge
    lines = Lines()
    logging.getLogger("framegate.ros2").addHandler(lines)
    stop = threading.Event()
    config = Ros2Config(
        ros_connect=(ros_endpoint,),
        node_name="sequence_bridge",  # its own log line, whatever else runs in this process
        image_in=TOPIC,
        camera_info="",
        in_depth=16,
    )
    bridge = threading.Thread(target=run, args=(config, NetworkConfig(listen=(endpoint,)), stop))
    bridge.start()
    try:
        with Node(network=NetworkConfig(connect=(endpoint,))) as client:

            def counted() -> tuple[int, int]:
                try:
                    info = client.buffer_info("ros2/images", timeout_s=2.0)
                except FramegateError:
                    return (0, 0)
                return info.puts, info.skipped.get("lost-in-transport", 0)

            wait_until(
                lambda: any("graph taken by sequence_bridge" in m for m in lines.lines),
                60,
                "the graph",
            )
            before.publish(1000)  # its first sample seen: counting starts, nothing lost
            wait_until(lambda: counted()[0] >= 1, 30, "the old driver's image")
            with zenoh.open(zenoh_config("peer", ros_endpoint, listen=False)) as late:
                driver = Driver(late, codec, "new_driver")
                # Its first two samples never left (as when a new session does not know the
                # bridge's subscription yet); the next are sent at once, as a driver does.
                for sequence in range(3, 7):
                    driver.publish(sequence)
                # A loss shows only when a later sample arrives (on a loaded machine the
                # whole burst may be lost): the driver goes on, as a camera does, until
                # every number up to its last is stored or counted.
                deadline = time.monotonic() + scaled(30)
                while (c := counted())[0] + c[1] < 1 + driver.sequence:
                    assert time.monotonic() < deadline, f"{c} for {driver.sequence} samples"
                    driver.publish()
                    time.sleep(0.1)
                puts, lost = c
                driver.close()
        assert lost >= 2
        assert puts + lost == 1 + driver.sequence  # every number of the new driver
    finally:
        stop.set()
        bridge.join(10)
        logging.getLogger("framegate.ros2").removeHandler(lines)
        before.close()
    assert not bridge.is_alive()
