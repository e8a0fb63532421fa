"""The bridge's configuration: one frozen dataclass, one flag per field.

The ROS 2 side has its own connection flags shaped like every service's (``--ros-connect``,
``--ros-listen``, ``--ros-config``), because the ROS 2 system's router (``rmw_zenohd``,
``tcp/localhost:7447`` by default) is usually not framegate's network. Mappings are
``framegate buffer=ROS 2 topic`` pairs; in a deploy file a list gives several:
``image_out: [mediator/images=/framegate/image]``.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass
from pathlib import Path

from middleware import ConfigError, FramegateError, NetworkConfig, check_name, split_target
from services.lib.argtypes import (
    non_negative_float,
    non_negative_int,
    positive_float,
    positive_int,
)

from ._rmw import DISTROS, History, Qos, Reliability, fully_qualified

DEFAULT_ROUTER = "tcp/localhost:7447"
STAMPS = ("start", "middle", "end")


@dataclass(frozen=True, slots=True)
class Mapping:
    """A framegate buffer (``service/buffer``) and the ROS 2 topic it is carried to."""

    buffer: str
    topic: str

    @classmethod
    def parse(cls, text: str, namespace: str = "/") -> Mapping:
        """``SERVICE/BUFFER=TOPIC``; a bare ``SERVICE/BUFFER`` is carried to ``/SERVICE/BUFFER``."""
        buffer, sep, topic = text.partition("=")
        if not buffer or (sep and not topic):
            raise ConfigError(f"bad mapping {text!r}: use SERVICE/BUFFER=/ros/topic")
        try:
            split_target(buffer)
        except FramegateError as exc:
            raise ConfigError(f"bad mapping {text!r}: {exc}") from exc
        return cls(buffer, fully_qualified(topic if sep else "/" + buffer, namespace))


@dataclass(frozen=True, slots=True)
class Ros2Config:
    """Everything the bridge can be told (one flag per field)."""

    name: str = "ros2"
    ros_connect: tuple[str, ...] = (DEFAULT_ROUTER,)
    ros_listen: tuple[str, ...] = ()
    ros_config: Path | None = None
    ros_distro: str = "jazzy"
    domain_id: int = 0
    node_name: str = "framegate_bridge"
    ros_namespace: str = "/"
    # in: ROS 2 camera and IMU -> framegate frame and gyro buffers
    image_in: str | None = None
    imu_in: str | None = None
    exposure_ms: float = 10.0
    camera_xml: Path | None = None
    # None: the camera_info topic beside image_in (image_transport); "" reads none.
    camera_info: str | None = None
    imu_to_camera: tuple[float, ...] | None = None  # row-major R, v_camera = R @ v_imu
    stamp: str = "start"
    gyro_batch: int = 10
    gyro_wait_ms: float = 50.0
    in_reliability: Reliability = Reliability.BEST_EFFORT
    in_depth: int = 5
    retention_frames: int = 64
    # out: framegate buffers -> ROS 2 topics
    image_out: tuple[Mapping, ...] = ()
    detections_out: tuple[Mapping, ...] = ()
    verdicts_out: tuple[Mapping, ...] = ()
    frame_id: str = "camera"
    out_reliability: Reliability = Reliability.RELIABLE
    out_depth: int = 10
    out_queue: int = 8
    # the loop: a ROS 2 node's results free its slots (see _consumer_loop)
    consumer_done: str | None = None
    consumer_input: str | None = None
    consumer_queue: int = 2
    consumer_timeout_ms: float = 1000.0

    def __post_init__(self) -> None:
        check_name(self.name, "service")
        if self.ros_distro not in DISTROS:
            raise ConfigError(f"--ros-distro {self.ros_distro!r}: use one of {', '.join(DISTROS)}")
        if self.stamp not in STAMPS:
            raise ConfigError(f"--stamp {self.stamp!r}: use one of {', '.join(STAMPS)}")
        if not self.exposure_ms > 0:
            raise ConfigError(f"--exposure-ms must be > 0, got {self.exposure_ms}")
        for flag, value in (
            ("--gyro-batch", self.gyro_batch),
            ("--out-queue", self.out_queue),
            ("--retention-frames", self.retention_frames),
        ):
            if value < 1:
                raise ConfigError(f"{flag} must be >= 1, got {value}")
        if self.imu_to_camera is not None and len(self.imu_to_camera) != 9:
            raise ConfigError(
                f"--imu-to-camera takes 9 numbers (a row-major 3x3 rotation), got "
                f"{len(self.imu_to_camera)}"
            )
        if self.in_depth < 1 or self.out_depth < 0:
            raise ConfigError("--in-depth must be >= 1 and --out-depth >= 0 (0 = keep all)")
        if not self.ros_namespace.startswith("/"):
            raise ConfigError(f"--ros-namespace must start with '/', got {self.ros_namespace!r}")
        self._check_consumer()

    def _check_consumer(self) -> None:
        if self.consumer_queue < 1:
            raise ConfigError(f"--consumer-queue must be >= 1, got {self.consumer_queue}")
        if not self.consumer_timeout_ms > 0:
            raise ConfigError(f"--consumer-timeout-ms must be > 0, got {self.consumer_timeout_ms}")
        if self.consumer_done is not None:
            self.consumer_mapping  # noqa: B018 -- raises ConfigError when there is none

    @property
    def consumer_mapping(self) -> Mapping | None:
        """The ``--image-out`` mapping whose ROS 2 node closes the loop (None without
        ``--consumer-done``): the one of ``--consumer-input``, else the only one."""
        if self.consumer_done is None:
            return None
        if self.consumer_input is not None:
            for mapping in self.image_out:
                if mapping.buffer == self.consumer_input:
                    return mapping
            raise ConfigError(
                f"--consumer-input {self.consumer_input}: not an --image-out buffer "
                f"({', '.join(m.buffer for m in self.image_out) or 'none given'})"
            )
        if len(self.image_out) != 1:
            raise ConfigError(
                "--consumer-done needs the node's input: one --image-out mapping "
                "(e.g. mediator/images=/camera/image_sharp), or --consumer-input BUFFER "
                "naming one of several"
            )
        return self.image_out[0]

    def check_has_work(self) -> None:
        """ConfigError when no topic is mapped either way (checked when the bridge starts)."""
        if not (self.image_in or self.imu_in or self.outputs):
            raise ConfigError(
                "the ros2 bridge has nothing to carry: give --image-in, --imu-in, "
                "--image-out, --detections-out or --verdicts-out"
            )

    @property
    def outputs(self) -> tuple[Mapping, ...]:
        return (*self.image_out, *self.detections_out, *self.verdicts_out)

    @property
    def exposure_ns(self) -> int:
        return int(self.exposure_ms * 1e6)

    @property
    def in_qos(self) -> Qos:
        return Qos(self.in_reliability, self.in_depth)

    @property
    def camera_info_topic(self) -> str | None:
        """The CameraInfo topic read for the intrinsics (None: none is read)."""
        if self.camera_info is not None:
            return self.camera_info or None
        if self.image_in is None:
            return None
        return self.image_in.rsplit("/", 1)[0] + "/camera_info"  # image_transport's layout

    @property
    def out_qos(self) -> Qos:
        keep_all = self.out_depth == 0
        return Qos(
            self.out_reliability,
            self.out_depth,
            History.KEEP_ALL if keep_all else History.KEEP_LAST,
        )

    def ros_network(self) -> NetworkConfig:
        """The ROS 2 session's network: rmw_zenoh's session defaults (a peer, no multicast,
        the router to connect to) in framegate's shape."""
        return NetworkConfig(
            connect=self.ros_connect,
            listen=self.ros_listen,
            config_file=self.ros_config,
        )

    def start_ns(self, stamp_ns: int) -> int:
        """Exposure start from a ROS header stamp (``--stamp`` says where in the exposure)."""
        return (
            stamp_ns
            - {"start": 0, "middle": self.exposure_ns // 2, "end": self.exposure_ns}[self.stamp]
        )

    def stamp_ns(self, start_ns: int) -> int:
        """The ROS header stamp of a frame exposed from ``start_ns`` (inverse of start_ns)."""
        return (
            start_ns
            + {"start": 0, "middle": self.exposure_ns // 2, "end": self.exposure_ns}[self.stamp]
        )


def _reliability(text: str) -> Reliability:
    try:
        return Reliability[text.upper().replace("-", "_")]
    except KeyError as exc:
        raise ConfigError(f"reliability {text!r}: use reliable or best_effort") from exc


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The bridge's flags (``framegate run ros2 --help``)."""
    d = Ros2Config()
    parser.add_argument("--name", default=d.name, help="service name (default %(default)s)")
    ros = parser.add_argument_group("ROS 2 network")
    ros.add_argument(
        "--ros-connect",
        action="append",
        metavar="ENDPOINT",
        help=f"the ROS 2 system's Zenoh router (rmw_zenohd; default {DEFAULT_ROUTER}, "
        "or the --ros-config file's endpoints)",
    )
    ros.add_argument("--ros-listen", action="append", metavar="ENDPOINT", help="listen endpoint")
    ros.add_argument("--ros-config", metavar="FILE", help="Zenoh JSON5 file for the ROS 2 session")
    ros.add_argument(
        "--ros-distro",
        choices=DISTROS,
        default=d.ros_distro,
        help="the ROS 2 system's distro: the type hashes in keys (default %(default)s)",
    )
    ros.add_argument(
        "--domain-id",
        type=non_negative_int,
        default=int(os.environ.get("ROS_DOMAIN_ID") or 0),
        help="ROS_DOMAIN_ID (default: $ROS_DOMAIN_ID or 0)",
    )
    ros.add_argument(
        "--node-name",
        default=d.node_name,
        help="the bridge's ROS 2 node name (default %(default)s)",
    )
    ros.add_argument(
        "--ros-namespace", default=d.ros_namespace, help="ROS 2 namespace (default %(default)s)"
    )
    inbound = parser.add_argument_group("ROS 2 -> framegate")
    inbound.add_argument("--image-in", metavar="TOPIC", help="sensor_msgs/msg/Image -> NAME/images")
    inbound.add_argument("--imu-in", metavar="TOPIC", help="sensor_msgs/msg/Imu -> NAME/rates")
    inbound.add_argument(
        "--exposure-ms",
        type=positive_float,
        default=d.exposure_ms,
        help="exposure time of the camera (default %(default)s)",
    )
    inbound.add_argument(
        "--camera-xml",
        help="camera description (camera metadata XML); overrides CameraInfo and /tf_static",
    )
    inbound.add_argument(
        "--camera-info",
        metavar="TOPIC",
        help="sensor_msgs/msg/CameraInfo giving the intrinsics (default: camera_info beside "
        "--image-in, as image_transport names it; '' reads none)",
    )
    inbound.add_argument(
        "--imu-to-camera",
        nargs=9,
        type=float,
        metavar="R",
        help="rotation R (row-major, v_camera = R v_imu) instead of the one /tf_static gives "
        "between the IMU's and the image's header.frame_id",
    )
    inbound.add_argument(
        "--stamp",
        choices=STAMPS,
        default=d.stamp,
        help="where in the exposure header.stamp lies (default %(default)s)",
    )
    inbound.add_argument(
        "--gyro-batch",
        type=positive_int,
        default=d.gyro_batch,
        help="IMU samples per put (default %(default)s)",
    )
    inbound.add_argument(
        "--gyro-wait-ms",
        type=non_negative_float,
        default=d.gyro_wait_ms,
        help="how long a refused gyro batch waits for credit before it is dropped "
        "(default %(default)s)",
    )
    inbound.add_argument(
        "--in-reliability",
        choices=["reliable", "best_effort"],
        default="best_effort",
        help="QoS of the subscriptions (default: sensor data, best effort)",
    )
    inbound.add_argument(
        "--in-depth",
        type=positive_int,
        default=d.in_depth,
        help="KEEP_LAST depth in (default %(default)s)",
    )
    inbound.add_argument(
        "--retention-frames",
        type=positive_int,
        default=d.retention_frames,
        help="frames NAME/images keeps (default %(default)s)",
    )
    outbound = parser.add_argument_group("framegate -> ROS 2")
    for flag, what in (
        ("--image-out", "frame buffer -> sensor_msgs/msg/Image"),
        ("--detections-out", "detections -> vision_msgs/msg/Detection2DArray"),
        ("--verdicts-out", "mediator decisions -> std_msgs/msg/String (JSON)"),
    ):
        outbound.add_argument(
            flag, nargs="+", action="extend", metavar="BUFFER=TOPIC", help=what + " (repeatable)"
        )
    outbound.add_argument(
        "--frame-id", default=d.frame_id, help="header.frame_id of outputs (default %(default)s)"
    )
    outbound.add_argument(
        "--out-reliability",
        choices=["reliable", "best_effort"],
        default="reliable",
        help="QoS of the publishers (default reliable)",
    )
    outbound.add_argument(
        "--out-depth",
        type=non_negative_int,
        default=d.out_depth,
        help="KEEP_LAST depth out, 0: keep all (default %(default)s)",
    )
    outbound.add_argument(
        "--out-queue",
        type=positive_int,
        default=d.out_queue,
        help="notification queue of each observed framegate buffer (default %(default)s)",
    )
    loop = parser.add_argument_group(
        "a ROS 2 node in the loop (its results free its slots: the mediator sees its load)"
    )
    loop.add_argument(
        "--consumer-done",
        metavar="TOPIC",
        help="the node's result topic: any message whose first field is a std_msgs/Header "
        "copied from the input image (type read from the ROS graph)",
    )
    loop.add_argument(
        "--consumer-input",
        metavar="BUFFER",
        help="the --image-out buffer the node subscribes to (default: the only one)",
    )
    loop.add_argument(
        "--consumer-queue",
        type=positive_int,
        default=d.consumer_queue,
        help="images the node may hold without a result (default %(default)s)",
    )
    loop.add_argument(
        "--consumer-timeout-ms",
        type=positive_float,
        default=d.consumer_timeout_ms,
        help="an image without a result frees its slot after this long, counted "
        "(default %(default)s)",
    )


def config_from_args(args: argparse.Namespace) -> Ros2Config:
    """The config the parsed flags describe."""
    ns = "/" + args.ros_namespace.strip("/") if args.ros_namespace.strip("/") else "/"

    def topic(value: str | None) -> str | None:
        return fully_qualified(value, ns) if value else None

    def maps(values: list[str] | None) -> tuple[Mapping, ...]:
        return tuple(Mapping.parse(v, ns) for v in values or ())

    return Ros2Config(
        name=args.name,
        # A --ros-config file names its own endpoints unless --ros-connect is given too.
        ros_connect=tuple(args.ros_connect or (() if args.ros_config else (DEFAULT_ROUTER,))),
        ros_listen=tuple(args.ros_listen or ()),
        ros_config=Path(args.ros_config) if args.ros_config else None,
        ros_distro=args.ros_distro,
        domain_id=args.domain_id,
        node_name=args.node_name,
        ros_namespace=ns,
        image_in=topic(args.image_in),
        imu_in=topic(args.imu_in),
        exposure_ms=args.exposure_ms,
        camera_xml=Path(args.camera_xml) if args.camera_xml else None,
        camera_info=topic(args.camera_info) if args.camera_info else args.camera_info,
        imu_to_camera=tuple(args.imu_to_camera) if args.imu_to_camera else None,
        stamp=args.stamp,
        gyro_batch=args.gyro_batch,
        gyro_wait_ms=args.gyro_wait_ms,
        in_reliability=_reliability(args.in_reliability),
        in_depth=args.in_depth,
        retention_frames=args.retention_frames,
        image_out=maps(args.image_out),
        detections_out=maps(args.detections_out),
        verdicts_out=maps(args.verdicts_out),
        frame_id=args.frame_id,
        out_reliability=_reliability(args.out_reliability),
        out_depth=args.out_depth,
        out_queue=args.out_queue,
        consumer_done=topic(args.consumer_done),
        consumer_input=args.consumer_input,
        consumer_queue=args.consumer_queue,
        consumer_timeout_ms=args.consumer_timeout_ms,
    )
