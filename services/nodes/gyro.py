"""The gyro service: angular-rate samples in gyro/rates, one element per sample.

Each sample is its own element (a one-sample ``gyro`` payload keyed by its time), so a query
by time finds single samples; they are published in batches with ``put_many`` (default 10
samples = 20 ms at 500 Hz): one message and one ack per batch, so 500-1000 Hz does not mean
1000 messages per second; samples are small, so they reach subscribers inline with the
notification. A batch never exceeds the smallest flow-controlled queue (queues count
elements, and a batch larger than one could never be accepted). Buffering rule: a consumer
that may lose nothing waits — when flow control refuses a batch, the gyro waits up to
``--wait-ms`` for credit (a sensor FIFO would buffer too), then drops the batch and counts
its samples.

Threads: none of its own; each batch is put by a deadline on the node's executor
(``GyroPump``), and the main thread waits in ``Node.spin``.
"""

from __future__ import annotations

import logging
import threading
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
    SubscriptionMode,
)
from services.lib.argtypes import non_negative_float, positive_float, positive_int
from services.lib.messages import gyro_metadata
from services.lib.quality import GyroSamples
from services.lib.settings import setting
from services.nodes._contract import Service
from services.nodes._runtime import Timeline, run_source, start_at_ns
from services.nodes.sources import (
    GyroSource,
    SourceSpec,
    open_gyro_source,
    source_service,
)

# Batches older than this when their time comes are skipped, not sent.
_STALE_NS = 500_000_000


@dataclass(frozen=True, slots=True)
class GyroConfig:
    """Everything the gyro service can be told."""

    source: SourceSpec
    name: str = setting("gyro", "service name")
    batch: int = setting(10, "samples per message (put_many batch)", parse=positive_int)
    wait_ms: float = setting(
        50.0,
        "how long a refused batch waits for credit before it is dropped",
        parse=non_negative_float,
    )
    retention_s: float = setting(
        30.0, "how many seconds of batches gyro/rates keeps", parse=positive_float
    )


def run(config: GyroConfig, network: NetworkConfig, stop: threading.Event | None = None) -> int:
    """Produce batches until the source ends, ``stop`` is set, or KeyboardInterrupt."""
    stop = stop or threading.Event()

    def pump(node: Node, source: GyroSource, log: logging.Logger) -> GyroPump:
        rates = node.offer(
            "rates",
            kind="gyro",
            retention=Retention(max_count=None, max_age_ns=int(config.retention_s * 1e9)),
        )
        log.info(
            "gyro: %s -> %s/rates (batches of %d)", source.description, config.name, config.batch
        )
        return GyroPump(node, rates, source, config, stop, log)

    return run_source(
        config.name, network, stop, lambda: open_gyro_source(config.source, stop), pump
    )


class GyroPump:
    """Puts each batch when its time comes: a deadline on the node's executor per batch
    (``Node.at``), no thread or sleep of its own. When the source ends the buffer keeps
    answering queries until stopped, or the service exits (``--exit-when-done``)."""

    def __init__(
        self,
        node: Node,
        rates: Producer,
        source: GyroSource,
        config: GyroConfig,
        stop: threading.Event,
        log: logging.Logger,
    ) -> None:
        self._node = node
        self._rates = rates
        self._source = source
        self._config = config
        self._stop = stop
        self._log = log
        self._timeline = Timeline(start_at_ns(config.source.start_at_ns))
        # Where on the shared timeline this gyro begins (as the camera's ``_joined_rel``): a
        # gyro restarted by ``launch``, or one slow to start, joins there. Samples due before
        # were never its to make: skipped, not counted late (a restart counted every sample
        # since the launch, 39,497 after 40 s).
        self._joined_rel = self._timeline.late_ns(0)
        self._batches = iter(source.batches(config.batch, stop))
        self._pending: tuple[list[int], npt.NDArray[np.float64]] | None = None
        self.stored = self.dropped = 0

    def close(self) -> None:
        """Nothing to stop: the gyro makes its samples on the executor."""

    def summary(self) -> str:
        return f"gyro: {self.stored} samples stored, {self.dropped} samples dropped"

    def on_time(self, now: int) -> None:
        """Put every batch that is due; then a deadline for the next one."""
        if self._pending is not None:
            rel, w = self._pending
            self._pending = None
            self._put(rel, w)
        for t_rel, w in self._batches:
            rel = [self._source.scale(int(t)) for t in t_rel]
            if rel[-1] < self._joined_rel:
                continue
            late = self._timeline.late_ns(rel[-1])
            # A sensor cannot deliver the past: a restarted or stalled gyro resumes now.
            if late > _STALE_NS:
                self._rates.count_skip("late", len(rel))
                continue
            if late < 0:  # not yet: its time is a deadline on the executor
                self._pending = (rel, w)
                self._node.at(now - late, self.on_time)
                return
            self._put(rel, w)
        if self._config.source.exit_when_done:
            self._stop.set()

    def _put(self, rel: list[int], w: npt.NDArray[np.float64]) -> None:
        t_wall = np.asarray(self._timeline.stamps_ns(rel), np.int64)
        samples = sample_elements(t_wall, w, period_ns=self._source.scale(self._source.period_ns))
        stored, dropped = put_samples(
            self._rates,
            samples,
            batch=self._config.batch,
            wait_s=self._config.wait_ms / 1e3,
            rejected=lambda exc: self._log.warning("gyro batch not stored: %s", exc),
        )
        self.stored += stored
        self.dropped += dropped


def sample_elements(
    t_ns: np.ndarray, rates_rad_s: np.ndarray, *, period_ns: int
) -> list[tuple[int, bytes, bytes]]:
    """``(timestamp_ns, payload, metadata)`` per sample: a one-sample ``gyro`` element."""
    elements = []
    for i in range(len(t_ns)):
        one = GyroSamples(t_ns[i : i + 1], rates_rad_s[i : i + 1], period_ns=period_ns)
        elements.append((int(t_ns[i]), one.to_bytes(), gyro_metadata(one)))
    return elements


def put_samples(
    rates: Producer,
    samples: list[tuple[int, bytes, bytes]],
    *,
    batch: int,
    wait_s: float,
    rejected: Callable[[FramegateError], None],
) -> tuple[int, int]:
    """Put ``samples`` in batches of at most ``batch`` that every flow-controlled queue can
    hold (a larger one could never fit); (stored, dropped): a batch still refused after
    ``wait_s`` is dropped whole, one the producer rejects goes to ``rejected``."""
    queues = [s.queue_size for s in rates.subscriptions() if s.mode is SubscriptionMode.FLOW]
    size = max(1, min([batch, *queues]))
    stored = dropped = 0
    for i in range(0, len(samples), size):
        chunk = samples[i : i + size]
        try:
            rates.put_many(chunk, wait_s=wait_s)
            stored += len(chunk)
        except FlowControlRefused:
            dropped += len(chunk)
        except ClosedError:
            break  # a stop came: the rest has nowhere to go
        except FramegateError as exc:
            rejected(exc)
    return stored, dropped


SERVICE: Service[GyroConfig] = source_service("gyro", GyroConfig, run, device=False)
