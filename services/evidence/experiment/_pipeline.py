"""One configuration through real service processes on a private loopback rendezvous.

Camera replay, gyro replay, (mediator,) detector: each its own OS process, started by the
launch supervisor with a shared replay start instant. This process only watches, through a
client Node that never subscribes (so it never holds a producer back), and collects every
result from the services' own buffers before it stops them.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import psutil
from tqdm import tqdm

from middleware import BufferInfo, DataObject, FramegateError, NetworkConfig, Node
from services.launch import (
    ArgValue,
    Deployment,
    Supervisor,
    free_port,
    pipeline,
    private_specs,
)
from services.lib.messages import DecisionRecord
from services.lib.sim import Dataset

from ._config import ExperimentError, RunKind
from ._records import FrameDetections, RunRecord

# How long the counters may stand still, past the replay's end, before we stop waiting.
_STALL_S = 10.0
_POLL_S = 0.25
_ATTEMPTS = 4
# The longest start-up a retry is given. The camera stamps its camera/info with the replay's
# time zero, and a producer refuses elements stamped 10 s or more ahead of its clock: with a
# longer start-up a camera that came up quickly exited on its own first put (seen at 12 s).
MAX_STARTUP_S = 9.0
_CONSUMER_TIMEOUT_S = 60.0
# Collecting: how often a query of a service that is not live is asked, and how far apart.
_QUERY_TRIES = 5
_QUERY_RETRY_S = 2.0
_PRODUCERS = ("camera", "gyro")
# The `all` run is about every frame, not time: at half speed a busy machine does not make
# the camera fall a frame behind (and skip it).
_ALL_RATE = 0.5


@dataclass(frozen=True, slots=True)
class RunSettings:
    """How one run is set up (the same for every configuration of a seed)."""

    queue: int
    service_factor: float
    b0_px: float
    startup_s: float
    progress: bool = True
    log_dir: Path | None = None


def _frame_period_ms(dataset: Dataset) -> float:
    starts = [f.exposure_start_ns for f in dataset.frames]
    if len(starts) < 2:
        raise ExperimentError(f"dataset {dataset.root} has fewer than two frames")
    return (starts[-1] - starts[0]) / (len(starts) - 1) / 1e6


def deployment_for(kind: RunKind, dataset: Dataset, settings: RunSettings) -> Deployment:
    """The pipeline (deploy/local.yaml) replaying ``dataset`` in one configuration (see
    RunKind), no service restarted on a crash."""
    path = str(dataset.root)
    frames = len(dataset)
    replay: dict[str, ArgValue] = {"source": "replay", "path": path, "seed": None, "loop": None}
    camera = dict(replay)
    detector: dict[str, ArgValue] = {"frame_period_ms": f"{_frame_period_ms(dataset):.6f}"}
    if kind is RunKind.ALL:
        # Every frame, regardless of time: the camera waits instead of dropping, the queue
        # and retention hold the whole approach, and there is no emulated load.
        camera |= {"rate": _ALL_RATE, "lossless": True, "retention_frames": frames + 8}
        detector |= {"input": "camera/images", "queue": frames + 8, "service_factor": None}
    else:
        source = "camera/images" if kind is RunKind.UNCONTROLLED else "mediator/images"
        detector |= {
            "input": source,
            "queue": settings.queue,
            "service_factor": settings.service_factor,
        }
    mediator: dict[str, ArgValue] | None = None
    if kind.policy is not None:
        mediator = {"policy": kind.policy, "b0": settings.b0_px}
    return pipeline(
        {"camera": camera, "gyro": replay, "mediator": mediator, "detector": detector},
        name=f"experiment-{kind.value}",
        restart=False,
    )


class _Watch:
    """Reads the services' buffer descriptions; checks that no process has died."""

    def __init__(
        self, node: Node, supervisors: list[Supervisor], lines: list[str], what: str
    ) -> None:
        self.node = node
        self.supervisors = supervisors
        self.lines = lines
        self.what = what

    def buffers(self) -> dict[str, BufferInfo]:
        self.check_alive()
        out: dict[str, BufferInfo] = {}
        try:
            for service in self.node.services(timeout_s=1.0):
                for buffer in service.buffers:
                    out[buffer.name] = buffer
        except FramegateError:
            pass
        return out

    def check_alive(self) -> None:
        dead = []
        for supervisor in self.supervisors:
            supervisor.poll()
            dead += [name for name, pid in supervisor.pids().items() if pid is None]
        if dead:
            tail = "\n".join(self.lines[-15:])
            raise ExperimentError(f"{self.what}: {', '.join(dead)} exited early; log:\n{tail}")


def _ready(kind: RunKind, buffers: dict[str, BufferInfo]) -> bool:
    """Every subscription the run needs is registered with its producer."""
    needed = ["camera/images", "gyro/rates", "detector/detections"]
    if kind.policy is not None:
        needed += ["mediator/images", "mediator/decisions"]
    if any(name not in buffers for name in needed):
        return False
    if kind.policy is None:
        return len(buffers["camera/images"].subscriptions) == 1
    return (
        len(buffers["camera/images"].subscriptions) == 1
        and len(buffers["gyro/rates"].subscriptions) == 1
        and len(buffers["mediator/images"].subscriptions) == 1
    )


def _wait(
    watch: _Watch, predicate: Callable[[dict[str, BufferInfo]], bool], stalled: Callable[[], bool]
) -> dict[str, BufferInfo]:
    while True:
        buffers = watch.buffers()
        if predicate(buffers) or stalled():
            return buffers
        time.sleep(_POLL_S)


def _count(buffers: dict[str, BufferInfo], name: str, what: str = "puts") -> int:
    info = buffers.get(name)
    return int(getattr(info, what)) if info is not None else 0


def _query(node: Node, key: str) -> list[DataObject]:
    """Every element of ``key``, asked again (at most ``_QUERY_TRIES`` times) when its
    service was not live: on an overloaded machine a service that did not run past its 1 s
    lease is dropped by its peers until it reconnects (3.5 s without running seen at load
    29), and one such moment at the end lost the whole run."""
    for attempt in range(1, _QUERY_TRIES + 1):
        try:
            return node.query(key, timeout_s=10.0)
        except FramegateError:
            if attempt == _QUERY_TRIES:
                raise
            time.sleep(_QUERY_RETRY_S)
    raise AssertionError("unreachable")


def _decisions(node: Node) -> tuple[list[DecisionRecord], list[DecisionRecord]]:
    """The first and the latest decision per frame (a held frame is decided again when it
    leaves; its first record was written when the mediator first decided it)."""
    first: dict[int, DecisionRecord] = {}
    final: dict[int, DecisionRecord] = {}
    for element in _query(node, "mediator/decisions"):
        record = DecisionRecord.from_metadata(element.metadata)
        first.setdefault(record.frame_timestamp_ns, record)
        final[record.frame_timestamp_ns] = record
    return (
        sorted(first.values(), key=lambda r: r.frame_timestamp_ns),
        sorted(final.values(), key=lambda r: r.frame_timestamp_ns),
    )


def _final_decisions(node: Node) -> list[DecisionRecord]:
    """The latest decision per frame."""
    return _decisions(node)[1]


def run_configuration(
    kind: RunKind, dataset: Dataset, seed: int, settings: RunSettings
) -> RunRecord:
    """Replay ``dataset`` through the services of ``kind`` in real time and collect.

    The consumers (mediator, detector) start first; once they are live, the camera and gyro
    replays start with a time zero ``settings.startup_s`` ahead. If they are not up and
    subscribed by then (a busy machine), the run is abandoned and tried again with twice
    the start-up time, at most ``MAX_STARTUP_S``; ``RunRecord.startup_s`` says what worked.
    """
    startup_s = settings.startup_s
    for attempt in range(1, _ATTEMPTS + 1):
        record = _attempt(kind, dataset, seed, settings, startup_s, attempt)
        if record is not None:
            return record
        startup_s = min(2 * startup_s, MAX_STARTUP_S)
    raise ExperimentError(
        f"seed {seed} {kind.value}: the camera and gyro did not come up within "
        f"{startup_s:.0f} s in {_ATTEMPTS} attempts; is the machine overloaded?"
    )


def _attempt(
    kind: RunKind, dataset: Dataset, seed: int, settings: RunSettings, startup_s: float,
    attempt: int,
) -> RunRecord | None:  # fmt: skip
    what = f"seed {seed} {kind.value}"
    frames = len(dataset)
    rate = _ALL_RATE if kind is RunKind.ALL else 1.0
    port = free_port()
    lines: list[str] = []
    load_before = os.getloadavg()[0]
    psutil.cpu_percent(interval=None)  # starts the machine-wide CPU measurement
    started = time.monotonic()
    deployment = deployment_for(kind, dataset, settings)
    # This client is the first on the port, so it is the rendezvous hub for the whole run.
    with Node(network=NetworkConfig(local_port=port)) as node:
        consumers = Supervisor(
            [s for s in private_specs(deployment, port, start_at_ns=0) if s.name not in _PRODUCERS],
            colour=False,
            out=lines.append,
        )
        watch = _Watch(node, [consumers], lines, what)
        producers: Supervisor | None = None
        consumers.start()
        try:
            _wait_consumers(watch, kind)
            start_at_ns = time.time_ns() + int(startup_s * 1e9)
            producers = Supervisor(
                [
                    s
                    for s in private_specs(deployment, port, start_at_ns=start_at_ns)
                    if s.name in _PRODUCERS
                ],
                colour=False,
                out=lines.append,
            )
            watch.supervisors.append(producers)
            producers.start()
            ready_by = start_at_ns - int(0.3e9)
            buffers = _wait(watch, lambda b: _ready(kind, b), lambda: time.time_ns() > ready_by)
            if not _ready(kind, buffers):
                seen = {name: len(info.subscriptions) for name, info in buffers.items()}
                lines.append(
                    f"experiment: attempt {attempt}: camera and gyro not ready {startup_s:.1f} s "
                    f"after their start (buffers and their subscriptions: {seen}); retrying"
                )
                return None
            # The replay: until every frame was stored or refused at the camera.
            last_end_ns = dataset.frames[-1].exposure_start_ns + dataset.frames[-1].exposure_ns
            replay_end_ns = start_at_ns + int(last_end_ns / rate)
            buffers = _replay(watch, frames, replay_end_ns, settings.progress, what)
            buffers, drained = _drain(watch, kind, buffers)
            record = _collect(node, watch, kind, seed, frames, buffers)
            cpu_s = _cpu_seconds([consumers, producers])
        finally:
            if producers is not None:
                producers.stop()
            consumers.stop()
            if settings.log_dir is not None:
                settings.log_dir.mkdir(parents=True, exist_ok=True)
                log = settings.log_dir / f"seed{seed}-{kind.value}.log"
                with log.open("w" if attempt == 1 else "a", encoding="utf-8") as handle:
                    handle.write("\n".join(lines) + "\n")
    return replace(
        record,
        wall_s=time.monotonic() - started,
        attempts=attempt,
        startup_s=startup_s,
        drained=drained,
        load_avg=(load_before, os.getloadavg()[0]),
        cpu_busy_pct=psutil.cpu_percent(interval=None),
        cpu_s=cpu_s,
    )


def _wait_consumers(watch: _Watch, kind: RunKind) -> None:
    """Mediator and detector up, whatever it takes (they wait for the replay, not it for
    them); only a process that dies or a minute without them is an error."""
    needed = ["detector/detections"] + (["mediator/images"] if kind.policy else [])
    deadline = time.monotonic() + _CONSUMER_TIMEOUT_S
    buffers = _wait(
        watch,
        lambda b: all(name in b for name in needed),
        lambda: time.monotonic() > deadline,
    )
    if not all(name in buffers for name in needed):
        tail = "\n".join(watch.lines[-15:])
        raise ExperimentError(
            f"{watch.what}: mediator/detector not up after {_CONSUMER_TIMEOUT_S:.0f} s; "
            f"log:\n{tail}"
        )


def _replay(
    watch: _Watch, frames: int, replay_end_ns: int, progress: bool, what: str
) -> dict[str, BufferInfo]:
    seen = {"n": -1, "since": time.monotonic()}

    def handled(buffers: dict[str, BufferInfo]) -> int:
        return _count(buffers, "camera/images") + _count(buffers, "camera/images", "refused")

    def stalled() -> bool:
        # Frames the camera skipped as late are never stored nor refused: once the replay
        # is over and nothing moves for a while, stop waiting for them.
        return (
            time.time_ns() > replay_end_ns + int(2e9)
            and time.monotonic() - seen["since"] > _STALL_S / 2
        )

    # disable=None: no bar when stderr is no terminal (a log gets no \r updates).
    disable = None if progress else True
    with tqdm(total=frames, desc=what, unit="frame", disable=disable, leave=False) as bar:

        def done(buffers: dict[str, BufferInfo]) -> bool:
            n = handled(buffers)
            if n != seen["n"]:
                seen["n"], seen["since"] = n, time.monotonic()
                bar.update(n - bar.n)
                bar.set_postfix(
                    dropped=_count(buffers, "camera/images", "refused"),
                    processed=_count(buffers, "detector/detections"),
                )
            return n >= frames

        return _wait(watch, done, stalled)


def _drain(
    watch: _Watch, kind: RunKind, buffers: dict[str, BufferInfo]
) -> tuple[dict[str, BufferInfo], bool]:
    """Wait until the detector has processed everything it was given (and, with a mediator,
    every stored frame has a final decision); False if it stalled instead."""
    source = "camera/images" if kind.policy is None else "mediator/images"
    seen = {"n": -1, "since": time.monotonic()}

    def drained(buffers: dict[str, BufferInfo]) -> bool:
        progress = _count(buffers, "detector/detections") + _count(buffers, "mediator/decisions")
        if progress != seen["n"]:
            seen["n"], seen["since"] = progress, time.monotonic()
        queues = [
            s.queued
            for name in ("camera/images", "mediator/images")
            if name in buffers
            for s in buffers[name].subscriptions
        ]
        if any(queues) or _count(buffers, "detector/detections") < _count(buffers, source):
            return False
        if kind.policy is None:
            return True
        decisions = _final_decisions(watch.node)
        return len(decisions) >= _count(buffers, "camera/images") and not any(
            d.reason == "held" for d in decisions
        )

    buffers = _wait(watch, drained, lambda: time.monotonic() - seen["since"] > _STALL_S)
    done = drained(buffers)
    if not done:
        # What each side saw when progress stopped (typed counters, for the run's log): a
        # subscription whose producer still counts elements queued has not taken them (or
        # its ack was lost); one at 0 took everything it was sent.
        state = {
            name: {
                "stored": info.puts,
                "refused": info.refused,
                "skipped": dict(info.skipped),
                "queued": [s.queued for s in info.subscriptions],
            }
            for name, info in sorted(buffers.items())
        }
        watch.lines.append(f"experiment: drain stalled for {_STALL_S:.0f} s: {state}")
    return buffers, done


def _collect(
    node: Node, watch: _Watch, kind: RunKind, seed: int, frames: int,
    buffers: dict[str, BufferInfo],
) -> RunRecord:  # fmt: skip
    detections = [
        FrameDetections.from_metadata(e.metadata) for e in _query(node, "detector/detections")
    ]
    first, decisions = _decisions(node) if kind.policy is not None else ([], [])
    watch.check_alive()
    stored = _count(buffers, "camera/images")
    dropped = _count(buffers, "camera/images", "refused")
    return RunRecord(
        kind=kind,
        seed=seed,
        frame_count=frames,
        stored=stored,
        dropped=dropped,
        skipped_late=max(0, frames - stored - dropped),
        forwarded=_count(buffers, "mediator/images") if kind.policy is not None else None,
        detections=tuple(sorted(detections, key=lambda d: d.frame_id)),
        decisions=tuple(decisions),
        first_decisions=tuple(first),
        gyro_batches=_count(buffers, "gyro/rates"),
        gyro_dropped=_count(buffers, "gyro/rates", "refused"),
        wall_s=0.0,
        attempts=1,
        startup_s=0.0,
        drained=True,
        load_avg=(0.0, 0.0),
        cpu_busy_pct=0.0,
        cpu_s={},
    )


def _cpu_seconds(supervisors: list[Supervisor]) -> dict[str, float]:
    out: dict[str, float] = {}
    pids = {name: pid for sup in supervisors for name, pid in sup.pids().items()}
    for name, pid in pids.items():
        if pid is None:
            continue
        try:
            times = psutil.Process(pid).cpu_times()
        except psutil.Error:
            continue
        out[name] = float(times.user + times.system)
    return out
