"""A ROS 2 camera driver and IMU played with plain Zenoh, publishing as rmw_zenoh does.

``python -m tests.services.nodes.ros2.fake_ros PARAMS_JSON`` opens a Zenoh *router* on
``listen`` (standing in for ``rmw_zenohd``), declares a ``camera_driver`` node with a
publisher on ``/camera/image_raw`` (sensor_msgs/msg/Image) and one on ``/imu/data``
(sensor_msgs/msg/Imu), each with its liveliness token, renders ``frames`` simulator frames
(seed ``seed``), saves them to ``frames_path`` (.npy) and the camera to ``camera_path``,
prints ``{"ready": true}``, waits for a line on stdin (the test's "go"), then plays them at
``rate`` x real time: the IMU samples as their stamps pass, each image at its exposure end
with ``header.stamp`` = exposure start. Every sample carries rmw_zenoh's attachment. One
JSON line per published image (``index``, ``stamp_ns``), then ``{"done": n}``; it then
keeps the router up until stdin closes.

With ``camera_info`` the driver also describes its camera as ROS 2 does: a
``sensor_msgs/msg/CameraInfo`` on ``/camera/camera_info`` before each image, images stamped
in ``camera_optical_frame`` and IMU samples in ``imu_link`` on the camera's clock (a ROS 2
system has one clock), and ``/tf_static`` from two static broadcasters (rmw_zenoh's
transient-local publishers: an advanced publisher with a cache and publisher detection):
``robot`` publishes a two-link chain before ``ready`` (a bridge started later must fetch it
from the cache), ``imu`` starts at ``go`` (a late publisher). ``skip_sequence`` lists image
indices before which the image publisher's sequence number jumps by one (a lost sample).
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from typing import Any

import numpy as np
import zenoh
import zenoh.ext

from services.lib.sim import Scenario, ScenarioConfig
from services.nodes.ros2._camera_info import CAMERA_INFO, TF_MESSAGE
from services.nodes.ros2._cdr import IMAGE, IMU, Codec
from services.nodes.ros2._rmw import (
    Attachment,
    Durability,
    EntityKind,
    NodeIdentity,
    Qos,
    data_key,
    gid,
    type_hash,
)
from tests.services.nodes.ros2.ros_camera import IMAGE_FRAME, IMU_FRAME, camera_info, tf_static


def _emit(**fields: Any) -> None:
    print(json.dumps(fields), flush=True)


def main(params: dict[str, Any]) -> None:
    scenario = Scenario(ScenarioConfig(seed=int(params["seed"])))
    count = int(params["frames"])
    images = np.stack([np.asarray(scenario.render(i), dtype=np.uint8) for i in range(count)])
    np.save(params["frames_path"], images)
    with open(params["camera_path"], "wb") as out:
        out.write(scenario.camera.to_xml())
    infos = [scenario.frame_info(i) for i in range(count)]
    gyro = scenario.gyro_samples()
    rate = float(params["rate"])
    codec = Codec("jazzy")
    store = codec.store

    conf = zenoh.Config()
    for key, value in {
        "mode": "router",
        "listen/endpoints": [params["listen"]],
        "scouting/multicast/enabled": False,
        # rmw_zenoh's sessions stamp samples: its transient-local publishers need it.
        "timestamping/enabled": True,
    }.items():
        conf.insert_json5(key, json.dumps(value))
    with zenoh.open(conf) as session:
        node = NodeIdentity(0, str(session.info.zid()), "camera_driver")
        qos = Qos.sensor_data()
        tokens = [session.liveliness().declare_token(node.node_token())]
        publishers = {}
        for entity_id, (topic, ros_type) in enumerate(
            (("/camera/image_raw", IMAGE), ("/imu/data", IMU)), start=1
        ):
            hash_chunk = type_hash(codec.rihs01(ros_type), "jazzy")
            token = node.endpoint_token(
                entity_id, EntityKind.PUBLISHER, topic, ros_type, hash_chunk, qos
            )
            tokens.append(session.liveliness().declare_token(token))
            # Blocking, not dropping as a best-effort rmw_zenoh publisher does: the tests check
            # the pipeline, and a last image Zenoh drops under load leaves no gap in sequence
            # numbers for any subscriber to see (a CI run lost one of 8 images so, uncounted).
            publisher = session.declare_publisher(
                data_key(0, topic, ros_type, hash_chunk),
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            publishers[ros_type] = (publisher, gid(token))
        described = bool(params.get("camera_info"))
        camera = dataclasses.replace(scenario.camera, gyro_time_offset_ns=0)
        image_frame, imu_frame = (IMAGE_FRAME, IMU_FRAME) if described else ("camera", "imu")
        gyro_shift = scenario.camera.gyro_time_offset_ns if described else 0
        # ``latched_info``: CameraInfo once, before the bridge starts, from a transient-local
        # publisher's cache (as a driver with a fixed calibration publishes it), not per image.
        latched_info = bool(params.get("latched_info"))
        latched = Qos(depth=1, durability=Durability.TRANSIENT_LOCAL)
        if described:
            info_hash = type_hash(codec.rihs01(CAMERA_INFO), "jazzy")
            info_key = data_key(0, "/camera/camera_info", CAMERA_INFO, info_hash)
            token = node.endpoint_token(
                3,
                EntityKind.PUBLISHER,
                "/camera/camera_info",
                CAMERA_INFO,
                info_hash,
                latched if latched_info else qos,
            )
            tokens.append(session.liveliness().declare_token(token))
            publishers[CAMERA_INFO] = (
                zenoh.ext.declare_advanced_publisher(
                    session, info_key, cache=zenoh.ext.CacheConfig(1), publisher_detection=True
                )
                if latched_info
                else session.declare_publisher(info_key),
                gid(token),
            )
        sequence = {IMAGE: 0, IMU: 0, CAMERA_INFO: 0}

        def publish(ros_type: str, cdr: bytes | bytearray) -> None:
            publisher, source_gid = publishers[ros_type]
            sequence[ros_type] += 1
            attachment = Attachment(sequence[ros_type], time.time_ns(), source_gid).encode()
            publisher.put(cdr, attachment=attachment)

        broadcasts = tf_static(codec, camera.gyro_to_camera)

        def broadcaster(entity_id: int, name: str) -> None:
            # A tf2_ros StaticTransformBroadcaster on rmw_zenoh: one latched message.
            tf_hash = type_hash(codec.rihs01(TF_MESSAGE), "jazzy")
            owner = NodeIdentity(
                0, str(session.info.zid()), f"{name}_broadcaster", node_id=10 * entity_id
            )
            token = owner.endpoint_token(
                entity_id, EntityKind.PUBLISHER, "/tf_static", TF_MESSAGE, tf_hash, latched
            )
            tokens.append(session.liveliness().declare_token(token))
            publisher = zenoh.ext.declare_advanced_publisher(
                session,
                data_key(0, "/tf_static", TF_MESSAGE, tf_hash),
                cache=zenoh.ext.CacheConfig(1),
                publisher_detection=True,
            )
            tf_publishers.append(publisher)
            publisher.put(
                broadcasts[name], attachment=Attachment(1, time.time_ns(), gid(token)).encode()
            )

        tf_publishers: list[Any] = []
        if described:
            broadcaster(4, "robot")
        if latched_info:
            publish(CAMERA_INFO, camera_info(codec, camera, time.time_ns()))
        _emit(ready=True)
        if not sys.stdin.readline():
            return  # the test ended first
        if described:
            broadcaster(5, "imu")
        skip = set(params.get("skip_sequence") or ())

        t0 = time.time_ns() - int(infos[0].exposure_start_ns / rate) + 200_000_000
        Header, Time = (
            store.types["std_msgs/msg/Header"],
            store.types["builtin_interfaces/msg/Time"],
        )
        Imu = store.types[IMU]
        Vector3 = store.types["geometry_msgs/msg/Vector3"]
        Quaternion = store.types["geometry_msgs/msg/Quaternion"]
        zeros = np.zeros(9, dtype=np.float64)

        def wall(t_rel_ns: int) -> int:
            return t0 + int(t_rel_ns / rate)

        def imu_cdr(t_ns: int, w: np.ndarray) -> bytes | bytearray:
            header = Header(Time(t_ns // 10**9, t_ns % 10**9), imu_frame)
            message = Imu(
                header,
                Quaternion(0.0, 0.0, 0.0, 1.0),
                zeros,
                Vector3(float(w[0]), float(w[1]), float(w[2])),
                zeros,
                Vector3(0.0, 0.0, 9.81),
                zeros,
            )
            return bytes(store.serialize_cdr(message, IMU))

        g_t = np.asarray(gyro.t_ns, dtype=np.int64)
        g_w = np.asarray(gyro.rate_rad_s, dtype=np.float64)
        g_next = int(np.searchsorted(g_t, infos[0].exposure_start_ns - 100_000_000))
        last_t = infos[-1].exposure_start_ns + infos[-1].exposure_ns + 200_000_000
        frame = 0
        while frame < count or (g_next < len(g_t) and g_t[g_next] <= last_t):
            now = time.time_ns()
            while g_next < len(g_t) and wall(int(g_t[g_next])) <= now and g_t[g_next] <= last_t:
                publish(IMU, imu_cdr(wall(int(g_t[g_next]) - gyro_shift), g_w[g_next]))
                g_next += 1
            if frame < count:
                info = infos[frame]
                if wall(info.exposure_start_ns + info.exposure_ns) <= now:
                    stamp = wall(info.exposure_start_ns)
                    cdr = codec.encode_image(
                        stamp, image_frame, images.shape[2], images.shape[1], "mono8", images[frame]
                    )
                    if described and not latched_info:
                        publish(CAMERA_INFO, camera_info(codec, camera, stamp))
                    if frame in skip:
                        sequence[IMAGE] += 1  # as if one sample had been lost on the way
                    publish(IMAGE, cdr)
                    _emit(index=frame, stamp_ns=stamp)
                    frame += 1
            time.sleep(0.0005)
        _emit(done=count)
        sys.stdin.read()  # keep the router up until the test is done
        for declared in tokens:
            declared.undeclare()
        for publisher in tf_publishers:
            publisher.undeclare()


if __name__ == "__main__":
    main(json.loads(sys.argv[1]))
