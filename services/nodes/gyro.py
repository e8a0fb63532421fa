"""The gyro service: short batches of angular-rate samples in gyro/rates.

Batching (default 10 samples = 20 ms at 500 Hz) keeps 500-1000 Hz from meaning 1000
messages per second; batches are small, so they reach subscribers inline with the
notification. Buffering rule: a consumer that may lose nothing waits — when flow control
refuses a batch, the gyro waits up to ``--wait-ms`` for credit (a sensor FIFO would buffer
too), then drops the batch and counts it.
"""

from __future__ import annotations

import argparse
import threading
import time
from dataclasses import dataclass

import numpy as np

from middleware import FlowControlRefused, FramegateError, NetworkConfig, Node, Retention
from services.lib.messages import gyro_metadata
from services.lib.quality import GyroSamples
from services.nodes._contract import Service
from services.nodes._runtime import serve_until_stopped, setup_logging, sleep_until_ns, start_at_ns
from services.nodes.sources import SourceSpec, open_gyro_source

# Batches older than this when their time comes are skipped, not sent.
_STALE_NS = 500_000_000


@dataclass(frozen=True, slots=True)
class GyroConfig:
    """Everything the gyro service can be told."""

    source: SourceSpec
    name: str = "gyro"
    batch: int = 10
    wait_ms: float = 50.0
    retention_s: float = 30.0


def run(config: GyroConfig, network: NetworkConfig, stop: threading.Event | None = None) -> int:
    """Produce batches until the source ends, ``stop`` is set, or KeyboardInterrupt."""
    stop = stop or threading.Event()
    log = setup_logging(config.name)
    source = open_gyro_source(config.source)
    if stop.is_set():  # interrupted while the source was opening
        return 0
    with Node(config.name, network) as node:
        rates = node.offer(
            "rates",
            kind="gyro",
            retention=Retention(max_count=None, max_age_ns=int(config.retention_s * 1e9)),
        )
        t0_wall = start_at_ns(config.source.start_at_ns)
        log.info(
            "gyro: %s -> %s/rates (batches of %d)", source.description, config.name, config.batch
        )
        stored = dropped = 0
        try:
            for t_rel, w in source.batches(config.batch, stop):
                t_wall = t0_wall + np.asarray([source.scale(int(t)) for t in t_rel], np.int64)
                # A sensor cannot deliver the past: a restarted or stalled gyro resumes now.
                if time.time_ns() - int(t_wall[-1]) > _STALE_NS:
                    continue
                if not sleep_until_ns(int(t_wall[-1]), stop):
                    break
                batch = GyroSamples(t_wall, w, period_ns=source.scale(source.period_ns))
                try:
                    rates.put(
                        int(t_wall[-1]),
                        batch.to_bytes(),
                        gyro_metadata(batch),
                        wait_s=config.wait_ms / 1e3,
                    )
                    stored += 1
                except FlowControlRefused:
                    dropped += 1
                except FramegateError as exc:
                    log.warning("gyro batch not stored: %s", exc)
        except KeyboardInterrupt:
            pass
        log.info("gyro: %d batches stored, %d dropped", stored, dropped)
        if not config.source.exit_when_done:
            serve_until_stopped(stop)
    return 0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The gyro's flags (``framegate run gyro --help``)."""
    from services.nodes.sources import add_source_arguments

    parser.add_argument("--name", default="gyro", help="service name (default %(default)s)")
    add_source_arguments(parser, device=False)
    parser.add_argument("--batch", type=int, default=10, help="samples per element")
    parser.add_argument(
        "--wait-ms",
        type=float,
        default=50.0,
        help="how long a refused batch waits for credit before it is dropped",
    )
    parser.add_argument(
        "--retention-s",
        type=float,
        default=30.0,
        help="how many seconds of batches gyro/rates keeps (default %(default)s)",
    )


def config_from_args(args: argparse.Namespace) -> GyroConfig:
    from services.nodes.sources import source_from_args

    return GyroConfig(
        source=source_from_args(args),
        name=args.name,
        batch=args.batch,
        wait_ms=args.wait_ms,
        retention_s=args.retention_s,
    )


class Gyro:
    """The gyro as the registry sees it (the contract: services/nodes/_contract.py)."""

    name = "gyro"
    config_type = GyroConfig
    add_arguments = staticmethod(add_arguments)
    config_from_args = staticmethod(config_from_args)
    run = staticmethod(run)


SERVICE: Service[GyroConfig] = Gyro()
