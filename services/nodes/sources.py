"""Where the camera and gyro services get their data: simulator, dataset replay, device.

``sim`` renders each frame live (about a second of CPU per frame: a small machine cannot keep
15 frames/s); ``prerendered`` plays the same simulated approach rendered once and cached per
scenario (``services.lib.sim.cached_dataset``; the first start renders it with a progress
bar), so the camera keeps its nominal rate; ``replay DIR`` plays any dataset directory.

Simulated and replayed sources give times relative to a dataset epoch (camera clock for
frames, gyro clock for gyro samples); the services map them onto the wall clock from a
shared start instant, divided by ``--rate``. A device gives wall-clock times directly.
"""

from __future__ import annotations

import argparse
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from middleware import ConfigError, NetworkConfig, now_ns
from services.lib.argtypes import non_negative_int, positive_float, positive_int, positive_rate
from services.lib.camera_model import CameraModel
from services.lib.settings import add_flags, from_args, setting
from services.nodes._contract import ConfigT, Service, ServiceEntry

# Where frames come from; ``prerendered``'s optional path is its cache directory.
KINDS = ("sim", "prerendered", "replay", "device")


@dataclass(frozen=True, slots=True)
class SourceSpec:
    """Which source, and how to play it."""

    kind: str = setting(
        "sim", "where data comes from", flag="--source", choices=KINDS, dest="source"
    )
    path: str | None = setting(
        None, "dataset directory (replay), cache directory (prerendered) or device index/URL"
    )
    seed: int = setting(1, "simulator seed (sim, prerendered)", parse=non_negative_int)
    rate: float = setting(1.0, "replay speed factor", parse=positive_rate)
    loop: bool = setting(False, "start over at the end")
    frames: int | None = setting(None, "play only the first N frames", parse=positive_int)
    start_at_ns: int | None = setting(
        None,
        "wall-clock ns of replay time zero (default: $FRAMEGATE_START_AT_NS or now)",
        flag="--start-at",
        parse=int,
    )
    exit_when_done: bool = setting(False, "exit after the last element")
    exposure_ms: float = setting(30.0, "exposure time of a device camera", parse=positive_float)
    camera_xml: str | None = setting(
        None, "description of a device camera (camera metadata XML; --source device only)"
    )
    floor: str = setting(
        "default", "floor of the simulated approach (sim, prerendered): smooth, default or rough"
    )

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ConfigError(
                f"unknown source {self.kind!r}: use sim, prerendered, replay DIR or device N|URL"
            )
        if self.kind in ("replay", "device") and not self.path:
            raise ConfigError(f"source {self.kind} needs a path (--path)")
        if self.rate <= 0:
            raise ConfigError(f"--rate must be > 0, got {self.rate}")

    def scenario(self) -> Any:
        """The simulated approach of ``sim`` and ``prerendered`` (a ``ScenarioConfig``)."""
        from services.lib.sim import ScenarioConfig

        return ScenarioConfig(seed=self.seed).with_floor(self.floor)


@dataclass(frozen=True, slots=True)
class SourceFrame:
    """One frame and when it was exposed (relative to the source's epoch, or wall clock).

    ``load()`` renders or reads the image; a camera that is already too late for the frame
    skips it without paying for that.
    """

    frame_id: int
    exposure_start_ns: int
    exposure_ns: int
    load: Callable[[], npt.NDArray[np.uint8]]


class _Timeline:
    """Common to replayed sources: the loop period and the rate scaling."""

    relative = True

    def __init__(self, spec: SourceSpec, period_ns: int, count: int) -> None:
        self.spec = spec
        self.frame_period_ns = period_ns
        self.count = count if spec.frames is None else min(count, spec.frames)
        self.loop_ns = self.count * period_ns

    def scale(self, t_rel_ns: int) -> int:
        """Relative dataset time → relative wall time at ``--rate``."""
        return int(t_rel_ns / self.spec.rate)

    def loops(self, stop: threading.Event) -> Iterator[int]:
        k = 0
        while not stop.is_set():
            yield k * self.loop_ns
            k += 1
            if not self.spec.loop:
                return


class FrameSource(_Timeline):
    """Frames of the simulator or a dataset on disk."""

    def __init__(self, spec: SourceSpec, stop: threading.Event | None = None) -> None:
        if spec.kind == "sim":
            from services.lib.sim import FrameCache, Scenario

            self._scenario: Any = Scenario(spec.scenario())
            self._cache = FrameCache.from_env(self._scenario.config)
            self.camera: CameraModel = self._scenario.camera
            infos = [self._scenario.frame_info(i) for i in range(self._scenario.frame_count)]
            self.description = f"simulated approach, seed {spec.seed}"
        else:
            self._scenario = _dataset(spec, stop)
            self.camera = self._scenario.camera
            infos = list(self._scenario.frames)
            self.description = _described(spec)
        if not infos:
            raise ConfigError(f"{self.description} has no frames")
        self._infos = infos
        period = (
            int(np.median(np.diff([i.exposure_start_ns for i in infos])))
            if len(infos) > 1
            else 66_666_667
        )
        super().__init__(spec, period, len(infos))
        self.exposure_ns = int(infos[0].exposure_ns)
        if spec.rate != 1.0:
            self.description += f" at {spec.rate}x"

    def _image(self, index: int) -> npt.NDArray[np.uint8]:
        if self.spec.kind == "sim":
            render = partial(self._scenario.render, index)
            image = render() if self._cache is None else self._cache.frame(index, render)
            return np.asarray(image, dtype=np.uint8)
        return np.asarray(self._scenario.image(index), dtype=np.uint8)

    def frames(self, stop: threading.Event) -> Iterator[SourceFrame]:
        frame_id = 0
        for offset in self.loops(stop):
            for index in range(self.count):
                if stop.is_set():
                    return
                info = self._infos[index]
                yield SourceFrame(
                    frame_id,
                    offset + int(info.exposure_start_ns),
                    int(info.exposure_ns),
                    partial(self._image, index),
                )
                frame_id += 1


class GyroSource(_Timeline):
    """Gyro samples of the simulator or a dataset, on the gyro clock."""

    def __init__(self, spec: SourceSpec, stop: threading.Event | None = None) -> None:
        if spec.kind == "sim":
            from services.lib.sim import Scenario

            scenario: Any = Scenario(spec.scenario())
            trace = scenario.gyro_samples()
            period, count = scenario.config.frame_period_ns, scenario.frame_count
            first_frame_ns = scenario.frame_info(0).exposure_start_ns
            self.description = f"simulated gyro, seed {spec.seed}"
        elif spec.kind in ("replay", "prerendered"):
            dataset: Any = _dataset(spec, stop)
            trace = dataset.gyro
            starts = [f.exposure_start_ns for f in dataset.frames]
            period = int(np.median(np.diff(starts))) if len(starts) > 1 else 66_666_667
            count = len(starts)
            first_frame_ns = starts[0] if starts else 0
            self.description = _described(spec)
        else:
            raise ConfigError(
                "the gyro service has no device source; use sim, prerendered or replay DIR"
            )
        super().__init__(spec, period, count)
        # A loop repeats the span of the frames (which need not start at zero), so each
        # pass carries the gyro samples of exactly that span.
        self._first_ns = int(first_frame_ns) - period // 2
        self._t = np.asarray(trace.t_ns, dtype=np.int64)
        self._w = np.asarray(trace.rate_rad_s, dtype=np.float64)
        self.period_ns = int(np.median(np.diff(self._t))) if len(self._t) > 1 else 2_000_000

    def batches(
        self, size: int, stop: threading.Event
    ) -> Iterator[tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]]:
        """(t_rel_ns, rates) batches; a loop repeats the samples of [0, loop) shifted."""
        for offset in self.loops(stop):
            if self.spec.loop:
                # Only one loop period per pass, so looped times keep increasing.
                keep = (self._t >= self._first_ns) & (self._t < self._first_ns + self.loop_ns)
                t, w = self._t[keep], self._w[keep]
            else:
                t, w = self._t, self._w
            for i in range(0, len(t), size):
                if stop.is_set():
                    return
                yield t[i : i + size] + offset, w[i : i + size]


class DeviceSource:
    """A cv2.VideoCapture (camera index or URL); wall-clock times."""

    relative = False

    def __init__(self, spec: SourceSpec) -> None:
        import cv2

        target: int | str = int(str(spec.path)) if str(spec.path).isdigit() else str(spec.path)
        # OpenCV logs a WARN line per backend it tries on a missing device: the error below
        # is the one line a user needs.
        level = cv2.utils.logging.getLogLevel()
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
        try:
            self._capture = cv2.VideoCapture(target)
        finally:
            cv2.utils.logging.setLogLevel(level)
        if not self._capture.isOpened():
            raise ConfigError(f"cannot open video device {spec.path!r}")
        self.spec = spec
        self.exposure_ns = int(spec.exposure_ms * 1e6)
        fps = float(self._capture.get(cv2.CAP_PROP_FPS) or 0) or 15.0
        self.frame_period_ns = int(1e9 / fps)
        ok, first = self._capture.read()
        if not ok:
            raise ConfigError(f"video device {spec.path!r} delivered no image")
        self._first = self._gray(first)
        height, width = self._first.shape
        self.camera = (
            CameraModel.from_xml(Path(spec.camera_xml).read_bytes())
            if spec.camera_xml
            else CameraModel(width, height, float(width), float(width), width / 2, height / 2)
        )
        self.description = f"device {spec.path}"

    @staticmethod
    def _gray(image: Any) -> npt.NDArray[np.uint8]:
        import cv2

        array = np.asarray(image)
        if array.ndim == 3:
            array = cv2.cvtColor(array, cv2.COLOR_BGR2GRAY)
        return np.ascontiguousarray(array, dtype=np.uint8)

    def scale(self, t_ns: int) -> int:
        return t_ns

    def frames(self, stop: threading.Event) -> Iterator[SourceFrame]:
        frame_id = 0
        image: npt.NDArray[np.uint8] | None = self._first
        while not stop.is_set():
            if image is None:
                ok, raw = self._capture.read()
                if not ok:
                    return
                image = self._gray(raw)
            # Read time is the end of exposure (the driver gives no better clock here), on
            # the process clock: a backward step of the system clock (NTP) must not stamp
            # frames backward (each was refused as older than the newest, for the step's
            # length: all 1,947 read in 10 s after a -30 s step, with a warning each).
            start = now_ns() - self.exposure_ns
            yield SourceFrame(frame_id, start, self.exposure_ns, partial(_same, image))
            image = None
            frame_id += 1


def _dataset(spec: SourceSpec, stop: threading.Event | None) -> Any:
    """The dataset a replayed or prerendered spec plays (prerendered: rendered if not cached;
    ``RenderStopped`` if ``stop`` is set meanwhile)."""
    from services.lib.sim import (
        DatasetError,
        approach_cache_dir,
        cached_dataset,
        read_dataset,
    )

    try:
        if spec.kind == "prerendered":
            cache = Path(spec.path) if spec.path else approach_cache_dir()
            return cached_dataset(spec.scenario(), cache, stop=stop)
        return read_dataset(Path(str(spec.path)))
    except DatasetError as exc:
        raise ConfigError(str(exc)) from exc


def _described(spec: SourceSpec) -> str:
    if spec.kind == "prerendered":
        return f"prerendered approach, seed {spec.seed}"
    return f"replay of {spec.path}"


def _same(image: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    return image


def check_device_only(kind: str, camera_xml: str | None) -> None:
    """ConfigError for a camera description given to a source that is no device: only a
    device reads it (a simulated or recorded source brings its own), so it would be
    silently ignored."""
    if camera_xml is not None and kind != "device":
        raise ConfigError(
            f"--camera-xml describes a device camera (--source device); a {kind} source "
            "brings its own description: leave --camera-xml out"
        )


def open_frame_source(
    spec: SourceSpec, stop: threading.Event | None = None
) -> FrameSource | DeviceSource:
    """The frame source a spec names (``stop``: see ``_dataset``)."""
    check_device_only(spec.kind, spec.camera_xml)
    return DeviceSource(spec) if spec.kind == "device" else FrameSource(spec, stop)


def open_gyro_source(spec: SourceSpec, stop: threading.Event | None = None) -> GyroSource:
    """The gyro source a spec names (``stop``: see ``_dataset``)."""
    return GyroSource(spec, stop)


# What only a camera device has.
_DEVICE_ONLY = ("exposure_ms", "camera_xml")


def add_source_arguments(parser: argparse.ArgumentParser, *, device: bool) -> None:
    """--source and how to play it, shared by camera and gyro (a gyro has no device)."""
    kinds = list(KINDS) if device else [k for k in KINDS if k != "device"]
    add_flags(parser, SourceSpec, skip=() if device else _DEVICE_ONLY, choices={"kind": kinds})


def source_from_args(args: argparse.Namespace) -> SourceSpec:
    spec: SourceSpec = from_args(SourceSpec, args)
    return spec


def source_service(
    name: str,
    config_type: type[ConfigT],
    run: Callable[[ConfigT, NetworkConfig, threading.Event], int],
    *,
    device: bool,
) -> Service[ConfigT]:
    """A source service (camera, gyro): flags one per config field plus ``--source`` and
    how to play it; its config carries the parsed source as ``source``."""

    def add_arguments(parser: argparse.ArgumentParser) -> None:
        add_flags(parser, config_type)
        add_source_arguments(parser, device=device)

    def config_from_args(args: argparse.Namespace) -> ConfigT:
        config: ConfigT = from_args(config_type, args, source=source_from_args(args))
        return config

    return ServiceEntry(name, config_type, add_arguments, config_from_args, run)
