"""The ``ros2`` bridge: a ROS 2 node on rmw_zenoh's wire protocol, with no ROS 2 installed.

ROS 2 cameras and IMUs come in, filtered frames, detections and verdicts go out.

``framegate run ros2 --image-in /camera/image_raw --imu-in /imu/data --image-out
mediator/images=/framegate/image`` makes one ROS 2 node (``ros2 node list`` shows it) whose
subscriptions feed NAME/images and NAME/rates, the buffers the mediator reads, and whose
publishers carry framegate buffers to ROS 2 topics. ``_rmw`` is the wire grammar (keys,
tokens, QoS, attachments), ``_cdr`` the messages (via ``rosbags``), ``_link`` the Zenoh
session to the ROS 2 system, ``_bridge`` the loops and their buffering rules.
"""

from __future__ import annotations

import threading

from middleware import NetworkConfig
from services.nodes._contract import Service, ServiceEntry

from ._config import Mapping, Ros2Config, add_arguments, config_from_args


def run(config: Ros2Config, network: NetworkConfig, stop: threading.Event | None = None) -> int:
    """Bridge until ``stop`` is set (imports rosbags and opens sessions only when run)."""
    from ._bridge import run as bridge

    return bridge(config, network, stop)


SERVICE: Service[Ros2Config] = ServiceEntry(
    "ros2", Ros2Config, add_arguments, config_from_args, run
)

__all__ = ["SERVICE", "Mapping", "Ros2Config", "add_arguments", "config_from_args", "run"]
