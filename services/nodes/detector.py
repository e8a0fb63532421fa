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
from services.lib.markers import detect_markers
from services.lib.vision import Box, FrameMeta, ResultKind
from services.nodes._contract import Service, ServiceEntry
from services.nodes._vision_handler import Image
from services.nodes.vision import RunnerSpec, serve


@dataclass(frozen=True, slots=True)
class DetectorConfig:
    """Everything the detector can be told."""

    name: str = "detector"
    input: str = "mediator/images"
    queue: int = 2
    min_processing_ms: float = 0.0
    service_factor: float | None = None
    frame_period_ms: float = 1000.0 / 15.0
    # Observe instead of taking part in flow control: while the queue is full new frames are
    # missed by this detector only (as a camera dropping at the source would for it alone),
    # so a second, uncontrolled detector never holds the camera back for the others.
    observe: bool = False

    @property
    def processing_floor_s(self) -> float:
        """The emulated processing time per frame, in seconds."""
        if self.service_factor is not None:
            return self.service_factor * self.frame_period_ms / 1e3
        return self.min_processing_ms / 1e3


def detect_aruco(image: Image, frame: FrameMeta) -> list[Box]:
    """The marker detector as a vision handler: each ArUco marker found is a Box labelled
    with its id (``framegate run vision --handler services.nodes.detector:detect_aruco``)."""
    return [Box(d.marker_id, d.corners_px) for d in detect_markers(image)]


def run(config: DetectorConfig, network: NetworkConfig, stop: threading.Event | None = None) -> int:
    """Run until ``stop`` is set or KeyboardInterrupt."""
    spec = RunnerSpec(
        name=config.name,
        input=config.input,
        queue=config.queue,
        output="detections",
        kind=ResultKind.DETECTIONS,
        observe=config.observe,
        processing_floor_s=config.processing_floor_s,
    )
    return serve(spec, detect_aruco, network, stop or threading.Event())


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The detector's flags (``framegate run detector --help``)."""
    from services.lib.argtypes import non_negative_float, positive_float, positive_int

    d = DetectorConfig()
    parser.add_argument("--name", default=d.name, help="service name (default %(default)s)")
    parser.add_argument(
        "--input",
        default=d.input,
        help="frames to process: mediator/images (filtered) or camera/images",
    )
    parser.add_argument(
        "--queue", type=positive_int, default=d.queue, help="notification queue size N"
    )
    parser.add_argument(
        "--min-processing-ms",
        type=non_negative_float,
        default=d.min_processing_ms,
        help="emulate a slow computer: each frame takes at least this long",
    )
    parser.add_argument(
        "--service-factor",
        type=non_negative_float,
        default=None,
        help="emulated processing time as a multiple of the frame period",
    )
    parser.add_argument(
        "--frame-period-ms",
        type=positive_float,
        default=d.frame_period_ms,
        help="frame period used by --service-factor (default 15 fps)",
    )
    parser.add_argument(
        "--observe",
        action="store_true",
        help="never hold the input's producer back: a full queue misses new frames instead",
    )


def config_from_args(args: argparse.Namespace) -> DetectorConfig:
    return DetectorConfig(
        name=args.name,
        input=args.input,
        queue=args.queue,
        min_processing_ms=args.min_processing_ms,
        service_factor=args.service_factor,
        frame_period_ms=args.frame_period_ms,
        observe=args.observe,
    )


SERVICE: Service[DetectorConfig] = ServiceEntry(
    "detector", DetectorConfig, add_arguments, config_from_args, run
)
