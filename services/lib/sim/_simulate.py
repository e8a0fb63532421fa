"""Render a whole scenario into a dataset directory, with a progress bar on a terminal
(``disable=None``: none when stderr is no terminal, so a log gets no \\r updates)."""

from __future__ import annotations

import dataclasses
import os
import threading
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from middleware import FramegateError

from ._config import ScenarioConfig
from ._dataset import DatasetWriter
from ._records import FrameTruth
from ._scenario import Scenario


@dataclass(frozen=True, slots=True)
class SimulationRun:
    """What :func:`simulate` did."""

    root: Path
    frame_count: int
    render_s: float

    @property
    def frames_per_s(self) -> float:
        """Frames rendered (with truth, written) per second."""
        return self.frame_count / self.render_s if self.render_s > 0 else float("inf")


class RenderStopped(FramegateError):
    """``simulate``'s ``stop`` was set before the last frame: the dataset is incomplete."""


def simulate(
    config: ScenarioConfig, out: str | Path, *, progress: bool = True, overwrite: bool = False,
    workers: int | None = None, stop: threading.Event | None = None,
) -> SimulationRun:  # fmt: skip
    """Render every frame of the scenario with its truth and write the dataset to ``out``.

    Frames are rendered by ``workers`` threads (default: one per CPU); OpenCV and numpy
    release the GIL for the heavy work, and every frame has its own random stream, so the
    bytes written do not depend on the number of threads. ``stop`` set: the frames not yet
    started are dropped, the ones rendering finish (a frame or two per thread), and
    ``RenderStopped`` is raised; a service's Ctrl-C must not wait minutes for a render.
    """
    scenario = Scenario(config)
    workers = max(1, workers if workers is not None else (os.cpu_count() or 1))
    with DatasetWriter(
        out, scenario.camera, exposure_ns=config.exposure_ns,
        frame_period_ns=config.frame_period_ns, scenario=config, overwrite=overwrite,
    ) as writer:  # fmt: skip
        writer.write_gyro(scenario.gyro_samples())
        writer.set_truth_extra(bumps=[dataclasses.asdict(b) for b in scenario.bumps])
        started = time.perf_counter()
        scenario.renderer.scene  # noqa: B018 -- build textures once, before the threads share them

        def job(frame_id: int) -> tuple[np.ndarray, FrameTruth]:
            return scenario.render(frame_id), scenario.truth(frame_id)

        with (
            ThreadPoolExecutor(workers) as pool,
            tqdm(total=config.frame_count, desc="rendering", unit="frame",
                 disable=None if progress else True) as bar,
        ):  # fmt: skip
            # A short window of frames in flight bounds memory; results are taken in order.
            pending: deque[tuple[int, Future[tuple[np.ndarray, FrameTruth]]]] = deque()
            for frame_id in range(config.frame_count):
                _unless_stopped(stop, pending, frame_id, config.frame_count)
                pending.append((frame_id, pool.submit(job, frame_id)))
                if len(pending) > 2 * workers:
                    _write_next(writer, scenario, pending, bar)
            while pending:
                _unless_stopped(stop, pending, pending[0][0], config.frame_count)
                _write_next(writer, scenario, pending, bar)
        elapsed = time.perf_counter() - started
    return SimulationRun(Path(out), config.frame_count, elapsed)


def _unless_stopped(
    stop: threading.Event | None, pending: deque[tuple[int, Future[Any]]], frame_id: int,
    count: int,
) -> None:  # fmt: skip
    if stop is None or not stop.is_set():
        return
    for _, future in pending:
        future.cancel()
    raise RenderStopped(f"stopped while rendering frame {frame_id} of {count}")


def _write_next(
    writer: DatasetWriter, scenario: Scenario,
    pending: deque[tuple[int, Future[tuple[np.ndarray, FrameTruth]]]], bar: tqdm[None],
) -> None:  # fmt: skip
    frame_id, future = pending.popleft()
    image, truth = future.result()
    writer.add_frame(scenario.frame_info(frame_id), image)
    writer.add_truth(truth)
    bar.update()
