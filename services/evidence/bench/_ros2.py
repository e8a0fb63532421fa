"""``ros2``: what the ros2 bridge adds to a 1.3 MB image, in and out, against plain Zenoh.

Five processes on loopback: a plain-Zenoh ROS 2 side (``ros2-ros-pub``, a router standing
in for ``rmw_zenohd``, and ``ros2-ros-sub``), the bridge itself (``ros2-bridge``: the real
service, in ``/bench/in`` → ros2/images and out fgpub/images → ``/bench/out``), and a
framegate producer and consumer (``ros2-fg-pub``, ``ros2-fg-sub``). One-way latency is the
wall clock at arrival minus the stamp set just before the first put (one host, one clock):

- in: ROS 2 publisher → bridge → framegate consumer (pushed);
- out: framegate producer → bridge → ROS 2 subscriber;
- and, in the same run, the two hops every bridge path contains: plain Zenoh (ROS 2
  publisher → ROS 2 subscriber, the same CDR images) and framegate (producer → consumer).

A row's ``raw`` side is the sum of the two hops' p50s, its ``framegate`` side the bridge
path's p50, so ``extra`` is what the bridge adds: decoding and checking (in) or encoding
(out), the metadata, its threads. Goal: at most 1 ms added p50 each way.

Copies: the ROS 2 publisher encodes one CDR image once and only rewrites its stamp before
each put. The bridge's in path copies the pixels once (out of the received message into the
element's payload), its out path once (after the CDR head rosbags serializes, into the
message that goes to Zenoh); Zenoh's own copy of a put payload is there in the plain-Zenoh
hop too.
"""

from __future__ import annotations

import json
import struct
import threading
import time
from functools import partial
from typing import Any

from ._options import BenchOptions
from ._procs import Worker, WorkerGroup, free_endpoint
from ._records import Row, ScenarioResult, extra_goal
from ._serve import LatencyLog, paced, reply, serve, serve_while_consuming, sleep_until
from ._stats import percentile
from ._throughput import FRAME_BYTES

ADDED_P50_GOAL_US = 1000.0
INTERVAL_S = 0.02
WIDTH, HEIGHT = 1280, FRAME_BYTES // 1280
TOPIC_IN, TOPIC_OUT, TOPIC_RAW = "/bench/in", "/bench/out", "/bench/raw"
# Offset of header.stamp (int32 sec, uint32 nanosec) in a CDR message: after the
# 4-byte encapsulation header.
_STAMP = struct.Struct("<iI")
_STAMP_AT = 4


def _stamp_ns(payload: bytes) -> int:
    sec, nanosec = _STAMP.unpack_from(payload, _STAMP_AT)
    return int(sec) * 1_000_000_000 + int(nanosec)


def _zenoh_config(params: dict[str, Any]) -> Any:
    import zenoh

    conf = zenoh.Config()
    settings: dict[str, Any] = {
        "mode": params.get("mode", "peer"),
        "scouting/multicast/enabled": False,
    }
    if params.get("listen"):
        settings["listen/endpoints"] = [params["listen"]]
    else:
        settings["listen/endpoints"] = ["tcp/127.0.0.1:0"]
    if params.get("connect"):
        settings["connect/endpoints"] = [params["connect"]]
    for key, value in settings.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


def _image_key(topic: str) -> str:
    from services.nodes.ros2._cdr import IMAGE, Codec
    from services.nodes.ros2._rmw import data_key

    return data_key(0, topic, IMAGE, Codec("jazzy").rihs01(IMAGE))


def ros_pub(params: dict[str, Any]) -> None:
    """The ROS 2 camera: one CDR image, its stamp rewritten before each put."""
    import zenoh

    from services.nodes.ros2._cdr import Codec
    from services.nodes.ros2._rmw import Attachment

    image = Codec("jazzy").encode_image(1, "camera", WIDTH, HEIGHT, "mono8", bytes(FRAME_BYTES))
    template = bytearray(image)  # its stamp is rewritten in place before each put
    with zenoh.open(_zenoh_config({**params, "mode": "router"})) as session:
        publishers = {
            stream: session.declare_publisher(
                _image_key(topic), congestion_control=zenoh.CongestionControl.BLOCK
            )
            for stream, topic in (("in", TOPIC_IN), ("raw", TOPIC_RAW))
        }
        gid = bytes(16)

        def latency(command: dict[str, Any]) -> dict[str, Any]:
            publisher = publishers[str(command["stream"])]
            deadline = time.monotonic() + 30
            status: Any = publisher.matching_status  # typed bool in the stubs
            while not status.matching:
                if time.monotonic() > deadline:
                    raise RuntimeError("no subscriber matched within 30 s")
                time.sleep(0.01)
                status = publisher.matching_status
            sent = 0
            for tick in paced(float(command["seconds"]), INTERVAL_S):
                sleep_until(tick)
                now = time.time_ns()
                _STAMP.pack_into(template, _STAMP_AT, now // 1_000_000_000, now % 1_000_000_000)
                attachment = Attachment(sent + 1, now, gid).encode()
                publisher.put(template, attachment=attachment)
                sent += 1
            return {"sent": sent}

        reply(ready=True)
        serve({"latency": latency})


def ros_sub(params: dict[str, Any]) -> None:
    """The ROS 2 subscriber: latency = wall clock now − header.stamp."""
    import zenoh

    log = LatencyLog(["out", "raw"])

    def recorder(stream: str) -> Any:
        def on_sample(sample: zenoh.Sample) -> None:
            payload = sample.payload.to_bytes()
            now = time.time_ns()
            if len(payload) > FRAME_BYTES:
                log.record(stream, (now - _stamp_ns(payload)) / 1000)

        return on_sample

    with zenoh.open(_zenoh_config(params)) as session:
        subscribers = [
            session.declare_subscriber(_image_key(topic), zenoh.handlers.Callback(recorder(name)))
            for name, topic in (("out", TOPIC_OUT), ("raw", TOPIC_RAW))
        ]
        reply(ready=True)
        serve({"collect": log.collect})
        for subscriber in subscribers:
            subscriber.undeclare()


def bridge(params: dict[str, Any]) -> None:
    """The real ros2 bridge service, until told to exit."""
    from middleware import NetworkConfig
    from services.nodes.ros2._bridge import run
    from services.nodes.ros2._config import Mapping, Ros2Config

    config = Ros2Config(
        ros_connect=(str(params["ros"]),),
        image_in=TOPIC_IN,
        image_out=(Mapping("fgpub/images", TOPIC_OUT),),
        in_depth=4,
    )
    stop = threading.Event()
    thread = threading.Thread(
        target=run, args=(config, NetworkConfig(connect=(str(params["fg"]),)), stop), daemon=True
    )
    thread.start()
    reply(ready=True)
    try:
        serve({})
    finally:
        stop.set()
        thread.join(5)


def fg_pub(params: dict[str, Any]) -> None:
    """framegate producer: stream ``out`` puts to fgpub/images (the bridge observes it),
    ``fg`` to fgpub/direct (the consumer's baseline hop)."""
    from middleware import NetworkConfig, Node, Retention
    from services.lib.messages import frame_metadata_of
    from services.lib.quality import Exposure

    payload = bytes(FRAME_BYTES)
    with Node("fgpub", NetworkConfig(listen=(str(params["listen"]),))) as node:
        producers = {
            stream: node.offer(buffer, kind="frame", retention=Retention(max_count=16))
            for stream, buffer in (("out", "images"), ("fg", "direct"))
        }

        def latency(command: dict[str, Any]) -> dict[str, Any]:
            producer = producers[str(command["stream"])]
            if not producer.wait_for_subscribers(1, timeout_s=30.0):
                raise RuntimeError("no subscription registered within 30 s")
            sent = 0
            for tick in paced(float(command["seconds"]), INTERVAL_S):
                sleep_until(tick)
                now = time.time_ns()
                metadata = frame_metadata_of(
                    sent, Exposure(now, 1_000_000), "mono8", WIDTH, HEIGHT, None
                )
                producer.put(now, payload, metadata, wait_s=1.0)
                sent += 1
            return {"sent": sent}

        reply(ready=True)
        serve({"latency": latency})


def fg_sub(params: dict[str, Any]) -> None:
    """framegate consumer of ros2/images (the bridge's in path) and fgpub/direct."""
    from middleware import PUSH_ALL, NetworkConfig, Node

    log = LatencyLog(["in", "fg"])
    stop = threading.Event()
    with Node(network=NetworkConfig(connect=(str(params["connect"]),))) as node:

        def consume(stream: str, target: str) -> None:
            sub = node.subscribe(
                target, queue_size=4, wait_s=0, push_max_bytes=PUSH_ALL, await_service=True
            )
            while not stop.is_set():
                note = sub.take(timeout_s=0.2)
                if note is None:
                    continue
                element = sub.fetch(note)
                now = time.time_ns()
                if len(element.payload) == FRAME_BYTES:
                    log.record(stream, (now - element.timestamp_ns) / 1000)

        consumers = [partial(consume, "in", "ros2/images"), partial(consume, "fg", "fgpub/direct")]
        serve_while_consuming(consumers, stop, {"collect": log.collect})


ROLES = {
    "ros2-ros-pub": ros_pub,
    "ros2-ros-sub": ros_sub,
    "ros2-bridge": bridge,
    "ros2-fg-pub": fg_pub,
    "ros2-fg-sub": fg_sub,
}


def _run(producer: Worker, consumer: Worker, stream: str, seconds: float) -> list[float]:
    consumer.call("collect", stream=stream, expect=0, wait_s=0)  # forget stragglers
    sent = producer.call("latency", timeout_s=seconds + 60, stream=stream, seconds=seconds)
    answer = consumer.call("collect", timeout_s=30, stream=stream, expect=sent["sent"], wait_s=10)
    latencies = [float(v) for v in answer["latencies_us"]]
    if not latencies:
        raise RuntimeError(f"the {stream} stream delivered nothing")
    return latencies


def run_ros2(options: BenchOptions) -> ScenarioResult:
    result = ScenarioResult(
        "ros2",
        params={
            "image": f"{WIDTH}x{HEIGHT} mono8 sensor_msgs/msg/Image",
            "interval_s": INTERVAL_S,
            "window_s": options.duration_s,
            "raw": "p50 of plain Zenoh (ROS 2 pub -> sub) + p50 of framegate (put -> pushed take)",
            "framegate": "p50 through the bridge (in: ROS 2 -> framegate; out: framegate -> ROS 2)",
        },
    )
    rows = {
        "in": Row("bridge in (ROS 2 -> framegate) p50", "latency p50", "us", False),
        "out": Row("bridge out (framegate -> ROS 2) p50", "latency p50", "us", False),
    }
    ros_at, fg_at = free_endpoint(), free_endpoint()
    with WorkerGroup() as group:
        ros_pub_w = group.start("ros2-ros-pub", {"listen": ros_at})
        ros_sub_w = group.start("ros2-ros-sub", {"connect": ros_at})
        fg_pub_w = group.start("ros2-fg-pub", {"listen": fg_at})
        group.start("ros2-bridge", {"ros": ros_at, "fg": fg_at})
        fg_sub_w = group.start("ros2-fg-sub", {"connect": fg_at})
        group.wait_ready()
        for pair in range(options.pairs):
            seconds = options.duration_s
            hops = {
                "raw": _run(ros_pub_w, ros_sub_w, "raw", seconds),
                "fg": _run(fg_pub_w, fg_sub_w, "fg", seconds),
            }
            paths = {
                "in": _run(ros_pub_w, fg_sub_w, "in", seconds),
                "out": _run(fg_pub_w, ros_sub_w, "out", seconds),
            }
            baseline = percentile(hops["raw"], 50) + percentile(hops["fg"], 50)
            for name, latencies in paths.items():
                p50 = percentile(latencies, 50)
                base = {"pair": pair, "count": len(latencies)}
                rows[name].samples("raw").append({**base, "value": baseline})
                rows[name].samples("framegate").append(
                    {**base, "value": p50, "p99": percentile(latencies, 99)}
                )
                options.progress(
                    f"ros2 pair {pair + 1}/{options.pairs} {name}: p50 {p50:.0f} us through the "
                    f"bridge, hops {percentile(hops['raw'], 50):.0f} + "
                    f"{percentile(hops['fg'], 50):.0f} us, added {p50 - baseline:.0f} us"
                )
    for row in rows.values():
        row.goal = extra_goal(row, ADDED_P50_GOAL_US, what="added p50")
        row.note = "raw = plain Zenoh hop + framegate hop (p50s); extra = what the bridge adds"
        result.rows.append(row)
    return result
