"""What a ROS 2 camera driver and the robot's static transforms say about a camera: the
``sensor_msgs/msg/CameraInfo`` and ``/tf_static`` messages equivalent to a CameraModel."""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from services.lib.camera_model import CameraModel
from services.nodes.ros2._cdr import Codec

IMAGE_FRAME = "camera_optical_frame"
IMU_FRAME = "imu_link"
# The IMU's and the camera's mounting on the robot (any rotations would do).
BASE_TO_IMU = Rotation.from_euler("xyz", [0.0, 0.2, 0.1])
BASE_TO_CAMERA_LINK = Rotation.from_euler("z", 0.3)


def camera_info(
    codec: Codec,
    camera: CameraModel,
    stamp_ns: int,
    *,
    size: tuple[int, int] | None = None,
    binning: int = 1,
    calibrated: bool = True,
) -> bytes:
    """A CameraInfo for ``camera`` (K and P the same: no distortion), of a sensor
    ``binning`` times larger than the images when binned."""
    t = codec.store.types
    fx, fy, cx, cy = (v * binning for v in (camera.fx_px, camera.fy_px, camera.cx_px, camera.cy_px))
    if not calibrated:
        fx = fy = cx = cy = 0.0
    width, height = size or (camera.width_px * binning, camera.height_px * binning)
    header = t["std_msgs/msg/Header"](
        t["builtin_interfaces/msg/Time"](stamp_ns // 10**9, stamp_ns % 10**9), IMAGE_FRAME
    )
    message = t["sensor_msgs/msg/CameraInfo"](
        header=header,
        height=height,
        width=width,
        distortion_model="plumb_bob",
        d=np.zeros(5),
        k=np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], dtype=np.float64),
        r=np.eye(3).reshape(-1),
        p=np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], dtype=np.float64),
        binning_x=binning,
        binning_y=binning,
        roi=t["sensor_msgs/msg/RegionOfInterest"](0, 0, 0, 0, False),
    )
    return bytes(codec.store.serialize_cdr(message, "sensor_msgs/msg/CameraInfo"))


def _stamped(codec: Codec, parent: str, child: str, rotation: Rotation) -> Any:
    t = codec.store.types
    x, y, z, w = (float(v) for v in rotation.as_quat())
    return t["geometry_msgs/msg/TransformStamped"](
        header=t["std_msgs/msg/Header"](t["builtin_interfaces/msg/Time"](0, 0), parent),
        child_frame_id=child,
        transform=t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](0.1, 0.0, 0.05),
            rotation=t["geometry_msgs/msg/Quaternion"](x, y, z, w),
        ),
    )


def tf_static(codec: Codec, imu_to_camera: tuple[float, ...]) -> dict[str, bytes]:
    """Two static broadcasters' TFMessages whose transforms give v_camera = R v_imu:
    ``robot`` (base_link → camera_link → camera_optical_frame, a two-link chain) and
    ``imu`` (base_link → imu_link)."""
    r = Rotation.from_matrix(np.asarray(imu_to_camera).reshape(3, 3))
    # v_base = A v_imu = B v_camera, so R = B^T A and B = A R^T; B = camera_link * link_optical.
    base_to_camera = BASE_TO_IMU * r.inv()
    link_to_optical = BASE_TO_CAMERA_LINK.inv() * base_to_camera
    t = codec.store.types

    def message(*stamped: Any) -> bytes:
        return bytes(
            codec.store.serialize_cdr(
                t["tf2_msgs/msg/TFMessage"](transforms=list(stamped)), "tf2_msgs/msg/TFMessage"
            )
        )

    return {
        "robot": message(
            _stamped(codec, "base_link", "camera_link", BASE_TO_CAMERA_LINK),
            _stamped(codec, "camera_link", IMAGE_FRAME, link_to_optical),
        ),
        "imu": message(_stamped(codec, "/base_link", IMU_FRAME, BASE_TO_IMU)),
    }
