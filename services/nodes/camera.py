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

Threads: one of its own, ``camera-frames`` (a ``Worker``), that renders or reads each
frame, one at a time; everything else is a deadline or a handler on the node's executor
(``CameraPump``: it asks the worker for a frame, puts the frame once its exposure has ended,
and the producer's acks go on while a frame is made), and the main thread waits in
``Node.spin``.
"""

from __future__ import annotations

import collections
import functools
import logging
import os
import statistics
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from middleware import (
    ClosedError,
    FlowControlRefused,
    FramegateError,
    NetworkConfig,
    Node,
    Producer,
    Retention,
)
from services.lib.argtypes import positive_float, positive_int
from services.lib.messages import frame_metadata
from services.lib.quality import Exposure
from services.lib.settings import setting
from services.nodes._contract import Service
from services.nodes._runtime import Outcome, Timeline, Worker, run_source, start_at_ns
from services.nodes.sources import (
    DeviceSource,
    FrameSource,
    SourceFrame,
    SourceSpec,
    open_frame_source,
    source_service,
)


@dataclass(frozen=True, slots=True)
class CameraConfig:
    """Everything the camera can be told."""

    source: SourceSpec
    name: str = setting("camera", "service name")
    lossless: bool = setting(False, "wait for flow-control credit instead of dropping frames")
    lossless_wait_s: float = setting(
        60.0, "with --lossless: how long one frame waits for credit", parse=positive_float
    )
    retention_frames: int = setting(64, "how many frames camera/images keeps", parse=positive_int)


def run(config: CameraConfig, network: NetworkConfig, stop: threading.Event | None = None) -> int:
    """Produce frames until the source ends, ``stop`` is set, or KeyboardInterrupt."""
    stop = stop or threading.Event()

    def pump(node: Node, source: FrameSource | DeviceSource, log: logging.Logger) -> CameraPump:
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
        return CameraPump(node, images, source, config, Timeline(t0_wall), stop, log)

    return run_source(
        config.name, network, stop, lambda: open_frame_source(config.source, stop), pump
    )


class CameraPump:
    """Makes each frame when its time comes, on the node's executor: a ``Node.at`` deadline
    per frame (rendered or read, then put once its exposure has ended), no sleeping loop.
    A finished replay keeps serving its buffers until stopped; a device's end, or
    ``--exit-when-done``, stops the service."""

    def __init__(
        self,
        node: Node,
        images: Producer,
        source: FrameSource | DeviceSource,
        config: CameraConfig,
        timeline: Timeline,
        stop: threading.Event,
        log: logging.Logger,
    ) -> None:
        self._node = node
        self._images = images
        self._source = source
        self._config = config
        self._timeline = timeline
        self._stop = stop
        self._log = log
        self._warned_unreadable = False
        self._frames = iter(source.frames(stop))
        # Where on the shared timeline this camera begins: a camera restarted mid-run, or
        # one that opened its source after the start instant, joins there. Frames due
        # before were never its to make: skipped, not counted late.
        self._joined_rel = timeline.late_ns(0)
        self.rate = RateWatch(
            source.frame_period_ns, config.source.rate if source.relative else 1.0
        )
        # A frame made and waiting for its exposure to end: (frame, image, start_rel).
        self._made: tuple[SourceFrame, npt.NDArray[np.uint8], int] | None = None
        # Renders and reads: on a thread of their own, so the executor never waits for one.
        self._worker = Worker("camera-frames", node)
        self.produced = self.dropped = 0

    def summary(self) -> str:
        return (
            f"camera: {self.produced} frames stored, {self.dropped} dropped at the source "
            f"(flow control), {self.rate.late_total} skipped late"
        )

    def on_time(self, now: int) -> None:
        """Put the frame whose exposure has ended, then have the next one made."""
        if self._made is not None:
            frame, image, start_rel = self._made
            self._made = None
            exposure = Exposure(self._timeline.stamp_ns(start_rel), frame.exposure_ns)
            self._put(frame, image, exposure)
        self._next()

    def _next(self) -> None:
        """Have the next frame due made on the worker (the executor goes on meanwhile:
        acks, queries), skipping those already late; at a device's end, or with
        ``--exit-when-done`` at the source's, stop."""
        for frame in self._frames:
            if not self._source.relative:  # a device: its read waits for the frame
                self._worker.submit(_timed(frame.load), functools.partial(self._read, frame))
                return
            start_rel = self._source.scale(frame.exposure_start_ns)
            end_rel = start_rel + frame.exposure_ns
            if end_rel < self._joined_rel:
                continue
            # A real camera cannot deliver a frame late: if rendering or reading fell a
            # frame period behind, this frame is skipped (and counted) instead.
            if self._timeline.late_ns(end_rel) > self.rate.period_ns:
                self._images.count_skip("late")
                self.rate.late(self._log)
                continue
            made = functools.partial(self._made_at, frame, start_rel, end_rel)
            self._worker.submit(_timed(frame.load), made)
            return
        if self._config.source.kind == "device" or self._config.source.exit_when_done:
            self._stop.set()

    def _made_at(self, frame: SourceFrame, start_rel: int, end_rel: int, made: Loaded) -> None:
        """(the executor) A frame is made: it exists once its exposure has ended, not
        before, so it is put then (``on_time``)."""
        image = self._loaded(frame, made)
        if image is None:
            self._next()
            return
        self._made = (frame, image, start_rel)
        self._node.at(time.monotonic_ns() - self._timeline.late_ns(end_rel), self.on_time)

    def _read(self, frame: SourceFrame, read: Loaded) -> None:
        """(the executor) A device's frame is read: put at once, then the next read."""
        image = self._loaded(frame, read)
        if image is not None:
            self._put(frame, image, Exposure(frame.exposure_start_ns, frame.exposure_ns))
        self._node.at(time.monotonic_ns(), self.on_time)  # others' turn between reads

    def _loaded(self, frame: SourceFrame, outcome: Loaded) -> npt.NDArray[np.uint8] | None:
        """The image a step made, its time counted; None for a frame its source cannot
        give (counted ``unreadable``); anything else it raised is the executor's to log."""
        if isinstance(outcome.error, FramegateError):
            self._unreadable(frame, outcome.error)
            return None
        if outcome.error is not None:
            raise outcome.error
        assert outcome.value is not None  # a step that did not raise returned its image
        image, load_ns = outcome.value
        self.rate.loaded(load_ns)
        return image

    def close(self) -> None:
        self._worker.close()

    def _unreadable(self, frame: SourceFrame, exc: FramegateError) -> None:
        """A frame its source cannot give (a replayed dataset's missing or damaged image):
        skipped and counted, said once; the camera goes on with the next."""
        self._images.count_skip("unreadable")
        if not self._warned_unreadable:
            self._warned_unreadable = True
            self._log.warning(
                "frame %d skipped: %s (counted as unreadable in 'framegate info %s'; further "
                "ones are not logged)",
                frame.frame_id,
                exc,
                self._images.name,
            )

    def _put(self, frame: SourceFrame, image: npt.NDArray[np.uint8], exposure: Exposure) -> None:
        self.rate.made(self._log)
        metadata = frame_metadata(frame.frame_id, exposure, image, self._source.camera)
        config = self._config
        try:
            self._images.put(
                exposure.start_ns,
                image.tobytes(),
                metadata,
                wait_s=config.lossless_wait_s if config.lossless else 0.0,
            )
            self.produced += 1
        except FlowControlRefused:
            self.dropped += 1  # dropped at the source, counted in images.info().refused
        except ClosedError:
            pass  # a stop came between this frame's exposure and its put
        except FramegateError as exc:
            self._log.warning("frame %d not stored: %s", frame.frame_id, exc)


# A frame made by the worker, with how long it took (ns).
Loaded = Outcome[tuple[npt.NDArray[np.uint8], int]]


def _timed(
    load: Callable[[], npt.NDArray[np.uint8]],
) -> Callable[[], tuple[npt.NDArray[np.uint8], int]]:
    """``load`` as a worker step that also says how long it took."""

    def step() -> tuple[npt.NDArray[np.uint8], int]:
        started = time.monotonic_ns()
        image = load()
        return image, time.monotonic_ns() - started

    return step


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

    def loaded(self, load_ns: int) -> None:
        """A frame took ``load_ns`` to render or read."""
        self._load_ns.append(load_ns)

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


SERVICE: Service[CameraConfig] = source_service("camera", CameraConfig, run, device=True)
