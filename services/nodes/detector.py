"""The marker detector: the robot's "expensive vision code" (paper §5.2).

Buffering rule: flow-controlled subscriber with queue N (default 2), as in the paper. A
notification leaves the queue when taken, before processing, so up to N more frames may
wait while one is processed. ``--min-processing-ms`` (or ``--service-factor`` × the frame
period) emulates a resource-constrained computer: the paper's detector took about 1.6× the
inter-arrival time.
"""

from __future__ import annotations

import argparse
import threading
import time
from dataclasses import dataclass

from middleware import (
    PUSH_ALL,
    FramegateError,
    NetworkConfig,
    Node,
    Retention,
    SubscriptionMode,
)
from services.lib.markers import detect_markers
from services.lib.messages import decode_image, detections_metadata, read_frame_metadata
from services.nodes._contract import Service, ServiceEntry
from services.nodes._runtime import setup_logging


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


def run(config: DetectorConfig, network: NetworkConfig, stop: threading.Event | None = None) -> int:
    """Run until ``stop`` is set or KeyboardInterrupt."""
    stop = stop or threading.Event()
    log = setup_logging(config.name)
    with Node(config.name, network) as node:
        detections = node.offer(
            "detections", kind="detections", retention=Retention(max_count=100_000)
        )
        # Every frame given to the detector is processed: have it pushed, not fetched.
        frames = node.subscribe(
            config.input,
            queue_size=config.queue,
            mode=SubscriptionMode.OBSERVE if config.observe else SubscriptionMode.FLOW,
            wait_s=0,
            push_max_bytes=PUSH_ALL,
            await_service=True,  # a pipeline starts every service at once
        )
        log.info(
            "detector: %s (queue %d, processing >= %.0f ms)",
            config.input,
            config.queue,
            config.processing_floor_s * 1e3,
        )
        try:
            while not stop.is_set():
                note = frames.take(timeout_s=0.5)
                if note is None:
                    continue
                started = time.monotonic()
                try:
                    element = frames.fetch(note)
                    meta = read_frame_metadata(element.metadata)
                    found = detect_markers(decode_image(element.payload, meta))
                except FramegateError as exc:
                    log.warning("skipping frame %d: %s", note.timestamp_ns, exc)
                    continue
                # Emulated load: the frame occupies the processor at least this long.
                remaining = config.processing_floor_s - (time.monotonic() - started)
                if remaining > 0 and stop.wait(remaining):
                    break
                markers = [
                    (d.marker_id, [c for corner in d.corners_px for c in corner]) for d in found
                ]
                processing_ns = int((time.monotonic() - started) * 1e9)
                newest = detections.series.newest_ns
                if newest is not None and element.timestamp_ns <= newest:
                    # Our input went back in time (the mediator removed frames stamped by a
                    # wrong clock): so do our detections, or none could follow.
                    detections.discard_after(element.timestamp_ns - 1, "rewound")
                try:
                    detections.put(
                        element.timestamp_ns,
                        b"",
                        detections_metadata(
                            element.timestamp_ns,
                            meta.frame_id,
                            config.input,
                            processing_ns,
                            markers,
                        ),
                    )
                except FramegateError as exc:
                    log.warning("cannot store detections of frame %d: %s", meta.frame_id, exc)
        except KeyboardInterrupt:
            pass
    return 0


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
