"""rmw_zenoh's wire grammar, pure: data keys, liveliness tokens, QoS strings, attachments.

What a ROS 2 node using ``rmw_zenoh_cpp`` puts on Zenoh, so that the bridge looks like one:

- data key of a topic: ``<domain>/<fully qualified name without outer slashes>/<DDS type
  name>/<type hash>``, e.g. ``0/chatter/std_msgs::msg::dds_::String_/RIHS01_df66…``. The DDS
  type name of ``pkg/msg/Name`` is ``pkg::msg::dds_::Name_``; the type hash is ``RIHS01_`` +
  sha256 of the type description (REP-2016) from Iron on, ``TypeHashNotSupported`` on Humble.
- liveliness tokens (the ROS graph: ``ros2 node list``, ``ros2 topic list/info``)::

    @ros2_lv/<domain>/<session id>/<node id>/<node id>/NN/<enclave>/<namespace>/<node name>
    @ros2_lv/<domain>/<session id>/<node id>/<entity id>/MP|MS/<enclave>/<namespace>/
        <node name>/<topic>/<DDS type name>/<type hash>/<qos>

  every name "mangled" (each ``/`` becomes ``%``; the root namespace and enclave ``/`` are
  ``%``); the session id is the Zenoh id as Zenoh prints it.
- QoS string: ``<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan
  s>,<ns>:<liveliness>,<lease s>,<ns>`` with rmw's enum numbers, each field left empty when
  it equals rmw_zenoh's default (reliable, volatile, keep-last, depth 42, infinite
  durations, automatic liveliness): a depth-10 reliable publisher is ``::,10:,:,:,,``. A
  depth of 0 is first replaced by 42, as rmw_zenoh does, so keep-all is ``::2,:,:,:,,``.
- per-sample attachment, as zenoh's ``ext`` serializer writes it: int64 sequence number,
  int64 source timestamp (ns), then the 16-byte publisher gid as a sequence (one LEB128
  length byte, 16, and the bytes) — 33 bytes, little-endian.
- the gid of an entity is the XXH3-128 hash of its liveliness key expression, low 64 bits
  then high 64 bits, each little-endian.

Other nodes' tokens are read back (:func:`parse_endpoint`) to tell a user whose topic is
published under another type or type hash (another distro) than the bridge expects.

Nothing here touches Zenoh; tests check every string against rmw_zenoh's own examples.
"""

from __future__ import annotations

import enum
import re
import struct
from dataclasses import dataclass

import xxhash

from middleware import ConfigError, printable

ADMIN_SPACE = "@ros2_lv"
GID_BYTES = 16
ATTACHMENT_BYTES = 8 + 8 + 1 + GID_BYTES
HUMBLE_TYPE_HASH = "TypeHashNotSupported"
# Distros whose rmw_zenoh puts a RIHS01 hash in keys; Humble has no type hashes.
DISTROS = ("humble", "jazzy", "kilted", "rolling")
_ATTACHMENT = struct.Struct("<qqB")


class EntityKind(enum.Enum):
    """The entity kinds of liveliness tokens."""

    NODE = "NN"
    PUBLISHER = "MP"
    SUBSCRIPTION = "MS"


class Reliability(enum.IntEnum):
    """rmw_qos_reliability_policy_e."""

    RELIABLE = 1
    BEST_EFFORT = 2


class Durability(enum.IntEnum):
    """rmw_qos_durability_policy_e."""

    TRANSIENT_LOCAL = 1
    VOLATILE = 2


class History(enum.IntEnum):
    """rmw_qos_history_policy_e."""

    KEEP_LAST = 1
    KEEP_ALL = 2


# rmw_zenoh's own default profile: a field equal to it is written as an empty string.
DEFAULT_DEPTH = 42


@dataclass(frozen=True, slots=True)
class Qos:
    """The QoS of one ROS 2 entity (deadline, lifespan and liveliness: rmw_zenoh defaults)."""

    reliability: Reliability = Reliability.RELIABLE
    depth: int = 10
    history: History = History.KEEP_LAST
    durability: Durability = Durability.VOLATILE

    def __post_init__(self) -> None:
        if self.depth < 0:
            raise ConfigError(f"QoS depth must be >= 0, got {self.depth}")

    @classmethod
    def sensor_data(cls) -> Qos:
        """ROS 2's sensor-data profile: best effort, keep last 5."""
        return cls(Reliability.BEST_EFFORT, 5)

    def keyexpr(self) -> str:
        """The QoS chunk of a liveliness token."""

        def field(value: int, default: int) -> str:
            return "" if value == default else str(int(value))

        # rmw_zenoh first replaces a depth of 0 (rclcpp's keep-all) by its default depth.
        depth = self.depth or DEFAULT_DEPTH
        return (
            f"{field(self.reliability, Reliability.RELIABLE)}:"
            f"{field(self.durability, Durability.VOLATILE)}:"
            f"{field(self.history, History.KEEP_LAST)},{field(depth, DEFAULT_DEPTH)}:"
            ",:,:,,"
        )


def mangle(name: str) -> str:
    """A ROS name as one key-expression chunk: ``/`` → ``%`` (an empty name is ``%``)."""
    return name.replace("/", "%") if name else "%"


# One token of a ROS 2 name (rmw's full topic name rules): letters, digits and '_', not
# starting with a digit.
_NAME_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def fully_qualified(topic: str, namespace: str = "/") -> str:
    """``/ns/topic`` for a relative ``topic`` in ``namespace``; absolute topics unchanged.
    ConfigError for a name no ROS 2 node can use (as rcl refuses it): a node could never
    meet the bridge on it, which would wait for it silently."""
    if topic.startswith("~") or "{" in topic:
        raise ConfigError(
            f"bad ROS 2 topic name {topic!r}: '~' and '{{}}' substitutions name the bridge's "
            "own node; write the topic in full, e.g. /my_detector/detections"
        )
    full = topic if topic.startswith("/") else namespace.rstrip("/") + "/" + topic
    tokens = full[1:].split("/")
    if not topic or not all(_NAME_TOKEN.fullmatch(t) for t in tokens):
        raise ConfigError(
            f"bad ROS 2 topic name {topic!r}: use e.g. /camera/image_raw (letters, digits and "
            "'_' between single '/', no token starting with a digit)"
        )
    return full


def dds_type_name(ros_type: str) -> str:
    """``sensor_msgs/msg/Image`` → ``sensor_msgs::msg::dds_::Image_``."""
    parts = ros_type.split("/")
    if len(parts) != 3 or not all(parts):
        raise ConfigError(f"bad ROS 2 type name {ros_type!r}: expected pkg/msg/Name")
    package, kind, name = parts
    return f"{package}::{kind}::dds_::{name}_"


def type_hash(rihs01: str, distro: str) -> str:
    """The type-hash chunk for ``distro``: the RIHS01 hash, or Humble's placeholder."""
    if distro not in DISTROS:
        raise ConfigError(f"unknown ROS 2 distro {distro!r}; use one of {', '.join(DISTROS)}")
    return HUMBLE_TYPE_HASH if distro == "humble" else rihs01


def data_key(domain_id: int, topic_fqn: str, ros_type: str, hash_chunk: str) -> str:
    """The key expression samples of ``topic_fqn`` travel on."""
    return f"{domain_id}/{topic_fqn.strip('/')}/{dds_type_name(ros_type)}/{hash_chunk}"


@dataclass(frozen=True, slots=True)
class NodeIdentity:
    """Who the bridge is in the ROS graph: one node in one Zenoh session."""

    domain_id: int
    session_id: str
    node_name: str
    namespace: str = "/"
    enclave: str = "/"
    node_id: int = 0

    def __post_init__(self) -> None:
        if not 0 <= self.domain_id <= 232:
            raise ConfigError(f"ROS domain id must be 0..232, got {self.domain_id}")
        if not self.node_name or not self.node_name.replace("_", "a").isalnum():
            raise ConfigError(
                f"bad ROS 2 node name {self.node_name!r}: letters, digits and '_' only"
            )
        if not self.namespace.startswith("/"):
            raise ConfigError(f"ROS 2 namespace must start with '/', got {self.namespace!r}")

    def _prefix(self, entity_id: int, kind: EntityKind) -> str:
        return (
            f"{ADMIN_SPACE}/{self.domain_id}/{self.session_id}/{self.node_id}/{entity_id}/"
            f"{kind.value}/{mangle(self.enclave)}/{mangle(self.namespace)}/{self.node_name}"
        )

    def node_token(self) -> str:
        """The node's liveliness token (``ros2 node list``)."""
        return self._prefix(self.node_id, EntityKind.NODE)

    def endpoint_token(
        self,
        entity_id: int,
        kind: EntityKind,
        topic_fqn: str,
        ros_type: str,
        hash_chunk: str,
        qos: Qos,
    ) -> str:
        """A publisher's or subscription's liveliness token (``ros2 topic info -v``)."""
        return (
            f"{self._prefix(entity_id, kind)}/{mangle(topic_fqn)}/{dds_type_name(ros_type)}/"
            f"{hash_chunk}/{qos.keyexpr()}"
        )


@dataclass(frozen=True, slots=True)
class Endpoint:
    """A publisher or subscription some ROS 2 node announced (see :func:`parse_endpoint`)."""

    session_id: str
    kind: EntityKind
    topic: str
    dds_type: str
    type_hash: str


def parse_endpoint(token: str) -> Endpoint | None:
    """The publisher or subscription a liveliness token names; None for any other key."""
    parts = token.split("/")
    # Chunks after the QoS (newer rmw_zenoh may add one) do not change what is named.
    if len(parts) < 13 or parts[0] != ADMIN_SPACE or not all(parts):
        return None
    kinds = {EntityKind.PUBLISHER.value, EntityKind.SUBSCRIPTION.value}
    if parts[5] not in kinds:
        return None
    return Endpoint(
        parts[2], EntityKind(parts[5]), parts[9].replace("%", "/"), parts[10], parts[11]
    )


# Distinct remarks a graph check logs at most, and their length (a peer declares tokens of
# any number of made-up types, named as long as a key expression may be).
MAX_REMARKS = 16
REMARK_CHARS = 400


class TopicCheck:
    """Says, once per kind of mismatch, when another node's endpoint on one of the bridge's
    topics uses another type or type hash than the bridge: their samples travel on another
    data key, so the two never meet (the usual cause: ``--ros-distro`` is not the system's).

    Feed it every liveliness token seen (one caller at a time); pure, no Zenoh.
    """

    def __init__(self, own_session_id: str, expected: dict[str, tuple[str, str]]) -> None:
        self._own = own_session_id
        self._expected = expected  # topic -> (DDS type name, type-hash chunk)
        self._said: set[tuple[str, str, str]] = set()
        self._quiet = False  # MAX_REMARKS said: the rest is not logged

    def check(self, token: str) -> str | None:
        """A one-line warning for a newly seen mismatch, else None."""
        endpoint = parse_endpoint(token)
        if endpoint is None or endpoint.session_id == self._own:
            return None
        expected = self._expected.get(endpoint.topic)
        if expected is None or expected == (endpoint.dds_type, endpoint.type_hash):
            return None
        key = (endpoint.topic, endpoint.dds_type, endpoint.type_hash)
        if key in self._said or self._quiet:
            return None
        if len(self._said) >= MAX_REMARKS:
            # A token costs a peer nothing: one per made-up hash must not be a line each.
            self._quiet = True
            return f"{MAX_REMARKS} mismatched types said; further ones are not logged"
        self._said.add(key)
        dds_type, hash_chunk = expected
        role = "published" if endpoint.kind is EntityKind.PUBLISHER else "subscribed"
        if endpoint.dds_type != dds_type:
            hint = f"another message type: the bridge carries {dds_type} on it"
        elif endpoint.type_hash == HUMBLE_TYPE_HASH:
            hint = "that is a Humble system: run the bridge with --ros-distro humble"
        elif hash_chunk == HUMBLE_TYPE_HASH:
            hint = "that is a Jazzy or later system: give the bridge its --ros-distro"
        else:
            hint = "another definition of the type: check --ros-distro"
        return printable(
            f"ROS 2 topic {endpoint.topic} is {role} as {endpoint.dds_type} with type hash "
            f"{endpoint.type_hash}, the bridge uses {hash_chunk}, so they never meet; {hint}",
            REMARK_CHARS,
        )


def gid(token: str) -> bytes:
    """The 16-byte gid rmw_zenoh derives from an entity's liveliness key expression."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(GID_BYTES, "little")


@dataclass(frozen=True, slots=True)
class Attachment:
    """The attachment every rmw_zenoh sample carries."""

    sequence_number: int
    source_timestamp_ns: int
    source_gid: bytes

    def encode(self) -> bytes:
        if len(self.source_gid) != GID_BYTES:
            raise ValueError(f"gid must be {GID_BYTES} bytes, got {len(self.source_gid)}")
        return (
            _ATTACHMENT.pack(self.sequence_number, self.source_timestamp_ns, GID_BYTES)
            + self.source_gid
        )

    @classmethod
    def decode(cls, data: bytes) -> Attachment:
        """ValueError for anything but the 33 bytes rmw_zenoh writes."""
        if len(data) != ATTACHMENT_BYTES:
            raise ValueError(f"attachment of {len(data)} bytes, expected {ATTACHMENT_BYTES}")
        seq, stamp, length = _ATTACHMENT.unpack_from(data)
        if length != GID_BYTES:
            raise ValueError(f"attachment gid length {length}, expected {GID_BYTES}")
        return cls(seq, stamp, bytes(data[_ATTACHMENT.size :]))
