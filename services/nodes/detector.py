"""The marker detector: the robot's "expensive vision code" (paper §5.2).

It is the vision runner (``services/nodes/vision.py``) with the ArUco handler
:func:`detect_aruco` and an emulated cost; everything about queues, skips and rewinds is the
runner's.

Buffering rule: flow-controlled subscriber with queue N (default 2), as in the paper. A
notification leaves the queue when taken, before processing, so up to N more frames may
wait while one is processed. ``--min-processing-ms`` (or ``--service-factor`` × the frame
period) emulates a resource-constrained computer: the paper's detector took about 1.6× the
inter-arrival time.
"""

from __future__ import annotations

import argparse
import threading
from dataclasses import dataclass

from middleware import NetworkConfig
from services.lib.argtypes import non_negative_float, positive_float
from services.lib.markers import detect_markers
from services.lib.settings import add_flags, from_args, setting
from services.lib.vision import Box, FrameMeta, ResultKind
from services.nodes._contract import Service, ServiceEntry
from services.nodes._vision_handler import Image
from services.nodes.vision import RunnerConfig, serve


@dataclass(frozen=True, slots=True)
class DetectorConfig(RunnerConfig):
    """Everything the detector can be told: the runner's settings and an emulated cost."""

    name: str = setting("detector", "service name")
    min_processing_ms: float = setting(
        0.0,
        "emulate a slow computer: each frame takes at least this long",
        parse=non_negative_float,
    )
    service_factor: float | None = setting(
        None,
        "emulated processing time as a multiple of the frame period",
        parse=non_negative_float,
    )
    frame_period_ms: float = setting(
        1000.0 / 15.0,
        "frame period used by --service-factor",
        parse=positive_float,
        shown="15 fps",
    )

    @property
    def processing_floor_s(self) -> float:
        """The emulated processing time per frame, in seconds."""
        if self.service_factor is not None:
            return self.service_factor * self.frame_period_ms / 1e3
        return self.min_processing_ms / 1e3


def detect_aruco(image: Image, frame: FrameMeta) -> list[Box]:
    """The marker detector as a vision handler: each ArUco marker found is a Box labelled
    with its id (``framegate run vision --handler services.nodes.detector:detect_aruco``)."""
    return [Box(d.marker_id, d.corners_px) for d in detect_markers(image, frame.encoding)]


def run(config: DetectorConfig, network: NetworkConfig, stop: threading.Event | None = None) -> int:
    """Run until ``stop`` is set or KeyboardInterrupt."""
    spec = config.spec("detections", ResultKind.DETECTIONS, config.processing_floor_s)
    return serve(spec, detect_aruco, network, stop or threading.Event())


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The detector's flags (``framegate run detector --help``): one per config field."""
    add_flags(parser, DetectorConfig)


def config_from_args(args: argparse.Namespace) -> DetectorConfig:
    config: DetectorConfig = from_args(DetectorConfig, args)
    return config


SERVICE: Service[DetectorConfig] = ServiceEntry(
    "detector", DetectorConfig, add_arguments, config_from_args, run
)
