"""Samples lost between a ROS 2 publisher and the bridge, from rmw_zenoh's sequence numbers."""

from __future__ import annotations

import itertools

from services.nodes.ros2._rmw import Attachment, EntityKind, NodeIdentity, Qos, gid
from services.nodes.ros2._sequence import (
    CONFIRM_GAP,
    MAX_GAP,
    MAX_RATE_HZ,
    SequenceTracker,
    SequenceWatch,
)

A, B = b"a" * 16, b"b" * 16


def test_a_gap_in_one_publishers_numbers_is_counted_as_lost() -> None:
    tracker = SequenceTracker()
    for seq in (5, 6, 9, 10):
        tracker.sample(A, seq)
    assert tracker.lost == 2


def test_publishers_are_counted_apart_and_duplicates_or_reorderings_lose_nothing() -> None:
    tracker = SequenceTracker()
    for source, seq in ((A, 1), (B, 100), (A, 2), (B, 101), (A, 2), (A, 1), (B, 103)):
        tracker.sample(source, seq)
    assert tracker.lost == 1


def test_a_publisher_announced_after_the_graph_was_known_counts_its_first_losses() -> None:
    tracker = SequenceTracker()
    tracker.announce(A)  # already there when the bridge came: its numbers start anywhere
    tracker.settle()
    tracker.sample(A, 500)
    tracker.announce(B)  # started after the bridge: its first sample was number 1
    tracker.sample(B, 3)
    assert tracker.lost == 2


def test_a_fresh_publishers_sample_may_arrive_before_its_token() -> None:
    tracker = SequenceTracker()
    tracker.settle()
    tracker.sample(B, 4)
    assert tracker.lost == 0
    tracker.announce(B)
    tracker.announce(B)
    assert tracker.lost == 3


def test_forged_numbers_cost_bounded_memory_and_an_absurd_jump_is_not_a_loss() -> None:
    tracker = SequenceTracker(max_publishers=8)
    for i in range(1000):
        tracker.sample(i.to_bytes(16, "little"), 1)
    assert len(tracker._publishers) == 8
    tracker.sample(A, 1)
    tracker.sample(A, 2 + MAX_GAP + 1)
    tracker.sample(A, 0)  # not a number rmw_zenoh writes
    tracker.sample(A, 2 + MAX_GAP + 2)  # continued: a reset, not a loss of a million
    assert (tracker.lost, tracker.jumps) == (0, 1)


def test_one_forged_number_far_ahead_neither_adds_losses_nor_stops_the_count() -> None:
    tracker = SequenceTracker()
    for seq in (1, 2, 3):
        tracker.sample(A, seq)
    tracker.sample(A, 1 << 62)  # a peer forging A's gid
    tracker.sample(A, 4 + (1 << 20))  # and one that would add a million phantom losses
    for seq in (5, 8, 10):  # the real publisher goes on, losing 4, 6, 7 and 9
        tracker.sample(A, seq)
    assert (tracker.lost, tracker.jumps) == (4, 2)


def test_a_real_burst_of_losses_is_counted_once_the_next_sample_continues_it() -> None:
    tracker = SequenceTracker()
    tracker.sample(A, 1)
    tracker.sample(A, 1 + CONFIRM_GAP + 500)  # a link down for a while at 1 kHz
    assert tracker.lost == 0  # not yet: one number far ahead may be forged
    tracker.sample(A, 2 + CONFIRM_GAP + 500)
    assert (tracker.lost, tracker.jumps) == (CONFIRM_GAP + 499, 0)


def test_the_watch_reads_attachments_and_the_graphs_tokens() -> None:
    node = NodeIdentity(0, "aa" * 16, "driver")
    token = node.endpoint_token(
        1, EntityKind.PUBLISHER, "/camera/image_raw", "sensor_msgs/msg/Image", "h", Qos()
    )
    other = node.endpoint_token(
        2, EntityKind.PUBLISHER, "/other", "sensor_msgs/msg/Image", "h", Qos()
    )
    ticks = itertools.count(0, 1_000_000_000)  # a sample a second: any gap is possible
    watch = SequenceWatch("/camera/image_raw", clock=lambda: next(ticks))
    watch.settle()
    watch.announce(token)
    watch.announce(other)
    watch.announce("@ros2_lv/0/garbage")
    source = gid(token)
    for seq in (3, 4, 7):
        watch.observe(Attachment(seq, 0, source).encode())
    watch.observe(None)
    watch.observe(b"short")
    assert watch.take_lost().lost == 2 + 2
    assert watch.take_lost().lost == 0  # each loss is taken once


def test_numbers_far_ahead_of_what_a_publisher_could_send_are_jumps_not_losses() -> None:
    # A peer floods a publisher's gid with samples 1,000 numbers apart, 10,000 a second.
    tracker = SequenceTracker()
    t_ns = 0
    tracker.sample(A, 1, t_ns)
    for n in range(1, 10_001):
        t_ns += 100_000
        tracker.sample(A, 1 + 1_000 * n, t_ns)
    # At most what MAX_RATE_HZ allows in the second it took, not 10 million.
    assert tracker.lost <= MAX_RATE_HZ
    assert tracker.jumps > 9_000


def test_a_link_down_for_seconds_is_counted_in_full() -> None:
    tracker = SequenceTracker()
    tracker.sample(A, 1, 0)
    tracker.sample(A, 2, 1_000_000)
    tracker.sample(A, 3_003, 3_001_000_000)  # 1 kHz, 3 s without a sample
    tracker.sample(A, 3_004, 3_002_000_000)
    assert (tracker.lost, tracker.jumps) == (3_000, 0)


def test_a_fresh_token_with_a_first_number_far_ahead_is_a_jump_not_a_million_lost() -> None:
    tracker = SequenceTracker()
    tracker.settle()
    for i in range(100):  # a peer declares tokens, each with one sample numbered 2**20
        source = i.to_bytes(16, "little")
        tracker.announce(source, 1_000 * i)
        tracker.sample(source, 1 << 20, 1_000 * i + 1_000)
    assert (tracker.lost, tracker.jumps) == (0, 100)
    # A real publisher started after the bridge: its first two samples never came.
    tracker.announce(B, 10_000_000)
    tracker.sample(B, 3, 11_000_000)
    assert (tracker.lost, tracker.jumps) == (2, 100)
