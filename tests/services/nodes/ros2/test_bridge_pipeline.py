"""ROS 2 in, ROS 2 out, with no ROS 2: a plain-Zenoh camera driver and IMU (publishing as
rmw_zenoh does) feed ``ros2`` bridge → mediator → detector → bridge, and a plain-Zenoh ROS 2
subscriber (this test) receives the filtered images, the detections and the verdicts,
decodes them with rosbags and checks pixels and stamps byte for byte."""

from __future__ import annotations

import json
import queue
import re
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
import zenoh

from services.nodes.ros2._cdr import DETECTIONS, IMAGE, STRING, Codec
from services.nodes.ros2._rmw import (
    Attachment,
    EntityKind,
    History,
    NodeIdentity,
    Qos,
    data_key,
    gid,
    type_hash,
)
from tests.conftest import REPO, child_env, free_port, wait_until
from tests.helpers.timing import scaled
from tests.services.nodes.pipeline import Pipeline

pytestmark = [pytest.mark.integration, pytest.mark.slow]

FRAMES = 8
OUT = {
    "/framegate/image": IMAGE,
    "/framegate/detections": DETECTIONS,
    "/framegate/verdicts": STRING,
}


class Driver:
    """The fake camera driver + IMU process (tests/services/nodes/ros2/fake_ros.py)."""

    def __init__(self, params: dict[str, Any]) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "tests.services.nodes.ros2.fake_ros", json.dumps(params)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=REPO,
            env=child_env(),
        )
        self.lines: queue.Queue[dict[str, Any]] = queue.Queue()
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if line.startswith("{"):
                self.lines.put(json.loads(line))

    def next(self, timeout_s: float) -> dict[str, Any]:
        try:
            return self.lines.get(timeout=scaled(timeout_s))
        except queue.Empty:
            assert self.proc.stderr is not None
            raise AssertionError(f"fake driver silent; exit {self.proc.poll()}") from None

    def send(self, line: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def close(self) -> None:
        if self.proc.poll() is None:
            assert self.proc.stdin is not None
            self.proc.stdin.close()
            try:
                self.proc.wait(timeout=scaled(10))
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


class Listener:
    """A ROS 2 node with three subscriptions, as rmw_zenoh declares them, in plain Zenoh."""

    def __init__(self, endpoint: str, codec: Codec) -> None:
        conf = zenoh.Config()
        for key, value in {
            "mode": "peer",
            "connect/endpoints": [endpoint],
            "listen/endpoints": ["tcp/127.0.0.1:0"],
            "scouting/multicast/enabled": False,
        }.items():
            conf.insert_json5(key, json.dumps(value))
        self.session = zenoh.open(conf)
        self.received: dict[str, list[tuple[bytes, bytes | None]]] = {t: [] for t in OUT}
        node = NodeIdentity(0, str(self.session.info.zid()), "listener")
        self._declared: list[Any] = [self.session.liveliness().declare_token(node.node_token())]
        for entity_id, (topic, ros_type) in enumerate(OUT.items(), start=1):
            hash_chunk = type_hash(codec.rihs01(ros_type), "jazzy")
            token = node.endpoint_token(
                entity_id, EntityKind.SUBSCRIPTION, topic, ros_type, hash_chunk, Qos()
            )
            self._declared.append(self.session.liveliness().declare_token(token))

            def keep(sample: zenoh.Sample, topic: str = topic) -> None:
                attachment = sample.attachment
                self.received[topic].append(
                    (sample.payload.to_bytes(), attachment.to_bytes() if attachment else None)
                )

            self._declared.append(
                self.session.declare_subscriber(
                    data_key(0, topic, ros_type, hash_chunk), zenoh.handlers.Callback(keep)
                )
            )

    def tokens(self) -> list[str]:
        return [str(r.ok.key_expr) for r in self.session.liveliness().get("@ros2_lv/0/**") if r.ok]

    def close(self) -> None:
        for entity in reversed(self._declared):
            entity.undeclare()
        self.session.close()


@pytest.fixture
def ros_side(tmp_path: Path) -> Iterator[tuple[Driver, str]]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    driver = Driver(
        {
            "listen": endpoint,
            "seed": 3,
            "frames": FRAMES,
            "rate": 0.5,
            "frames_path": str(tmp_path / "frames.npy"),
            "camera_path": str(tmp_path / "camera.xml"),
        }
    )
    yield driver, endpoint
    driver.close()


def _deploy(endpoint: str, camera_xml: Path) -> str:
    bridge = {
        "ros_connect": endpoint,
        "image_in": "/camera/image_raw",
        "imu_in": "/imu/data",
        "exposure_ms": 60,
        "camera_xml": str(camera_xml),
        "image_out": ["mediator/images=/framegate/image"],
        "detections_out": ["detector/detections=/framegate/detections"],
        "verdicts_out": ["mediator/decisions=/framegate/verdicts"],
        # Keep-all reliable: the publishers block rather than drop, ROS 2's lossless QoS.
        # With keep-last Zenoh may drop a 768 kB image on a busy machine, as rmw_zenoh's does,
        # and "every accepted image reaches ROS 2" would not be a promise.
        "out_depth": 0,
    }
    services = {
        "ros2": {"args": bridge},
        "mediator": {"args": {"camera": "ros2/images", "gyro": "ros2/rates", "gyro_wait_ms": 400}},
        "detector": {"args": {"input": "mediator/images"}},
    }
    return yaml.safe_dump({"version": 1, "services": services})


def test_ros2_camera_and_imu_through_the_pipeline_back_to_ros2(
    tmp_path: Path, ros_side: tuple[Driver, str]
) -> None:
    driver, endpoint = ros_side
    assert driver.next(120).get("ready")
    codec = Codec("jazzy")
    pipe = Pipeline(tmp_path, _deploy(endpoint, tmp_path / "camera.xml"))
    listener = Listener(endpoint, codec)
    try:
        wait_until(
            lambda: (
                pipe.subscriber_count("ros2/images") >= 1
                and pipe.subscriber_count("ros2/rates") >= 1
                and pipe.subscriber_count("mediator/images") >= 2
                and pipe.subscriber_count("detector/detections") >= 1
                and pipe.subscriber_count("mediator/decisions") >= 1
            ),
            90,
            lambda: "bridge, mediator and detector to be up\n" + pipe.log(),
        )
        tokens = wait_until(
            lambda: (
                (t := listener.tokens()) and sum("/framegate_bridge" in k for k in t) >= 6 and t
            ),
            20,
            "the bridge's liveliness tokens",
        )
        driver.send("go")
        sent: dict[int, int] = {}
        while True:
            line = driver.next(60)
            if "done" in line:
                break
            sent[int(line["stamp_ns"])] = int(line["index"])
        assert len(sent) == FRAMES

        def image_stamps() -> set[int]:
            return {
                (m := codec.decode(p, IMAGE)).header.stamp.sec * 10**9 + m.header.stamp.nanosec
                for p, _ in list(listener.received["/framegate/image"])
            }

        def accepted_stamps() -> set[int]:
            return {
                v["stamp_ns"]
                for p, _ in list(listener.received["/framegate/verdicts"])
                if (v := json.loads(codec.decode(p, STRING).data))["accepted"]
            }

        def stored() -> int | None:
            # Every image the driver sent is stored, or refused or skipped and counted (a
            # busy machine may overflow the in-queue or the mediator's queue): the frames
            # the mediator must decide.
            info = pipe.info("ros2/images")
            settled = info.puts + info.refused + sum(info.skipped.values()) >= FRAMES
            return info.puts if settled else None

        def missing() -> str:
            return (
                f"stored {stored()}, verdicts {len(listener.received['/framegate/verdicts'])}, "
                f"detections {len(listener.received['/framegate/detections'])}, accepted "
                f"images not received {sorted(accepted_stamps() - image_stamps())}\n"
            )

        def lapsed(buffer: str) -> int:
            # A bridge starved past its lease (load 10 on 2 cores) lapses; what was stored
            # meanwhile is never published, and it says how many (an observer's counted loss).
            said = re.findall(
                rf"\[ros2 *\] .*subscription to {buffer} had lapsed: (\d+)", pipe.log()
            )
            return sum(int(n) for n in said)

        # Verdicts and images leave the bridge on two outputs, so an accepted frame's image
        # (768 kB) may reach ROS 2 after its verdict: wait for both.
        puts = wait_until(
            lambda: (
                (n := stored())
                and len(listener.received["/framegate/verdicts"])
                >= n - lapsed("mediator/decisions")
                and listener.received["/framegate/detections"]
                and len(accepted_stamps() - image_stamps()) <= lapsed("mediator/images")
                and n
            ),
            120,  # eight frames through bridge, mediator and detector: 30 s missed at load 10
            lambda: (
                "a verdict per stored frame, detections and every accepted image: "
                + missing()
                + pipe.log()
            ),
        )
        frames = np.load(tmp_path / "frames.npy")

        # The ROS graph sees the bridge as a node with its subscriptions and publishers.
        bridge = [k for k in tokens if "/framegate_bridge" in k]
        assert any(k.endswith("/NN/%/%/framegate_bridge") for k in bridge), bridge
        image_hash = codec.rihs01(IMAGE)
        assert any(
            f"/MS/%/%/framegate_bridge/%camera%image_raw/sensor_msgs::msg::dds_::Image_/"
            f"{image_hash}/2::,5:,:,:,," in k
            for k in bridge
        ), bridge
        out_tokens = {k.split("/")[9]: k for k in bridge if "/MP/" in k}
        assert set(out_tokens) == {
            "%framegate%image",
            "%framegate%detections",
            "%framegate%verdicts",
        }
        keep_all = Qos(depth=0, history=History.KEEP_ALL).keyexpr()
        assert all(k.endswith("/" + keep_all) for k in out_tokens.values())

        # Filtered images: every pixel and stamp as the driver sent them; rmw_zenoh attachments.
        images = listener.received["/framegate/image"]
        assert images, "no filtered image reached the ROS 2 subscriber\n" + pipe.log()
        sequence = []
        for payload, attachment in images:
            message = codec.decode(payload, IMAGE)
            stamp = message.header.stamp.sec * 10**9 + message.header.stamp.nanosec
            assert stamp in sent, stamp
            assert (message.width, message.height, message.encoding, message.step) == (
                1024,
                768,
                "mono8",
                1024,
            )
            assert message.data.tobytes() == frames[sent[stamp]].tobytes()
            assert attachment is not None
            decoded = Attachment.decode(attachment)
            assert decoded.source_gid == gid(out_tokens["%framegate%image"])
            sequence.append(decoded.sequence_number)
        assert sequence == sorted(sequence) and len(set(sequence)) == len(sequence)

        # Detections: the markers the detector found, stamped like their frames.
        found = 0
        for payload, _ in listener.received["/framegate/detections"]:
            message = codec.decode(payload, DETECTIONS)
            stamp = message.header.stamp.sec * 10**9 + message.header.stamp.nanosec
            assert stamp in sent
            for detection in message.detections:
                box = detection.bbox
                assert 0 <= box.center.position.x <= 1024 and 0 <= box.center.position.y <= 768
                assert detection.results[0].hypothesis.class_id == detection.id
                found += 1
        assert found >= 1

        # Verdicts: one JSON line per stored frame; the accepted ones are the images published.
        verdicts = [
            json.loads(codec.decode(p, STRING).data)
            for p, _ in listener.received["/framegate/verdicts"]
        ]
        stamps = [v["stamp_ns"] for v in verdicts]
        assert len(stamps) == len(set(stamps)) and set(stamps) <= set(sent), stamps
        assert puts - lapsed("mediator/decisions") <= len(stamps) <= puts, (stamps, puts)
        accepted = {v["stamp_ns"] for v in verdicts if v["accepted"]}
        if lapsed("mediator/decisions") or lapsed("mediator/images"):
            assert len(image_stamps() ^ accepted) <= lapsed("mediator/decisions") + lapsed(
                "mediator/images"
            )
        else:
            assert image_stamps() == accepted

        # framegate's side: every image stored; what a busy machine did not store, counted.
        info = pipe.info("ros2/images")
        assert info.puts + info.refused + sum(info.skipped.values()) == FRAMES, info
        assert set(info.skipped) <= {"in-queue-full", "lost-in-transport"}, info.skipped
        assert info.puts >= FRAMES // 2, info
    finally:
        listener.close()
        pipe.close()
