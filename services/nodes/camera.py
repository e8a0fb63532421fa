"""The camera service: one ``frame`` element per image in camera/images.

Buffering rule (the paper's): when flow control refuses a frame, the camera drops it at the
source and counts it ("prevented from generating new data"); the producer's ``refused``
counter is that count. ``--lossless`` waits for credit instead (the experiment's `all` run).

Sources (services/nodes/sources.py): ``sim`` renders live from the simulator, ``replay DIR``
plays a dataset at real-time pace (``--rate``) with timestamps rebased onto the wall clock,
``device N|URL`` reads a cv2.VideoCapture.
"""

from __future__ import annotations

import argparse
import threading
import time
from dataclasses import dataclass

from middleware import FlowControlRefused, FramegateError, NetworkConfig, Node, Retention
from services.lib.messages import frame_metadata
from services.lib.quality import Exposure
from services.nodes._contract import Service, ServiceEntry
from services.nodes._runtime import (
    serve_until_stopped,
    setup_logging,
    sleep_until_ns,
    start_at_ns,
    unless_stopped,
)
from services.nodes.sources import SourceSpec, open_frame_source


@dataclass(frozen=True, slots=True)
class CameraConfig:
    """Everything the camera can be told."""

    source: SourceSpec
    name: str = "camera"
    lossless: bool = False
    lossless_wait_s: float = 60.0
    retention_frames: int = 64


def run(config: CameraConfig, network: NetworkConfig, stop: threading.Event | None = None) -> int:
    """Produce frames until the source ends, ``stop`` is set, or KeyboardInterrupt."""
    stop = stop or threading.Event()
    log = setup_logging(config.name)
    source = open_frame_source(config.source)
    if stop.is_set():  # interrupted while the source was opening
        return 0
    with Node(config.name, network) as node:
        images = node.offer(
            "images",
            kind="frame",
            retention=Retention(max_count=config.retention_frames, max_bytes=512 * 2**20),
        )
        info = node.offer("info", kind="camera", retention=Retention(max_count=4))
        t0_wall = start_at_ns(config.source.start_at_ns) if source.relative else 0
        info.put(
            max(1, t0_wall),
            b"",
            source.camera.to_xml(
                max(1, t0_wall),
                exposure_ns=source.exposure_ns,
                frame_period_ns=source.frame_period_ns,
            ),
        )
        log.info("camera: %s -> %s/images", source.description, config.name)
        produced = dropped = late = 0
        try:
            for frame in source.frames(stop):
                exposure = Exposure(
                    t0_wall + source.scale(frame.exposure_start_ns), frame.exposure_ns
                )
                if source.relative:
                    # A real camera cannot deliver a frame late: if rendering or reading fell
                    # a frame period behind, this frame is skipped (and counted) instead.
                    if time.time_ns() > exposure.end_ns + source.frame_period_ns:
                        late += 1
                        continue
                    image = unless_stopped(frame.load, stop)
                    # The image exists once its exposure has ended, not before.
                    if image is None or not sleep_until_ns(exposure.end_ns, stop):
                        break
                else:
                    image = unless_stopped(frame.load, stop)
                    if image is None:
                        break
                metadata = frame_metadata(frame.frame_id, exposure, image, source.camera)
                try:
                    images.put(
                        exposure.start_ns,
                        image.tobytes(),
                        metadata,
                        wait_s=config.lossless_wait_s if config.lossless else 0.0,
                    )
                    produced += 1
                except FlowControlRefused:
                    dropped += 1  # dropped at the source, counted in images.info().refused
                except FramegateError as exc:
                    log.warning("frame %d not stored: %s", frame.frame_id, exc)
        except KeyboardInterrupt:
            pass
        log.info(
            "camera: %d frames stored, %d dropped at the source (flow control), %d skipped late",
            produced,
            dropped,
            late,
        )
        # A finished replay keeps serving its buffers until stopped.
        if config.source.kind != "device" and not config.source.exit_when_done:
            serve_until_stopped(stop)
    return 0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The camera's flags (``framegate run camera --help``)."""
    from services.nodes.sources import add_source_arguments

    parser.add_argument("--name", default="camera", help="service name (default %(default)s)")
    add_source_arguments(parser, device=True)
    parser.add_argument(
        "--lossless",
        action="store_true",
        help="wait for flow-control credit instead of dropping frames",
    )
    parser.add_argument(
        "--lossless-wait-s",
        type=float,
        default=60.0,
        help="with --lossless: how long one frame waits for credit (default %(default)s)",
    )
    parser.add_argument(
        "--retention-frames", type=int, default=64, help="how many frames camera/images keeps"
    )


def config_from_args(args: argparse.Namespace) -> CameraConfig:
    from services.nodes.sources import source_from_args

    return CameraConfig(
        source=source_from_args(args),
        name=args.name,
        lossless=args.lossless,
        lossless_wait_s=args.lossless_wait_s,
        retention_frames=args.retention_frames,
    )


SERVICE: Service[CameraConfig] = ServiceEntry(
    "camera", CameraConfig, add_arguments, config_from_args, run
)
