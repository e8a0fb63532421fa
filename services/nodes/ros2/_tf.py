"""The rotation between two frames from ``/tf_static``, pure, as tf2 reads it.

Each ``geometry_msgs/msg/TransformStamped`` says where ``child_frame_id`` is in
``header.frame_id`` (its parent): its rotation q turns a vector written in the child frame
into the parent frame, v_parent = R(q) v_child (tf2's convention). Only rotations matter
here: angular velocity does not depend on where a sensor sits.

A static broadcaster publishes ``tf2_msgs/msg/TFMessage`` messages on a transient-local
topic, so a late joiner receives the latest message of each. rclcpp's
``StaticTransformBroadcaster`` sends all its transforms in every message; rclpy's sends only
those of each ``sendTransform`` call, so one Python node's camera link and IMU mount may
come in two messages. As in tf2's buffer, which keeps every static transform it hears until
a newer one names the same child, a broadcaster's (keyed by its gid) transforms are merged
message by message, not replaced by its latest; where two broadcasters give a frame a
parent, the one heard last wins (tf2 keeps one static transform per child frame). The
rotation between two frames composes the chain up to their common root.

Frame names are compared without a leading ``/`` (tf2 strips it too). Bounded: at most
``MAX_BROADCASTERS`` broadcasters and ``MAX_FRAMES`` transforms each are kept, and a walk
up the tree stops at a cycle and after ``MAX_CHAIN`` links. Each step looks its frame up
through the index of which broadcaster sent it last, in O(1): merging all tables (up to
262,144 transforms) for every composition took 0.7 s along a peer's 262,144-link chain, and
a composition follows every /tf_static message, so a trickle of them held every image that
long.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

MAX_BROADCASTERS = 256
MAX_FRAMES = 1024
# Links from a frame up to its root at most: a robot's IMU and camera are a few links apart.
MAX_CHAIN = 64

Matrix = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class Transform:
    """One static transform's rotation: v_parent = rotation @ v_child."""

    parent: str
    child: str
    rotation: tuple[float, ...]  # row-major 3x3


def frame(name: str) -> str:
    """A frame name as tf2 compares it."""
    return name.lstrip("/")


# How far a quaternion's squared length may be from 1 (tf2 allows the same).
QUATERNION_TOLERANCE = 0.01


def rotation_from_quaternion(x: float, y: float, z: float, w: float) -> tuple[float, ...]:
    """The row-major rotation matrix of a unit quaternion (normalized first); ValueError for
    one that is not finite or not of unit length within ``QUATERNION_TOLERANCE`` (as tf2
    refuses such a transform: (1e-6, 0, 0, 0) is no 180-degree turn, only garbage)."""
    norm2 = x * x + y * y + z * z + w * w
    if not math.isfinite(norm2) or abs(norm2 - 1.0) > QUATERNION_TOLERANCE:
        raise ValueError(f"quaternion ({x}, {y}, {z}, {w}) is not a rotation (not unit length)")
    norm = math.sqrt(norm2)
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    return (
        1 - 2 * (y * y + z * z),
        2 * (x * y - z * w),
        2 * (x * z + y * w),
        2 * (x * y + z * w),
        1 - 2 * (x * x + z * z),
        2 * (y * z - x * w),
        2 * (x * z - y * w),
        2 * (y * z + x * w),
        1 - 2 * (x * x + y * y),
    )


class StaticTransforms:
    """The merged static transform tree (one caller at a time)."""

    def __init__(self) -> None:
        # broadcaster gid -> the transforms it sent last of each child frame, oldest first;
        # in order heard. A child frame is in one table only: its sender's last.
        self._latest: collections.OrderedDict[bytes, dict[str, Transform]] = (
            collections.OrderedDict()
        )
        self._sender: dict[str, bytes] = {}  # child frame -> whose table holds it

    def update(self, broadcaster: bytes, transforms: Iterable[Transform]) -> int:
        """A broadcaster's message: each transform replaces the one heard before of the same
        child frame, from any broadcaster, and the others stay (tf2's buffer forgets no
        static transform; an rclpy broadcaster sends one message per ``sendTransform``
        call); how many of the message's it kept. Past ``MAX_FRAMES`` the broadcaster's
        oldest are forgotten."""
        kept = self._latest.pop(broadcaster, {})
        taken = 0
        for transform in transforms:
            if taken >= MAX_FRAMES:
                break
            parent, child = frame(transform.parent), frame(transform.child)
            sender = self._sender.get(child)
            if sender is not None and sender != broadcaster:
                del self._latest[sender][child]
            kept.pop(child, None)  # to the end: the newest is forgotten last
            kept[child] = Transform(parent, child, transform.rotation)
            self._sender[child] = broadcaster
            taken += 1
        while len(kept) > MAX_FRAMES:
            del self._sender[(oldest := next(iter(kept)))]
            del kept[oldest]
        self._latest[broadcaster] = kept
        while len(self._latest) > MAX_BROADCASTERS:
            for child in self._latest.popitem(last=False)[1]:
                del self._sender[child]
        return taken

    def _parent(self, name: str) -> Transform | None:
        sender = self._sender.get(name)
        return None if sender is None else self._latest[sender][name]

    def _to_root(self, name: str) -> tuple[str, Matrix] | None:
        """The root of ``name``'s tree and R with v_root = R @ v_name; None for a chain
        longer than ``MAX_CHAIN`` links."""
        rotation = np.eye(3)
        seen = {name}
        while (step := self._parent(name)) is not None and step.parent not in seen:
            if len(seen) > MAX_CHAIN:
                return None
            rotation = np.asarray(step.rotation, dtype=float).reshape(3, 3) @ rotation
            name = step.parent
            seen.add(name)
        return name, rotation

    def rotation(self, target: str, source: str) -> tuple[float, ...] | None:
        """R with v_target = R @ v_source (row-major), or None while the two frames are not
        connected by the transforms heard so far (or only by more than ``MAX_CHAIN``)."""
        target, source = frame(target), frame(source)
        if target == source:
            return (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
        found_t, found_s = self._to_root(target), self._to_root(source)
        if found_t is None or found_s is None:
            return None
        (root_t, r_t), (root_s, r_s) = found_t, found_s
        if root_t != root_s:
            return None
        return tuple(float(v) for v in (r_t.T @ r_s).reshape(-1))
