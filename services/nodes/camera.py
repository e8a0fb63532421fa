"""The camera service: one ``frame`` element per image in camera/images.

Buffering rule (the paper's): when flow control refuses a frame, the camera drops it at the
source and counts it ("prevented from generating new data"); the producer's ``refused``
counter is that count. ``--lossless`` waits for credit instead (the experiment's `all` run).

Late frames: a replayed source that falls a frame period behind skips the frame, counted
as ``late`` in camera/images' ``skipped`` (``info``); when the frames made fall below 90 %
of the nominal rate the camera warns once, with its render/read time and the CPU load.

Sources (services/nodes/sources.py): ``sim`` renders live from the simulator, ``replay DIR``
plays a dataset at real-time pace (``--rate``) with timestamps rebased onto the wall clock,
``device N|URL`` reads a cv2.VideoCapture.
"""

from __future__ import annotations

import argparse
import collections
import logging
import os
import statistics
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from middleware import FlowControlRefused, FramegateError, NetworkConfig, Node, Retention
from services.lib.messages import frame_metadata
from services.lib.quality import Exposure
from services.nodes._contract import Service, ServiceEntry
from services.nodes._runtime import (
    Timeline,
    serve_until_stopped,
    setup_logging,
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
        timeline = Timeline(t0_wall)
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
        rate = RateWatch(source.frame_period_ns, config.source.rate if source.relative else 1.0)
        produced = dropped = 0
        # Where on the shared timeline this camera begins: a camera restarted mid-run, or
        # one that opened its source after the start instant, joins there. Frames due
        # before were never its to make: skipped, not counted late.
        joined_rel = timeline.late_ns(0)
        try:
            for frame in source.frames(stop):
                if source.relative:
                    start_rel = source.scale(frame.exposure_start_ns)
                    end_rel = start_rel + frame.exposure_ns
                    if end_rel < joined_rel:
                        continue
                    # A real camera cannot deliver a frame late: if rendering or reading fell
                    # a frame period behind, this frame is skipped (and counted) instead.
                    if timeline.late_ns(end_rel) > rate.period_ns:
                        images.count_skip("late")
                        rate.late(log)
                        continue
                    image = rate.timed_load(frame.load, stop)
                    # The image exists once its exposure has ended, not before.
                    if image is None or not timeline.sleep_until(end_rel, stop):
                        break
                    exposure = Exposure(timeline.stamp_ns(start_rel), frame.exposure_ns)
                else:
                    image = rate.timed_load(frame.load, stop)
                    if image is None:
                        break
                    exposure = Exposure(frame.exposure_start_ns, frame.exposure_ns)
                rate.made(log)
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
            rate.late_total,
        )
        # A finished replay keeps serving its buffers until stopped.
        if config.source.kind != "device" and not config.source.exit_when_done:
            serve_until_stopped(stop)
    return 0


# The share of its nominal rate below which a source says it cannot keep up.
KEEP_UP_SHARE = 0.9
# Frames (at least) over which the rate is judged.
_WINDOW_FRAMES = 30


class RateWatch:
    """Whether the source keeps its nominal rate; warns once, with the reason, if not.

    Judged over the last ``_WINDOW_FRAMES`` frames due (or about 2 s, whichever is more)
    after the first frame made: a frame made counts as produced whatever flow control does
    with it afterwards (a refusal is the consumer's doing, not the source's).
    """

    def __init__(self, frame_period_ns: int, rate: float) -> None:
        self.period_ns = max(1, int(frame_period_ns / rate))
        window = max(_WINDOW_FRAMES, round(2e9 / self.period_ns))
        self._recent: collections.deque[bool] = collections.deque(maxlen=window)
        self._load_ns: collections.deque[int] = collections.deque(maxlen=window)
        self.late_total = 0
        self.warned = False

    def timed_load(
        self, load: Callable[[], npt.NDArray[np.uint8]], stop: threading.Event
    ) -> npt.NDArray[np.uint8] | None:
        started = time.monotonic_ns()
        image = unless_stopped(load, stop)
        if image is not None:
            self._load_ns.append(time.monotonic_ns() - started)
        return image

    def late(self, log: logging.Logger) -> None:
        self.late_total += 1
        if self._load_ns:  # after the first frame: the first render is slow by nature
            self._recent.append(False)
            self._check(log)

    def made(self, log: logging.Logger) -> None:
        self._recent.append(True)
        self._check(log)

    def _check(self, log: logging.Logger) -> None:
        if self.warned or len(self._recent) < (self._recent.maxlen or 0):
            return
        share = sum(self._recent) / len(self._recent)
        if share >= KEEP_UP_SHARE:
            return
        self.warned = True
        nominal_hz = 1e9 / self.period_ns
        load_ms = statistics.median(self._load_ns) / 1e6
        cpus = os.cpu_count() or 1
        busy = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
        log.warning(
            "camera cannot keep its rate: %.1f of %.1f frames/s (%.0f %%, below %.0f %%), "
            "the rest skipped late; rendering/reading takes %.0f ms per frame (median) "
            "against a %.0f ms period; CPU load average %.1f on %d CPUs",
            share * nominal_hz,
            nominal_hz,
            100 * share,
            100 * KEEP_UP_SHARE,
            load_ms,
            self.period_ns / 1e6,
            busy,
            cpus,
        )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The camera's flags (``framegate run camera --help``)."""
    from services.lib.argtypes import positive_float, positive_int
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
        type=positive_float,
        default=60.0,
        help="with --lossless: how long one frame waits for credit (default %(default)s)",
    )
    parser.add_argument(
        "--retention-frames",
        type=positive_int,
        default=64,
        help="how many frames camera/images keeps",
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
