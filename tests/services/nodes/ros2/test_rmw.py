"""rmw_zenoh's wire grammar against the examples of its design document (docs/design.md of
ros2/rmw_zenoh) and against zenoh's own serializer."""

from __future__ import annotations

import pytest
import zenoh.ext

from middleware import ConfigError
from services.nodes.ros2._cdr import Codec
from services.nodes.ros2._rmw import (
    ATTACHMENT_BYTES,
    HUMBLE_TYPE_HASH,
    MAX_REMARKS,
    REMARK_CHARS,
    Attachment,
    Endpoint,
    EntityKind,
    History,
    NodeIdentity,
    Qos,
    Reliability,
    TopicCheck,
    data_key,
    dds_type_name,
    fully_qualified,
    gid,
    mangle,
    parse_endpoint,
    type_hash,
)

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
ADD_TWO_INTS_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"


def test_rosbags_computes_the_design_documents_string_hash() -> None:
    for distro in ("jazzy", "kilted", "rolling"):
        assert Codec(distro).rihs01("std_msgs/msg/String") == STRING_HASH


def test_humble_keys_carry_no_type_hash() -> None:
    assert type_hash(STRING_HASH, "humble") == HUMBLE_TYPE_HASH == "TypeHashNotSupported"
    assert type_hash(STRING_HASH, "jazzy") == STRING_HASH
    with pytest.raises(ConfigError, match="unknown ROS 2 distro 'foxy'"):
        type_hash(STRING_HASH, "foxy")


@pytest.mark.parametrize(
    ("domain", "topic", "ros_type", "hash_", "key"),
    [
        (
            0,
            "/chatter",
            "std_msgs/msg/String",
            STRING_HASH,
            f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}",
        ),
        (
            0,
            "/robot1/chatter",
            "std_msgs/msg/String",
            STRING_HASH,
            f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}",
        ),
        (
            2,
            "/add_two_ints",
            "example_interfaces/srv/AddTwoInts",
            ADD_TWO_INTS_HASH,
            f"2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/{ADD_TWO_INTS_HASH}",
        ),
    ],
)
def test_data_keys_match_the_design_document(
    domain: int, topic: str, ros_type: str, hash_: str, key: str
) -> None:
    assert data_key(domain, topic, ros_type, hash_) == key


def test_qos_strings_match_the_design_document() -> None:
    assert Qos(Reliability.RELIABLE, 10).keyexpr() == "::,10:,:,:,,"  # listener
    assert Qos(Reliability.RELIABLE, 7).keyexpr() == "::,7:,:,:,,"  # talker
    assert Qos.sensor_data().keyexpr() == "2::,5:,:,:,,"
    assert Qos(Reliability.RELIABLE, 42).keyexpr() == "::,:,:,:,,"  # all rmw_zenoh defaults


def test_depth_zero_is_written_as_rmw_zenohs_default_depth() -> None:
    # rmw_zenoh replaces a depth of 0 (what rclcpp's KeepAll() sets) by its default, 42,
    # before it writes the token, so the depth field is empty like any default.
    assert Qos(Reliability.RELIABLE, 0, History.KEEP_ALL).keyexpr() == "::2,:,:,:,,"
    assert Qos(Reliability.BEST_EFFORT, 0).keyexpr() == "2::,:,:,:,,"


def test_liveliness_tokens_match_the_design_document() -> None:
    listener = NodeIdentity(2, "aac3178e146ba6f1fc6e6a4085e77f21", "listener")
    assert (
        listener.node_token() == "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    )
    assert listener.endpoint_token(
        10, EntityKind.SUBSCRIPTION, "/chatter", "std_msgs/msg/String", STRING_HASH, Qos()
    ) == (
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/"
        f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,10:,:,:,,"
    )
    talker = NodeIdentity(2, "8b20917502ee955ac4476e0266340d5c", "talker")
    assert talker.endpoint_token(
        10, EntityKind.PUBLISHER, "/chatter", "std_msgs/msg/String", STRING_HASH, Qos(depth=7)
    ) == (
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
        f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,"
    )


def test_namespaces_are_mangled() -> None:
    node = NodeIdentity(0, "ab", "cam", namespace="/robot1")
    assert node.node_token() == "@ros2_lv/0/ab/0/0/NN/%/%robot1/cam"
    assert mangle("/robot1/cmd_vel") == "%robot1%cmd_vel"
    assert mangle("") == "%"
    assert fully_qualified("image_raw", "/robot1") == "/robot1/image_raw"
    assert fully_qualified("/abs", "/robot1") == "/abs"


@pytest.mark.parametrize(
    "bad",
    # The last ones are names rcl refuses, so no ROS 2 node can publish or take them: the
    # bridge waited for one silently (``~/y`` became ``/~/y``).
    ["", "/a//b", "/a/", "/a b", "/a/*", "~/y", "/{node}/y", "/camera/image-raw", "/2d/x",
     "/a.b", "/a%b", "/\u00e9"],
)  # fmt: skip
def test_bad_topic_names_are_refused(bad: str) -> None:
    with pytest.raises(ConfigError, match="bad ROS 2 topic name"):
        fully_qualified(bad)


def test_dds_type_names() -> None:
    assert dds_type_name("sensor_msgs/msg/Image") == "sensor_msgs::msg::dds_::Image_"
    with pytest.raises(ConfigError, match="expected pkg/msg/Name"):
        dds_type_name("Image")


def test_attachment_is_what_zenohs_serializer_writes() -> None:
    source_gid = bytes(range(16))
    attachment = Attachment(7, 1_700_000_000_123_456_789, source_gid)
    expected = zenoh.ext.z_serialize(
        (zenoh.ext.Int64(7), zenoh.ext.Int64(1_700_000_000_123_456_789), source_gid)
    ).to_bytes()
    assert attachment.encode() == expected
    assert len(expected) == ATTACHMENT_BYTES == 33
    assert Attachment.decode(expected) == attachment


def test_attachment_layout_is_the_design_documents() -> None:
    # 8 bytes sequence number and 8 bytes source timestamp (int64, little-endian), 1 byte
    # for the gid's length (16), then the 16 gid bytes.
    source_gid = bytes(range(0xA0, 0xB0))
    encoded = Attachment(1, 0x0102030405060708, source_gid).encode()
    assert encoded == (bytes.fromhex("0100000000000000080706050403020110") + source_gid)


@pytest.mark.parametrize("bad", [b"", bytes(32), bytes(34), bytes(16) + b"\x0f" + bytes(16)])
def test_malformed_attachments_are_refused(bad: bytes) -> None:
    with pytest.raises(ValueError, match="attachment"):
        Attachment.decode(bad)


def test_gid_is_the_xxh3_128_of_the_token_low_half_first() -> None:
    token = "@ros2_lv/0/ab/0/1/MP/%/%/n/%t/std_msgs::msg::dds_::String_/x/::,10:,:,:,,"
    value = gid(token)
    assert len(value) == 16
    assert value == gid(token) != gid(token + "x")
    # xxh3-128 of the empty string (the reference value of the xxHash test vectors).
    assert gid("") == (0x99AA06D3014798D86001C324468D497F).to_bytes(16, "little")


def test_node_identity_refuses_bad_values() -> None:
    with pytest.raises(ConfigError, match="domain id"):
        NodeIdentity(300, "ab", "n")
    with pytest.raises(ConfigError, match="node name"):
        NodeIdentity(0, "ab", "bad-name")


def test_endpoint_tokens_parse_back_to_what_they_name() -> None:
    talker = (
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
        f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,"
    )
    assert parse_endpoint(talker) == Endpoint(
        "8b20917502ee955ac4476e0266340d5c",
        EntityKind.PUBLISHER,
        "/chatter",
        "std_msgs::msg::dds_::String_",
        STRING_HASH,
    )
    node = NodeIdentity(0, "ab", "cam", namespace="/robot1")
    token = node.endpoint_token(
        3, EntityKind.SUBSCRIPTION, "/robot1/image", "sensor_msgs/msg/Image", "x", Qos()
    )
    parsed = parse_endpoint(token)
    assert parsed is not None
    assert (parsed.kind, parsed.topic, parsed.type_hash) == (
        EntityKind.SUBSCRIPTION,
        "/robot1/image",
        "x",
    )


@pytest.mark.parametrize(
    "other",
    [
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener",  # a node
        "@ros2_lv/2/f9/0/10/SS/%/%/s/%add_two_ints/example_interfaces::srv::dds_::X_/h/::,:,:,:,,",
        "@ros2_lv/2/ab/0/1/MP/%/%/n",  # cut short
        "0/chatter/std_msgs::msg::dds_::String_/h",  # a data key
    ],
)
def test_other_keys_are_not_endpoints(other: str) -> None:
    assert parse_endpoint(other) is None


def _token(session: str, kind: EntityKind, topic: str, ros_type: str, hash_: str) -> str:
    return NodeIdentity(0, session, "driver").endpoint_token(1, kind, topic, ros_type, hash_, Qos())


def test_a_topic_under_another_distros_hash_is_said_once_with_the_flag_to_change() -> None:
    image_hash = Codec("jazzy").rihs01("sensor_msgs/msg/Image")
    check = TopicCheck("own", {"/camera/image_raw": ("sensor_msgs::msg::dds_::Image_", image_hash)})
    humble = _token(
        "ab", EntityKind.PUBLISHER, "/camera/image_raw", "sensor_msgs/msg/Image", HUMBLE_TYPE_HASH
    )
    said = check.check(humble)
    assert said is not None and "--ros-distro humble" in said and "/camera/image_raw" in said
    assert check.check(humble) is None  # once
    matching = _token(
        "cd", EntityKind.PUBLISHER, "/camera/image_raw", "sensor_msgs/msg/Image", image_hash
    )
    assert check.check(matching) is None
    own = _token("own", EntityKind.SUBSCRIPTION, "/camera/image_raw", "x/msg/Y", "h")
    assert check.check(own) is None
    elsewhere = _token("ab", EntityKind.PUBLISHER, "/other", "sensor_msgs/msg/Image", "h")
    assert check.check(elsewhere) is None


def test_a_humble_bridge_is_told_of_a_jazzy_subscriber_and_of_other_types() -> None:
    check = TopicCheck("own", {"/out": ("std_msgs::msg::dds_::String_", HUMBLE_TYPE_HASH)})
    jazzy = _token("ab", EntityKind.SUBSCRIPTION, "/out", "std_msgs/msg/String", STRING_HASH)
    said = check.check(jazzy)
    assert said is not None and "subscribed" in said and "Jazzy or later" in said
    other = _token("ab", EntityKind.SUBSCRIPTION, "/out", "std_msgs/msg/Int32", "h")
    said = check.check(other)
    assert said is not None and "another message type" in said


def test_tokens_of_made_up_types_cost_a_bounded_number_of_one_line_remarks() -> None:
    check = TopicCheck("own", {"/camera/image_raw": ("sensor_msgs::msg::dds_::Image_", "h")})
    said = [
        check.check(
            _token("ab", EntityKind.PUBLISHER, "/camera/image_raw", "x/msg/Y", f"RIHS01_{i}")
        )
        for i in range(1000)
    ]
    lines = [s for s in said if s is not None]
    assert len(lines) == MAX_REMARKS + 1
    assert "not logged" in lines[-1]
    assert len(check._said) <= MAX_REMARKS  # memory too


def test_a_remark_quotes_a_peers_type_name_on_one_bounded_line() -> None:
    check = TopicCheck("own", {"/out": ("std_msgs::msg::dds_::String_", "h")})
    long_hash = "RIHS01_\n\x1b[31m" + "x" * 100_000
    said = check.check(
        _token("ab", EntityKind.SUBSCRIPTION, "/out", "std_msgs/msg/String", long_hash)
    )
    assert said is not None and "\n" not in said and "\x1b" not in said
    assert len(said) < 2 * REMARK_CHARS
