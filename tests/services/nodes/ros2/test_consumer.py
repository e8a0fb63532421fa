"""The loop's pure parts: the leading header of any result, the outstanding images, and the
result type read from the ROS graph."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from middleware import ConfigError
from services.nodes.ros2._cdr import DETECTIONS, IMAGE, Codec
from services.nodes.ros2._config import Mapping, Ros2Config
from services.nodes.ros2._consumer import (
    MAX_RESULT_TYPES,
    ConsumerCounts,
    DoneTopic,
    GateBook,
    Header,
    HeaderError,
    Outstanding,
    decode_header,
    ros_type_of,
)
from services.nodes.ros2._rmw import MAX_REMARKS, EntityKind, NodeIdentity, Qos, dds_type_name

STAMP = 1_700_000_000_123_456_789


def test_the_header_of_a_detection_array_is_read_without_its_type() -> None:
    codec = Codec("jazzy")
    raw = bytes(codec.encode_detections(STAMP, "camera_optical", [(7, [0.0] * 8)]))
    assert decode_header(raw) == Header(STAMP, "camera_optical")


def test_the_header_of_a_big_endian_message_is_read() -> None:
    text = b"cam\0"
    raw = b"\x00\x00\x00\x00" + struct.pack(">iII", 12, 34, len(text)) + text
    assert decode_header(raw) == Header(12_000_000_034, "cam")


@pytest.mark.parametrize(
    ("raw", "match"),
    [
        (b"", "cannot hold"),
        (b"\x00\x07\x00\x00" + bytes(16), "encapsulation 0007"),
        (b"\x00\x01\x00\x00" + struct.pack("<iII", 1, 10**9, 1) + b"\0", "nanosec"),
        (b"\x00\x01\x00\x00" + struct.pack("<iII", -1, 0, 1) + b"\0", "sec=-1"),
        (b"\x00\x01\x00\x00" + struct.pack("<iII", 1, 0, 99) + b"ab\0", "frame_id of 99"),
        (b"\x00\x01\x00\x00" + struct.pack("<iII", 1, 0, 0) + b"\0", "frame_id of 0"),
        (b"\x00\x01\x00\x00" + struct.pack("<iII", 1, 0, 2) + b"ab", "NUL"),
        (b"\x00\x01\x00\x00" + struct.pack("<iII", 1, 0, 2) + b"\xff\0", "UTF-8"),
    ],
)
def test_an_unreadable_header_is_a_header_error(raw: bytes, match: str) -> None:
    with pytest.raises(HeaderError, match=match):
        decode_header(raw)


@settings(deadline=None)  # pure and small: no wall-clock bound per example
@given(st.binary(max_size=64))
def test_any_bytes_give_a_header_or_a_header_error(raw: bytes) -> None:
    try:
        decode_header(raw)
    except HeaderError:
        pass


def test_an_answer_frees_its_slot_and_a_second_answer_matches_nothing() -> None:
    ledger = Outstanding(2, 1000)
    assert ledger.add(10, 0) and ledger.add(20, 5)
    assert not ledger.add(30, 6)  # every slot taken
    resolved = ledger.answer(20, 50)
    assert not isinstance(resolved, str)
    assert (resolved.stamp_ns, resolved.resolved_ns - resolved.published_ns) == (20, 45)
    assert ledger.answer(20, 60) == "unmatched"
    assert ledger.answer(99, 60) == "unmatched"
    assert len(ledger) == 1
    assert ledger.counts() == ConsumerCounts(published=2, answered=1, unmatched=2, outstanding=1)


def test_an_unanswered_image_times_out_once_and_its_late_answer_is_told_apart() -> None:
    ledger = Outstanding(3, 100)
    ledger.add(10, 0)
    ledger.add(20, 50)
    assert ledger.next_deadline_ns() == 100
    assert ledger.expire(99) == []
    gone = ledger.expire(100)
    assert [(g.stamp_ns, g.answered) for g in gone] == [(10, False)]
    assert ledger.next_deadline_ns() == 200  # 20's clock started when 10 left, at 100
    assert ledger.answer(10, 120) == "late"
    assert [g.stamp_ns for g in ledger.expire(10_000)] == [20]
    assert ledger.next_deadline_ns() is None
    assert ledger.counts() == ConsumerCounts(published=2, timed_out=2, late=1)


def test_images_queued_behind_a_slow_node_time_out_only_on_its_time_for_one() -> None:
    """A node that takes 500 of a 1000 timeout per image, three images queued at once:
    each answered in turn, none timed out (counted from their publishing, the third had
    waited 1500 when answered)."""
    ledger = Outstanding(3, 1000)
    for stamp in (1, 2, 3):
        assert ledger.add(stamp, 0)
    for stamp in (1, 2, 3):
        now = 500 * stamp
        assert ledger.expire(now) == []
        assert not isinstance(ledger.answer(stamp, now), str)
    assert ledger.counts() == ConsumerCounts(published=3, answered=3)


def test_a_node_that_never_answers_frees_one_slot_per_timeout() -> None:
    ledger = Outstanding(3, 100)
    for stamp in (1, 2, 3):
        ledger.add(stamp, stamp)
    assert [g.stamp_ns for g in ledger.expire(150)] == [1]
    assert ledger.next_deadline_ns() == 201  # 2's clock from 1's deadline, 101
    assert [g.stamp_ns for g in ledger.expire(10_000)] == [2, 3]  # late turn: both due
    assert ledger.add(4, 10_000) and ledger.next_deadline_ns() == 10_100


def test_a_withdrawn_image_was_never_published() -> None:
    ledger = Outstanding(1, 100)
    ledger.add(10, 0)
    ledger.withdraw(10)
    assert ledger.add(11, 1)
    assert ledger.counts().published == 1


def _token(topic: str, ros_type: str, hash_chunk: str, kind: EntityKind) -> str:
    node = NodeIdentity(0, "a1b2", "yolo")
    return node.endpoint_token(3, kind, topic, ros_type, hash_chunk, Qos())


def test_every_result_type_a_publisher_announces_is_listened_to() -> None:
    done = DoneTopic("/yolo/detections")
    hash_chunk = Codec("jazzy").rihs01(DETECTIONS)
    # Subscriptions and other topics say nothing about the publisher's type.
    assert done.feed(_token("/yolo/detections", IMAGE, "h", EntityKind.SUBSCRIPTION)) is None
    assert done.feed(_token("/other", IMAGE, "h", EntityKind.PUBLISHER)) is None
    assert done.feed("@ros2_lv/0/garbage") is None
    assert done.found == []
    # A peer's token of another type first (anyone can declare one) does not shut out the
    # node's own: both are listened to.
    forged = _token("/yolo/detections", "std_msgs/msg/String", "RIHS01_00", EntityKind.PUBLISHER)
    assert done.feed(forged) is None
    real = _token("/yolo/detections", DETECTIONS, hash_chunk, EntityKind.PUBLISHER)
    assert done.feed(real) is None and done.feed(real) is None
    assert [(t.ros_type, t.type_hash) for t in done.found] == [
        ("std_msgs/msg/String", "RIHS01_00"),
        (DETECTIONS, hash_chunk),
    ]
    # Bounded: a peer inventing types costs at most MAX_RESULT_TYPES entries.
    for i in range(2 * MAX_RESULT_TYPES):
        said = done.feed(
            _token("/yolo/detections", f"my_msgs/msg/T{i}", "RIHS01_00", EntityKind.PUBLISHER)
        )
    assert len(done.found) == MAX_RESULT_TYPES
    assert said is not None and "hears every type" in said


@pytest.mark.parametrize("ros_type", [DETECTIONS, "my_msgs/msg/Done", "a_b/msg/C_d"])
def test_dds_type_names_turn_back_into_ros_type_names(ros_type: str) -> None:
    assert ros_type_of(dds_type_name(ros_type)) == ros_type


@pytest.mark.parametrize(
    "bad", ["Detection2DArray", "a::msg::Name_", "a::msg::dds_::Name", "a::b::dds_::_"]
)
def test_other_names_are_not_type_names(bad: str) -> None:
    with pytest.raises(ValueError, match="not a DDS type name"):
        ros_type_of(bad)


def test_the_loop_needs_one_image_out_mapping_or_its_name() -> None:
    one = (Mapping("mediator/images", "/sharp"),)
    two = (*one, Mapping("camera/images", "/raw"))
    assert Ros2Config(image_out=one, consumer_done="/det").consumer_mapping == one[0]
    assert Ros2Config(image_out=one).consumer_mapping is None
    with pytest.raises(ConfigError, match="one --image-out mapping"):
        Ros2Config(image_out=two, consumer_done="/det")
    with pytest.raises(ConfigError, match="not an --image-out buffer"):
        Ros2Config(image_out=two, consumer_done="/det", consumer_input="x/y")
    config = Ros2Config(image_out=two, consumer_done="/det", consumer_input="camera/images")
    assert config.consumer_mapping == two[1]
    with pytest.raises(ConfigError, match="--consumer-queue"):
        Ros2Config(image_out=one, consumer_done="/det", consumer_queue=0)
    # Beyond what a producer grants one flow queue: said at start, naming the flag.
    with pytest.raises(ConfigError, match=r"--consumer-queue must be 1\.\.32768 .* got 600000"):
        Ros2Config(image_out=one, consumer_done="/det", consumer_queue=600_000)
    assert Ros2Config(image_out=one, consumer_done="/det", consumer_queue=32768)


@pytest.mark.parametrize(
    "extra",
    [{}, {"image_in": "/camera/image_raw"}, {"verdicts_out": (Mapping("m/decisions", "/v"),)}],
)
def test_the_loop_refuses_a_result_topic_the_bridge_carries_itself(
    extra: dict[str, object],
) -> None:
    topics = {"image_in": "/camera/image_raw", "verdicts_out": "/v"}
    done = next((topics[k] for k in extra), "/sharp")
    with pytest.raises(ConfigError, match=f"--consumer-done {done}: a topic this bridge carries"):
        Ros2Config(
            image_out=(Mapping("mediator/images", "/sharp"),),
            consumer_done=done,
            **extra,  # type: ignore[arg-type]
        )


def test_each_resolution_is_owed_one_gate_take() -> None:
    book = GateBook(100)
    book.owe(2, 0)
    assert book.debt == 2
    assert book.taken(1, 10) == 0 and book.debt == 1  # one notification not there yet
    assert book.taken(1, 20) == 0 and book.debt == 0


def test_a_debt_no_gate_notification_comes_for_is_cancelled_after_the_timeout() -> None:
    book = GateBook(100)
    book.owe(1, 0)
    assert book.taken(0, 100) == 0 and book.debt == 1
    assert book.taken(0, 101) == 1 and book.debt == 0
    book.owe(1, 200)  # a new debt starts its own clock
    assert book.taken(0, 250) == 0 and book.debt == 1


def test_only_a_surplus_that_lasts_the_timeout_is_freed() -> None:
    book = GateBook(100)
    assert book.surplus(3, 3, 0) == 0
    assert book.surplus(4, 3, 10) == 0  # an image between the feed and the ledger
    assert book.surplus(3, 3, 50) == 0  # gone: its clock restarts
    assert book.surplus(4, 3, 120) == 0
    assert book.surplus(4, 3, 220) == 0
    assert book.surplus(5, 3, 221) == 2
    assert book.surplus(5, 3, 222) == 0  # freed: a new surplus starts its own clock


def test_no_surplus_is_freed_while_a_debt_is_paid() -> None:
    book = GateBook(100)
    book.owe(1, 0)
    assert book.surplus(2, 0, 0) == 0
    assert book.surplus(2, 0, 500) == 0


def test_a_deficit_that_lasts_the_timeout_spares_as_many_resolutions() -> None:
    # The gate registered after image 1 was put; image 1's answer took image 2's gate entry
    # (a notification there at once): the node holds 2 and 3, the gate counts 3 alone.
    # Before, that lasted for good: the mediator saw the node one image less busy.
    book = GateBook(100)
    assert book.owe(1, 0) == 0 and book.taken(1, 0) == 0  # image 1 answered, 2's entry taken
    assert book.surplus(1, 2, 10) == 0  # gate 1, ledger 2: a young deficit
    assert book.owe(1, 20) == 0 and book.taken(1, 20) == 0  # an answer during it: paid
    assert book.surplus(0, 1, 30) == 0 and book.spare == 0
    assert book.surplus(0, 1, 111) == 0 and book.spare == 1  # it lasted the timeout
    assert book.surplus(0, 1, 300) == 0 and book.spare == 1  # not counted twice
    assert book.owe(1, 310) == 1 and book.debt == 0  # the next resolution takes nothing
    assert book.surplus(0, 0, 320) == 0 and book.spare == 0


def test_a_gate_note_later_than_its_image_is_no_deficit() -> None:
    book = GateBook(100)
    for now in range(0, 1000, 50):  # a note a few ms behind its image, again and again
        assert book.surplus(0, 1, now) == 0
        assert book.surplus(1, 1, now + 5) == 0
    assert book.spare == 0


def test_made_up_types_past_the_bound_cost_one_line_and_no_memory() -> None:
    done = DoneTopic("/yolo/detections")
    said = [
        done.feed(_token("/yolo/detections", "ba-d/msg/T", f"RIHS01_{i}", EntityKind.PUBLISHER))
        for i in range(1000)
    ]
    lines = [s for s in said if s is not None]
    assert len(lines) == MAX_REMARKS + 1 and "not logged" in lines[-1]
    assert len(done._said) <= MAX_REMARKS + 1


def test_a_node_subscribing_with_a_queue_shorter_than_the_loops_is_said_once() -> None:
    from services.nodes.ros2._consumer import InputDepthCheck
    from services.nodes.ros2._rmw import History, Reliability

    check = InputDepthCheck("/camera/image_sharp", 3)

    def subscription(session: str, qos: Qos, topic: str = "/camera/image_sharp") -> str:
        node = NodeIdentity(0, session, "yolo")
        return node.endpoint_token(1, EntityKind.SUBSCRIPTION, topic, IMAGE, "h", qos)

    # Deep enough, keep-all, rmw_zenoh's default (an empty depth), another topic: nothing.
    assert check.feed(subscription("a1", Qos(Reliability.BEST_EFFORT, 5))) is None
    assert check.feed(subscription("a2", Qos(depth=1, history=History.KEEP_ALL))) is None
    assert check.feed(subscription("a3", Qos(depth=42))) is None
    assert check.feed(subscription("a4", Qos(depth=1), "/other")) is None
    # A "latest image only" detector: its middleware drops what the loop counts as held.
    said = check.feed(subscription("b1", Qos(Reliability.BEST_EFFORT, 1)))
    assert said is not None and "keeps 1 image(s)" in said and "--consumer-queue 1" in said
    assert check.feed(subscription("b1", Qos(depth=2))) is None  # once per node's session


def test_a_result_type_known_to_start_with_no_header_is_said_at_once() -> None:
    # A node publishing std_msgs/String (JSON, say) on the result topic: no result can
    # free a slot, and the user saw only a cryptic bad-result line and every image timing
    # out. Said when its token names the type; still listened to (a name may be redefined).
    codec = Codec("jazzy")
    done = DoneTopic("/yolo/detections", codec.first_field)
    string = _token("/yolo/detections", "std_msgs/msg/String", "RIHS01_00", EntityKind.PUBLISHER)
    said = done.feed(string)
    assert said is not None
    assert "std_msgs/msg/String, whose first field is string, not a std_msgs/msg/Header" in said
    assert "--consumer-timeout-ms" in said
    assert said.endswith("(as vision_msgs/msg/Detection2DArray)"), said  # whole, not cut
    assert done.feed(string) is None  # once
    assert [t.ros_type for t in done.found] == ["std_msgs/msg/String"]
    # Types that lead with a Header, and types the bridge does not know, say nothing.
    for ros_type in (DETECTIONS, "my_msgs/msg/Done"):
        assert done.feed(_token("/yolo/detections", ros_type, "h", EntityKind.PUBLISHER)) is None
    assert codec.first_field(DETECTIONS) == "std_msgs/msg/Header"
    assert codec.first_field("my_msgs/msg/Done") is None
