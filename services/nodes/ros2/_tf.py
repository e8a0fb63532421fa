"""The rotation between two frames from ``/tf_static``, pure, as tf2 reads it.

Each ``geometry_msgs/msg/TransformStamped`` says where ``child_frame_id`` is in
``header.frame_id`` (its parent): its rotation q turns a vector written in the child frame
into the parent frame, v_parent = R(q) v_child (tf2's convention). Only rotations matter
here: angular velocity does not depend on where a sensor sits.

Every static broadcaster (tf2_ros' ``StaticTransformBroadcaster``) publishes one
``tf2_msgs/msg/TFMessage`` holding all its transforms, again whole when one changes; the
topic is transient-local, so a late joiner receives the latest message of each. The
transforms are those of the latest message of every broadcaster (keyed by its gid), merged;
where two broadcasters give a frame a parent, the one heard last wins, as in tf2's buffer.
The rotation between two frames composes the chain up to their common root.

Frame names are compared without a leading ``/`` (tf2 strips it too). Bounded: at most
``MAX_BROADCASTERS`` broadcasters and ``MAX_FRAMES`` transforms each are kept, and a walk
up the tree stops at a cycle and after ``MAX_CHAIN`` links. Each step looks its frame up in
the broadcasters' own tables, newest first: merging them all (up to 262,144 transforms) for
every composition took 0.7 s along a peer's 262,144-link chain, and a composition follows
every /tf_static message, so a trickle of them held every image that long.
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
        # broadcaster gid -> its latest transforms, by child frame; in order heard.
        self._latest: collections.OrderedDict[bytes, dict[str, Transform]] = (
            collections.OrderedDict()
        )

    def update(self, broadcaster: bytes, transforms: Iterable[Transform]) -> int:
        """A broadcaster's latest message replaces its previous one; how many it kept."""
        kept: dict[str, Transform] = {}
        for transform in transforms:
            if len(kept) >= MAX_FRAMES:
                break
            parent, child = frame(transform.parent), frame(transform.child)
            kept[child] = Transform(parent, child, transform.rotation)
        self._latest.pop(broadcaster, None)
        self._latest[broadcaster] = kept
        while len(self._latest) > MAX_BROADCASTERS:
            self._latest.popitem(last=False)
        return len(kept)

    def _parent(self, name: str) -> Transform | None:
        for transforms in reversed(self._latest.values()):  # heard last: it wins
            if (step := transforms.get(name)) is not None:
                return step
        return None

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
