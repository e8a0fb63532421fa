"""The bridge's configuration: one frozen dataclass, one flag per field.

The ROS 2 side has its own connection flags shaped like every service's (``--ros-connect``,
``--ros-listen``, ``--ros-config``), because the ROS 2 system's router (``rmw_zenohd``,
``tcp/localhost:7447`` by default) is usually not framegate's network. Mappings are
``framegate buffer=ROS 2 topic`` pairs; in a deploy file a list gives several:
``image_out: [mediator/images=/framegate/image]``.
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from middleware import (
    FLOW_QUEUE_MAX,
    ConfigError,
    FramegateError,
    NetworkConfig,
    check_name,
    checked_endpoints,
    split_target,
)
from services.lib.argtypes import (
    non_negative_float,
    non_negative_int,
    positive_float,
    positive_int,
)
from services.lib.camera_model import check_rotation
from services.lib.settings import add_flags, from_args, setting

from ._rmw import DISTROS, History, Qos, Reliability, fully_qualified

DEFAULT_ROUTER = "tcp/localhost:7447"
STAMPS = ("start", "middle", "end")
# The ROS 2 session's lease: Zenoh's default, which rmw_zenoh keeps (see ``ros_network``).
ROS_LEASE_MS = 10_000
# The outputs' header.frame_id when neither --frame-id nor images in name one.
DEFAULT_FRAME_ID = "camera"
# A header.frame_id longer than this is not taken over for the outputs (TF names are short).
MAX_FRAME_ID_CHARS = 256


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
        try:
            return cls(buffer, fully_qualified(topic if sep else "/" + buffer, namespace))
        except ConfigError as exc:
            if sep:
                raise
            # The topic was made from the buffer's name, which may hold '-' and '.'.
            raise ConfigError(
                f"bad mapping {text!r}: {exc}; name the topic: {buffer}=/ros/topic"
            ) from exc


_NETWORK = "ROS 2 network"
_IN = "ROS 2 -> framegate"
_OUT = "framegate -> ROS 2"
_LOOP = "a ROS 2 node in the loop (its results free its slots: the mediator sees its load)"
# The mapping flags: BUFFER=TOPIC pairs, repeatable (a deploy file gives a list).
_MAPPINGS: dict[str, Any] = {"repeat": True, "metavar": "BUFFER=TOPIC", "group": _OUT}


def _namespace(text: str) -> str:
    """``robot1``, ``/robot1/`` -> ``/robot1``; empty -> ``/``."""
    inner = text.strip("/")
    return "/" + inner if inner else "/"


@dataclass(frozen=True, slots=True)
class Ros2Config:
    """Everything the bridge can be told (one flag per field)."""

    name: str = setting("ros2", "service name")
    ros_connect: tuple[str, ...] = setting(
        (DEFAULT_ROUTER,),
        "the ROS 2 system's Zenoh router, rmw_zenohd",
        repeat=True,
        metavar="ENDPOINT",
        shown=f"{DEFAULT_ROUTER}, or the --ros-config file's endpoints",
        group=_NETWORK,
    )
    ros_listen: tuple[str, ...] = setting(
        (), "listen endpoint", repeat=True, metavar="ENDPOINT", group=_NETWORK
    )
    ros_config: Path | None = setting(
        None, "Zenoh JSON5 file for the ROS 2 session", parse=Path, metavar="FILE", group=_NETWORK
    )
    ros_distro: str = setting(
        "jazzy",
        "the ROS 2 system's distro: the type hashes in keys",
        choices=DISTROS,
        group=_NETWORK,
    )
    domain_id: int = setting(
        0, "ROS_DOMAIN_ID", parse=non_negative_int, env="ROS_DOMAIN_ID", group=_NETWORK
    )
    node_name: str = setting("framegate_bridge", "the bridge's ROS 2 node name", group=_NETWORK)
    ros_namespace: str = setting("/", "ROS 2 namespace", parse=_namespace, group=_NETWORK)
    # in: ROS 2 camera and IMU -> framegate frame and gyro buffers
    image_in: str | None = setting(
        None, "sensor_msgs/msg/Image -> NAME/images", metavar="TOPIC", group=_IN
    )
    imu_in: str | None = setting(
        None, "sensor_msgs/msg/Imu -> NAME/rates", metavar="TOPIC", group=_IN
    )
    exposure_ms: float = setting(
        10.0, "exposure time of the camera", parse=positive_float, group=_IN
    )
    camera_xml: Path | None = setting(
        None,
        "camera description (camera metadata XML); overrides CameraInfo and /tf_static",
        parse=Path,
        group=_IN,
    )
    # None: the camera_info topic beside image_in (image_transport); "" reads none.
    camera_info: str | None = setting(
        None,
        "sensor_msgs/msg/CameraInfo giving the intrinsics",
        metavar="TOPIC",
        shown="camera_info beside --image-in, as image_transport names it; '' reads none",
        group=_IN,
    )
    imu_to_camera: tuple[float, ...] | None = setting(
        None,
        "rotation R (row-major, v_camera = R v_imu) instead of the one /tf_static gives "
        "between the IMU's and the image's header.frame_id",
        parse=float,
        count=9,
        metavar="R",
        group=_IN,
    )
    stamp: str = setting(
        "start", "where in the exposure header.stamp lies", choices=STAMPS, group=_IN
    )
    max_ahead_ms: float = setting(
        1000.0,
        "a stamp further ahead of this host's clock is a counted future-stamp (the buffers "
        "refuse it too: one accepted far ahead would hold back every later message)",
        parse=positive_float,
        group=_IN,
    )
    gyro_batch: int = setting(10, "IMU samples per put", parse=positive_int, group=_IN)
    gyro_wait_ms: float = setting(
        50.0,
        "how long a refused gyro batch waits for credit before it is dropped",
        parse=non_negative_float,
        group=_IN,
    )
    in_reliability: Reliability = setting(
        Reliability.BEST_EFFORT,
        "QoS of the subscriptions",
        shown="sensor data, best_effort",
        group=_IN,
    )
    in_depth: int = setting(5, "KEEP_LAST depth in", parse=positive_int, group=_IN)
    retention_frames: int = setting(64, "frames NAME/images keeps", parse=positive_int, group=_IN)
    # out: framegate buffers -> ROS 2 topics
    image_out: tuple[Mapping, ...] = setting(
        (), "frame buffer -> sensor_msgs/msg/Image (repeatable)", **_MAPPINGS
    )
    detections_out: tuple[Mapping, ...] = setting(
        (), "detections -> vision_msgs/msg/Detection2DArray (repeatable)", **_MAPPINGS
    )
    verdicts_out: tuple[Mapping, ...] = setting(
        (), "mediator decisions -> std_msgs/msg/String (JSON) (repeatable)", **_MAPPINGS
    )
    frame_id: str | None = setting(
        None,
        "header.frame_id of outputs (default: that of the images on --image-in, as a node "
        f"that copies it into its results expects; without them {DEFAULT_FRAME_ID!r})",
        group=_OUT,
    )
    out_reliability: Reliability = setting(
        Reliability.RELIABLE, "QoS of the publishers", group=_OUT
    )
    out_depth: int = setting(
        10, "KEEP_LAST depth out, 0: keep all", parse=non_negative_int, group=_OUT
    )
    out_queue: int = setting(
        8,
        "notification queue of each observed framegate buffer",
        parse=positive_int,
        group=_OUT,
    )
    # the loop: a ROS 2 node's results free its slots (see _consumer_loop)
    consumer_done: str | None = setting(
        None,
        "the node's result topic: any message whose first field is a std_msgs/Header "
        "copied from the input image (type read from the ROS graph)",
        metavar="TOPIC",
        group=_LOOP,
    )
    consumer_input: str | None = setting(
        None,
        "the --image-out buffer the node subscribes to (default: the only one)",
        metavar="BUFFER",
        group=_LOOP,
    )
    # ``unset``: given with the default's value but without --consumer-done is refused too.
    consumer_queue: int = setting(
        2,
        "images the node may hold without a result",
        parse=positive_int,
        group=_LOOP,
        unset=True,
    )
    consumer_timeout_ms: float = setting(
        1000.0,
        "the most the node may take for one image, from its turn (the image before it "
        "answered): then its slot is freed, counted",
        parse=positive_float,
        group=_LOOP,
        unset=True,
    )

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
        if self.imu_to_camera is not None:
            check_rotation(self.imu_to_camera, "--imu-to-camera")
        if self.in_depth < 1 or self.out_depth < 0:
            raise ConfigError("--in-depth must be >= 1 and --out-depth >= 0 (0 = keep all)")
        if not self.ros_namespace.startswith("/"):
            raise ConfigError(f"--ros-namespace must start with '/', got {self.ros_namespace!r}")
        self._check_consumer()
        self._check_topics()

    def _check_topics(self) -> None:
        """ConfigError for an output on a topic the bridge reads, or two outputs on one
        topic: the bridge's own images came back in as new frames (counted
        ``duplicate-stamp``), and every node on the topic got two streams mixed."""
        inputs = {
            self.camera_info_topic: "the CameraInfo, --camera-info",
            "/tf_static": "the static transforms",
            self.image_in: "--image-in",
            self.imu_in: "--imu-in",
        }
        seen: dict[str, str] = {}
        for mapping in self.outputs:
            said = f"{mapping.buffer}={mapping.topic}"
            if mapping.topic in inputs:
                raise ConfigError(
                    f"output {said}: the bridge reads {mapping.topic} "
                    f"({inputs[mapping.topic]}) and would read its own messages back; "
                    "publish to a topic of its own (e.g. /camera/image_sharp)"
                )
            if mapping.topic in seen:
                raise ConfigError(
                    f"outputs {seen[mapping.topic]} and {said} publish on one topic; give each "
                    "its own"
                )
            seen[mapping.topic] = said

    def _check_consumer(self) -> None:
        if not 1 <= self.consumer_queue <= FLOW_QUEUE_MAX:
            raise ConfigError(
                f"--consumer-queue must be 1..{FLOW_QUEUE_MAX} (the largest flow-controlled "
                f"queue a producer grants), got {self.consumer_queue}"
            )
        if not int(self.consumer_timeout_ms * 1e6) >= 1:  # in int ns, as the loop keeps it
            raise ConfigError(
                f"--consumer-timeout-ms must be at least 1e-06 (1 ns), got "
                f"{self.consumer_timeout_ms}"
            )
        if self.consumer_done is None:
            # Flags of the loop without the loop: said, not silently ignored.
            defaults = {f.name: f.default for f in dataclasses.fields(self)}
            _loop_without_done(
                [name for name in LOOP_FIELDS if getattr(self, name) != defaults[name]]
            )
        if self.camera_xml is not None and self.camera_info:
            # What the XML overrides, given as well: said, not silently ignored.
            raise ConfigError(
                f"--camera-info {self.camera_info} with --camera-xml: the camera description "
                "gives the intrinsics (CameraInfo is not read); give one or the other"
            )
        if self.consumer_done is not None:
            self.consumer_mapping  # noqa: B018 -- raises ConfigError when there is none
            ours = [m.topic for m in self.outputs]
            if self.consumer_done in ours or self.consumer_done in (self.image_in, self.imu_in):
                # Our own messages would "answer" our own images: the node's load unseen.
                raise ConfigError(
                    f"--consumer-done {self.consumer_done}: a topic this bridge carries "
                    "itself; give the topic your node publishes its results on"
                )

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
            # Zenoh's lease, as rmw_zenoh nodes have: framegate's 1 s lease (a dead consumer
            # freed within about a second) is for its own flow control. On the ROS side it
            # only made the bridge's link drop, and what it published meanwhile vanish, each
            # time a loaded machine left the bridge without CPU for over a second.
            lease_ms=ROS_LEASE_MS,
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


# The loop's flags besides --consumer-done: meaningless without it.
LOOP_FIELDS = ("consumer_input", "consumer_queue", "consumer_timeout_ms")


def _loop_without_done(given: list[str]) -> None:
    """ConfigError naming the loop's flags ``given`` (field names) without --consumer-done."""
    if given:
        flags = ", ".join("--" + name.replace("_", "-") for name in given)
        raise ConfigError(
            f"{flags} without --consumer-done: the loop through a ROS 2 node's results needs "
            "its result topic"
        )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The bridge's flags (``framegate run ros2 --help``): one per config field."""
    add_flags(parser, Ros2Config)


def config_from_args(args: argparse.Namespace) -> Ros2Config:
    """The config the parsed flags describe; topics and mappings in the namespace given."""
    ns = args.ros_namespace  # already normalized by its flag

    def topic(value: str | None) -> str | None:
        return fully_qualified(value, ns) if value else value  # "" (none) kept

    def maps(values: list[str] | None) -> tuple[Mapping, ...]:
        return tuple(Mapping.parse(v, ns) for v in values or ())

    if not args.consumer_done:  # a loop flag given, even with the default's value
        _loop_without_done([name for name in LOOP_FIELDS if getattr(args, name) is not None])
    config: Ros2Config = from_args(
        Ros2Config,
        args,
        # A --ros-config file names its own endpoints unless --ros-connect is given too.
        ros_connect=checked_endpoints(
            args.ros_connect or (() if args.ros_config else (DEFAULT_ROUTER,)), "--ros-connect"
        ),
        ros_listen=checked_endpoints(args.ros_listen or (), "--ros-listen", lowest=0),
        image_in=topic(args.image_in or None),
        imu_in=topic(args.imu_in or None),
        camera_info=topic(args.camera_info),
        consumer_done=topic(args.consumer_done or None),
        image_out=maps(args.image_out),
        detections_out=maps(args.detections_out),
        verdicts_out=maps(args.verdicts_out),
    )
    return config
