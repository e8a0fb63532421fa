"""The camera description from ROS 2 itself, end to end: a plain-Zenoh camera driver that
publishes CameraInfo beside its images (or once, latched) and the robot's /tf_static (one
broadcaster before the bridge starts, one after), a bridge without --camera-xml and its
mediator, beside a bridge given the equivalent --camera-xml and its mediator (on the first
bridge's gyro buffer), all real processes. Both mediators must estimate the same blur for
every frame; a sequence number the driver skips is counted as lost in transport."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import pytest
import yaml

from services.lib.camera_model import CameraModel
from services.lib.messages import DecisionRecord
from tests.conftest import free_port, wait_until
from tests.helpers.timing import answered, scaled
from tests.services.nodes.pipeline import Pipeline
from tests.services.nodes.ros2.test_bridge_pipeline import Driver

pytestmark = [pytest.mark.integration, pytest.mark.slow]

# About 1 s of the approach at a quarter speed (4.3 s): a mediator starved past its lease
# (2.1 s at load 10 on 2 cores, seen in CI) misses the frames stored meanwhile and records
# them without blur; 8 frames at half speed were all lost that way once. Blur is compared on
# at least COMMON frames.
FRAMES = 16
RATE = 0.25
COMMON = 4


def _deploy(endpoint: str, camera_xml: Path) -> str:
    # Deep in-queues: on a loaded machine a full IMU queue (counted) leaves frames uncovered.
    common = {
        "ros_connect": endpoint,
        "image_in": "/camera/image_raw",
        "exposure_ms": 60,
        "in_depth": 256,
    }
    services: dict[str, Any] = {
        "ros2": {"args": {**common, "imu_in": "/imu/data"}},
        "ros2xml": {
            "type": "ros2",
            "args": {**common, "node_name": "framegate_bridge_xml", "camera_xml": str(camera_xml)},
        },
    }
    # Both mediators read the same gyro buffer: the camera description is the one difference.
    for mediator, bridge in (("mediator", "ros2"), ("mediatorxml", "ros2xml")):
        services[mediator] = {
            "type": "mediator",
            # A frame waits for late gyro samples as long as a loaded machine needs: with
            # 400 ms, at load 20-27 one mediator decided frames 1-5 without gyro (no blur)
            # while the other, on the same gyro buffer, covered them.
            "args": {
                "camera": f"{bridge}/images",
                "gyro": "ros2/rates",
                "gyro_wait_ms": round(scaled(5000)),
            },
        }
    return yaml.safe_dump({"version": 1, "services": services})


def _blurs(pipe: Pipeline, buffer: str) -> dict[int, float]:
    # Asked again while the mediator does not answer: a live one may have lost its lease.
    elements = answered(lambda: pipe.node.query(buffer), buffer)
    records = [DecisionRecord.from_metadata(e.metadata) for e in elements]
    return {r.frame_timestamp_ns: r.blur_px for r in records if r.blur_px is not None}


@pytest.mark.parametrize("latched_info", [False, True], ids=["info-per-image", "info-latched"])
def test_blur_from_camera_info_and_tf_static_equals_blur_from_the_camera_xml(
    tmp_path: Path, latched_info: bool
) -> None:
    """``info-latched``: the driver published its CameraInfo once, transient local, before
    the bridge started (a plain subscriber would never hear it)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    driver = Driver(
        {
            "listen": endpoint,
            "seed": 3,
            "frames": FRAMES,
            "rate": RATE,
            "frames_path": str(tmp_path / "frames.npy"),
            "camera_path": str(tmp_path / "sim.xml"),
            "camera_info": True,
            "latched_info": latched_info,
            "skip_sequence": [4],
        }
    )
    pipe = None
    try:
        assert driver.next(120).get("ready")
        # The XML equivalent of what the driver says: ROS 2 stamps share one clock.
        sim = CameraModel.from_xml((tmp_path / "sim.xml").read_bytes())
        xml = tmp_path / "camera.xml"
        xml.write_bytes(dataclasses.replace(sim, gyro_time_offset_ns=0).to_xml())
        pipe = Pipeline(tmp_path, _deploy(endpoint, xml))
        wait_until(
            lambda: (
                pipe.subscriber_count("ros2/images") >= 1
                and pipe.subscriber_count("ros2xml/images") >= 1
                and pipe.subscriber_count("ros2/rates") >= 2
            ),
            90,
            lambda: "bridges and mediators to be up\n" + pipe.log(),
        )
        driver.send("go")
        while "done" not in driver.next(60):
            pass

        def both() -> tuple[dict[int, float], dict[int, float]] | None:
            ros, xml_ = _blurs(pipe, "mediator/decisions"), _blurs(pipe, "mediatorxml/decisions")
            # Frames the gyro does not cover (it may lag under load) have no blur in either.
            return (ros, xml_) if len(set(ros) & set(xml_)) >= COMMON else None

        ros, from_xml = wait_until(
            both, 60, lambda: "blur estimates from both mediators\n" + pipe.log()
        )
        common = sorted(set(ros) & set(from_xml))
        assert len(common) >= COMMON, (ros, from_xml)
        for stamp in common:
            assert ros[stamp] == pytest.approx(from_xml[stamp], rel=1e-4, abs=1e-6), stamp
        assert max(ros.values()) > 0.1  # real motion blur, not a comparison of zeros
        log = pipe.log()
        assert "camera description from /camera/camera_info and /tf_static" in log, log
        # The one sequence number the driver skipped (and any real loss) is counted.
        skipped = pipe.info("ros2/images").skipped
        assert skipped.get("lost-in-transport", 0) >= 1, skipped
        assert "camera-info-mismatch" not in skipped
    finally:
        if pipe is not None:
            pipe.close()
        driver.close()
