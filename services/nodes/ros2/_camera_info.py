"""The camera description from ROS 2 itself: intrinsics from ``sensor_msgs/msg/CameraInfo``,
the IMU-to-camera rotation from ``/tf_static``.

The mediator estimates blur from the camera's intrinsics and its rotation to the gyro, which
every frame of NAME/images carries in its metadata (the ``<camera>`` element, the same
description ``--camera-xml`` reads). Without ``--camera-xml`` the bridge builds it:

- intrinsics: the ``camera_info`` topic beside the image topic, as image_transport names it
  (``/ns/image_raw`` → ``/ns/camera_info``). K (the raw image's camera matrix) for a raw
  image topic, P (the rectified image's projection) for an ``image_rect*`` topic; divided by
  ``binning_x``/``binning_y`` and moved by the region of interest, as image_geometry does.
  ``K[0] == 0`` (or, for a rectified topic, ``P[0] == 0``) is an uncalibrated camera: no
  intrinsics yet.
- rotation: v_camera = R v_imu where the camera frame is the image's ``header.frame_id``
  (normally the optical frame, REP 103: x right, y down, z forward, framegate's camera
  axes) and the IMU frame the IMU message's ``header.frame_id``, from the static transform
  tree (:mod:`._tf`), turned by the CameraInfo's rectification R for a rectified topic
  (a stereo pair's images are rotated into the common rectified plane). ``--imu-to-camera``
  gives the rotation instead, as it is.

Both change rarely; the latest CameraInfo waits in a one-message slot and /tf_static
messages in a short queue (oldest dropped, counted) until the image worker, the one caller
of :meth:`CameraSource.for_image`, reads them before its next image, at most
``TF_BYTES_PER_IMAGE`` of them per image (a flood must not hold the images). A CameraInfo whose
size is not the images' is a counted skip (``camera-info-mismatch``), an undecodable one
``bad-camera-info``, an undecodable /tf_static message (or a transform in it whose
quaternion is no rotation: that one alone) ``bad-tf``. While something is
missing the bridge says once, in one line, what it waits for and which topic or flag
provides it.

Threads: ``on_camera_info`` and ``on_tf`` run on Zenoh's callback thread and only store
bytes; ``set_imu_frame`` on the IMU worker; everything else on the image worker. ``_lock``
guards the slot, the queue and the IMU frame.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from middleware import ConfigError, FramegateError, printable
from services.lib.camera_model import CameraModel, check_rotation

from ._cdr import CdrError, Codec
from ._rmw import Attachment
from ._tf import StaticTransforms, Transform, frame, rotation_from_quaternion

CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TF_STATIC = "/tf_static"
# /tf_static messages waiting for the image worker; a broadcaster sends one per change.
TF_QUEUE = 64
# Focal lengths and the principal point of a CameraInfo, in pixels, at most this large (a
# focal length of 1e300 px is garbage, and would give blur estimates of 1e297 px); a focal
# length is at least 1 px.
MAX_PIXELS = 1e6
# A /tf_static message larger than this is not kept (counted ``bad-tf``): a robot's static
# transforms are a few hundred bytes each, and TF_QUEUE messages of Zenoh's largest size
# (a peer's garbage) would hold gigabytes.
TF_MAX_BYTES = 256 * 1024
# /tf_static bytes decoded before one image at most (at least one message): the rest wait
# for the next images. Decoding is ~0.1 ms per KB here; a peer's flood of 64 messages of
# TF_MAX_BYTES decoded at once held every image 3 s on the executor.
TF_BYTES_PER_IMAGE = TF_MAX_BYTES
# How many times a changed camera description is logged (a peer may change it forever).
_LOG_CHANGES = 8
# A waiting line names frames and topics as peers spell them: at most this many characters
# of each line, unprintable ones escaped (a frame id may be megabytes, newlines included).
_LINE_CHARS = 600

# (reason, detail, how many): count skipped messages under ``reason``.
CountSkip = Callable[[str, str, int], None]


def is_rectified(image_topic: str) -> bool:
    """True for image_proc's rectified topics (``image_rect``, ``image_rect_color``)."""
    return image_topic.rsplit("/", 1)[-1].startswith("image_rect")


@dataclass(frozen=True, slots=True)
class Intrinsics:
    """What a CameraInfo says about the images it describes."""

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    # A rectified topic's R when it is not the identity (a stereo pair's): the rotation from
    # the camera frame the images name to the rectified one, v_rect = R v_camera.
    rectification: tuple[float, ...] | None = None


class Uncalibrated(CdrError):
    """A CameraInfo of an uncalibrated camera (its matrix starts with 0)."""


def intrinsics(codec: Codec, raw: bytes, rectified: bool) -> Intrinsics:
    """The intrinsics a CameraInfo gives for its images; CdrError for a message that is not
    one, Uncalibrated for a camera without calibration."""
    try:
        msg: Any = codec.store.deserialize_cdr(memoryview(raw), CAMERA_INFO)
        k, p, r = [float(v) for v in msg.k], [float(v) for v in msg.p], [float(v) for v in msg.r]
        width, height = int(msg.width), int(msg.height)
        bx, by = max(1, int(msg.binning_x)), max(1, int(msg.binning_y))
        roi = msg.roi
        x0, y0 = int(roi.x_offset), int(roi.y_offset)
        roi_w, roi_h = int(roi.width), int(roi.height)
    except Exception as exc:  # rosbags raises several types for truncated input
        raise CdrError(f"not a CDR {CAMERA_INFO}: {exc}") from exc
    if len(k) != 9 or len(p) != 12 or len(r) != 9:
        raise CdrError(f"{CAMERA_INFO} with {len(k)} K, {len(r)} R and {len(p)} P numbers")
    fx, fy, cx, cy = (p[0], p[5], p[2], p[6]) if rectified else (k[0], k[4], k[2], k[5])
    # K[0] == 0 says uncalibrated for the rectified images too (image_proc then rectifies
    # nothing), whatever P holds.
    for name, first in (("K", k[0]), ("P", p[0]))[: 2 if rectified else 1]:
        if first == 0.0:
            raise Uncalibrated(f"{name}[0] is 0: the camera is uncalibrated")
    sane = all(math.isfinite(v) and abs(v) <= MAX_PIXELS for v in (fx, fy, cx, cy))
    if not sane or fx < 1.0 or fy < 1.0:
        raise CdrError(f"{CAMERA_INFO} focal lengths {fx}, {fy} or centre {cx}, {cy}")
    # A region of interest (width 0: the full image) is cut out first, then binned.
    if roi_w and roi_h:
        width, height, cx, cy = roi_w, roi_h, cx - x0, cy - y0
        if abs(cx) > MAX_PIXELS or abs(cy) > MAX_PIXELS:  # an offset of 2**32 - 1, say
            raise CdrError(f"{CAMERA_INFO} centre {cx}, {cy} after its region of interest")
    return Intrinsics(
        width // bx, height // by, fx / bx, fy / by, cx / bx, cy / by, _rectification(r, rectified)
    )


def _rectification(r: list[float], rectified: bool) -> tuple[float, ...] | None:
    """R when it turns a rectified topic's images (see ``Intrinsics``); None for the identity,
    for a raw topic (whose images are not turned) and for all zeros (a monocular driver that
    leaves R unset means no rotation). CdrError for one that is no rotation."""
    if not rectified or not any(r) or r == [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]:
        return None
    try:
        check_rotation(r, "R")
    except ConfigError as exc:
        raise CdrError(f"{CAMERA_INFO} rectification {exc}") from exc
    return tuple(r)


def transforms(codec: Codec, raw: bytes) -> tuple[list[Transform], list[str]]:
    """The rotations of a ``tf2_msgs/msg/TFMessage``, and why each transform left out was
    (a quaternion that is no rotation: tf2 refuses that transform alone and keeps the
    message's others); CdrError for a message that does not decode."""
    try:
        msg: Any = codec.store.deserialize_cdr(memoryview(raw), TF_MESSAGE)
        found, refused = [], []
        for stamped in msg.transforms:
            q = stamped.transform.rotation
            parent, child = str(stamped.header.frame_id), str(stamped.child_frame_id)
            try:
                rotation = rotation_from_quaternion(float(q.x), float(q.y), float(q.z), float(q.w))
            except ValueError as exc:
                refused.append(f"{TF_STATIC} transform {parent[:80]} -> {child[:80]}: {exc}")
                continue
            found.append(Transform(frame(parent), frame(child), rotation))
    except Exception as exc:  # rosbags' errors
        raise CdrError(f"not a usable {TF_MESSAGE}: {exc}") from exc
    return found, refused


class CameraSource:
    """The camera description of the images, from flags or from ROS 2 (see module doc)."""

    def __init__(
        self,
        codec: Codec,
        log: logging.Logger,
        *,
        image_topic: str,
        info_topic: str | None,
        imu_topic: str | None,
        override: CameraModel | None = None,
        rotation: tuple[float, ...] | None = None,
    ) -> None:
        self._codec, self._log = codec, log
        if override is not None and rotation is not None:
            # --imu-to-camera overrides the XML's rotation (ConfigError if it is none).
            override = dataclasses.replace(override, gyro_to_camera=rotation)
        self._image_topic, self._info_topic, self._imu_topic = image_topic, info_topic, imu_topic
        self._override, self._rotation = override, rotation
        self._rectified = is_rectified(image_topic)
        self._lock = threading.Lock()
        self._info_raw: bytes | None = None
        self._tf_raw: collections.deque[tuple[bytes, bytes]] = collections.deque()
        self._tf_dropped = 0
        self._tf_oversize = 0
        self._imu_frame: str | None = None
        self._tf = StaticTransforms()
        self._tf_version = 0
        self._rotation_found: tuple[tuple[Any, ...], tuple[float, ...] | None] = ((), None)
        self._info_body = b""
        self._info_found: Intrinsics | CdrError = CdrError("no CameraInfo yet")
        self._intrinsics: Intrinsics | None = None
        self._info_problem: str | None = None  # why the last CameraInfo was not taken
        self._model: CameraModel | None = None
        self._model_key: tuple[Any, ...] | None = None
        self._said: set[str] = set()
        self._changes = 0
        self.source = "--camera-xml" if override is not None else "ROS 2"

    @property
    def wants_camera_info(self) -> bool:
        return self._override is None and self._info_topic is not None

    @property
    def wants_tf(self) -> bool:
        return self._override is None and self._rotation is None

    # -- Zenoh's thread and the IMU worker: store only -------------------------------------
    def on_camera_info(self, payload: bytes, _attachment: bytes | None) -> None:
        with self._lock:
            self._info_raw = payload  # only the latest matters

    def on_tf(self, payload: bytes, attachment: bytes | None) -> None:
        broadcaster = b""
        if attachment is not None:
            with contextlib.suppress(ValueError):  # not rmw_zenoh's: one unnamed broadcaster
                broadcaster = Attachment.decode(attachment).source_gid
        with self._lock:
            if len(payload) > TF_MAX_BYTES:
                self._tf_oversize += 1
                return
            if len(self._tf_raw) >= TF_QUEUE:
                self._tf_raw.popleft()
                self._tf_dropped += 1
            self._tf_raw.append((broadcaster, payload))

    def set_imu_frame(self, name: str) -> None:
        with self._lock:
            self._imu_frame = frame(name)

    # -- the image worker --------------------------------------------------------------------
    def for_image(
        self, image_frame: str, width: int, height: int, skip: CountSkip
    ) -> CameraModel | None:
        """The description of an image of this frame and size, or None while something is
        missing (said once); CameraInfo and /tf_static messages are read here."""
        with self._lock:
            info_raw, self._info_raw = self._info_raw, None
            tf_raw: list[tuple[bytes, bytes]] = []
            budget = TF_BYTES_PER_IMAGE
            while self._tf_raw and (not tf_raw or len(self._tf_raw[0][1]) <= budget):
                budget -= len(self._tf_raw[0][1])
                tf_raw.append(self._tf_raw.popleft())
            dropped, self._tf_dropped = self._tf_dropped, 0
            oversize, self._tf_oversize = self._tf_oversize, 0
            imu_frame = self._imu_frame
        if dropped:
            skip("tf-queue-full", f"{dropped} {TF_STATIC} messages waited too long", dropped)
        if oversize:
            skip("bad-tf", f"{oversize} {TF_STATIC} messages over {TF_MAX_BYTES} bytes", oversize)
        for broadcaster, raw in tf_raw:
            try:
                found, refused = transforms(self._codec, raw)
            except CdrError as exc:
                skip("bad-tf", str(exc), 1)
                continue
            if refused:  # one count for all of a message's (a peer's may hold thousands)
                skip("bad-tf", refused[0], len(refused))
            self._tf.update(broadcaster, found)
            self._tf_version += 1
        if info_raw is not None:
            self._read_info(info_raw, width, height, skip)
        if self._intrinsics is not None and (
            self._intrinsics.width_px,
            self._intrinsics.height_px,
        ) != (width, height):
            # The images changed size (a CameraInfo of the old size with them, a skip, is
            # not a reason to keep it): wait for a new CameraInfo, the images going on
            # without a description, as before the first one.
            self._intrinsics = None
        return self._describe(frame(image_frame), imu_frame, width, height)

    def _decoded(self, raw: bytes) -> Intrinsics | CdrError:
        """The CameraInfo's intrinsics or why there are none. Drivers send the same
        CameraInfo with every image: but for the stamp (bytes 4..12, after the 4-byte CDR
        header) a repeat is the same bytes, and is not decoded again."""
        body = raw[:4] + raw[12:]
        if body != self._info_body:
            try:
                self._info_found = intrinsics(self._codec, raw, self._rectified)
            except CdrError as exc:
                self._info_found = exc
            self._info_body = body
        return self._info_found

    def _read_info(self, raw: bytes, width: int, height: int, skip: CountSkip) -> None:
        found = self._decoded(raw)
        if isinstance(found, Uncalibrated):
            self._info_problem = f"a calibrated CameraInfo on {self._info_topic} ({found})"
            self._intrinsics = None
            return
        if isinstance(found, CdrError):
            skip("bad-camera-info", f"{self._info_topic}: {found}", 1)
            return
        if (found.width_px, found.height_px) != (width, height):
            skip(
                "camera-info-mismatch",
                f"{self._info_topic} describes {found.width_px}x{found.height_px} images, "
                f"{self._image_topic} has {width}x{height}",
                1,
            )
            self._info_problem = (
                f"a CameraInfo on {self._info_topic} for {width}x{height} images "
                f"(it says {found.width_px}x{found.height_px})"
            )
            return
        self._intrinsics, self._info_problem = found, None

    def _describe(
        self, image_frame: str, imu_frame: str | None, width: int, height: int
    ) -> CameraModel | None:
        if self._override is not None:
            if self._model is not None:
                return self._model
            return self._settled(self._override, ("xml",))
        missing = []
        if self._intrinsics is None:
            missing.append(
                self._info_problem
                or (
                    f"a CameraInfo on {self._info_topic} (or --camera-xml)"
                    if self._info_topic is not None
                    else "--camera-xml (CameraInfo is not read: --camera-info '')"
                )
            )
        rotation = self._rotation
        if rotation is None:
            if imu_frame is None:
                missing.append(
                    f"an IMU message on {self._imu_topic} to name the IMU frame "
                    "(or --imu-to-camera)"
                    if self._imu_topic
                    else "--imu-to-camera (no --imu-in names the IMU frame)"
                )
            elif not imu_frame or not image_frame:  # tf2 names no frame "": TF cannot say
                topic = self._imu_topic if not imu_frame else self._image_topic
                missing.append(
                    f"--imu-to-camera (the messages on {topic} name no frame: their "
                    "header.frame_id is empty, so /tf_static cannot give the rotation)"
                )
            else:
                tf_key = (self._tf_version, image_frame, imu_frame)
                if self._rotation_found[0] != tf_key:  # composed again only when it may change
                    self._rotation_found = (tf_key, self._tf.rotation(image_frame, imu_frame))
                rotation = self._rotation_found[1]
                if rotation is None:
                    missing.append(
                        f"the transform from {imu_frame} to {image_frame} on {TF_STATIC} "
                        "(or --imu-to-camera)"
                    )
                elif "optical" not in image_frame:
                    # TF gives the rotation into whatever frame the images name; a driver
                    # that stamps them in its body frame (x forward) turns the blur's axes
                    # and nothing else would show it.
                    self._say(
                        f"ros2: the images on {self._image_topic} are stamped in frame "
                        f"{image_frame!r}, which is not named as an optical frame (REP 103: "
                        "images are in the camera's optical frame, z forward, x right, y "
                        "down, by convention '<camera>_optical_frame'); its rotation from "
                        f"{TF_STATIC} is used as the optical frame's: if it is the camera's "
                        "body frame, the blur is estimated about the wrong axes: give "
                        "--imu-to-camera"
                    )
        if missing or self._intrinsics is None or rotation is None:
            self._say(
                "ros2: no camera description for the mediator yet (it cannot estimate blur "
                "until then); waiting for " + "; ".join(missing)
            )
            return None
        i = self._intrinsics
        if self._rotation is None and i.rectification is not None:
            # TF names the rotation into the images' frame; rectified ones are turned by R
            # from it (``--imu-to-camera`` is taken as given for the images bridged).
            turn = np.asarray(i.rectification).reshape(3, 3) @ np.asarray(rotation).reshape(3, 3)
            rotation = tuple(float(v) for v in turn.reshape(-1))
        key = (i, rotation)
        if key == self._model_key and self._model is not None:
            return self._model
        try:
            model = CameraModel(
                i.width_px, i.height_px, i.fx_px, i.fy_px, i.cx_px, i.cy_px,
                gyro_to_camera=rotation, name="ros2",
            )  # fmt: skip
        except FramegateError as exc:  # ConfigError: e.g. a rotation that is no rotation
            self._say(f"ros2: the camera description from ROS 2 is unusable: {exc}")
            return None
        where = f"{self._info_topic}" + ("" if self._rotation else f" and {TF_STATIC}")
        return self._settled(model, key, where)

    def _settled(
        self, model: CameraModel, key: tuple[Any, ...], where: str = "--camera-xml"
    ) -> CameraModel:
        if key != self._model_key:
            self._model, self._model_key = model, key
            self._changes += 1
            if self._changes <= _LOG_CHANGES:
                self._log.info(
                    "ros2: camera description from %s: %dx%d, fx %.1f fy %.1f cx %.1f cy %.1f, "
                    "imu-to-camera %s",
                    where,
                    model.width_px,
                    model.height_px,
                    model.fx_px,
                    model.fy_px,
                    model.cx_px,
                    model.cy_px,
                    " ".join(f"{v:.4g}" for v in model.gyro_to_camera),
                )
        return model

    def _say(self, line: str) -> None:
        line = printable(line, _LINE_CHARS)
        if line not in self._said and len(self._said) < 16:
            self._said.add(line)
            self._log.warning("%s", line)
