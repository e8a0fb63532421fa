"""Clock offset between this host and each service's host, NTP-style (paper §4.1).

Buffers are keyed by each host's wall clock, so frames and gyro samples from different hosts
only line up if those clocks agree. One sample: we read our clock before (t0) and after (t3)
an ``@info`` query; the service read its clock (t) somewhere in between, so
``offset = t - (t0 + t3) / 2`` with an error of at most ``(t3 - t0) / 2``. Of several
samples the one with the shortest round trip has the tightest bound (NTP's clock filter):
a sample delayed by a busy link or a slow reply is simply outvoted.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Protocol

from middleware import ClockSample, ConfigError, FramegateError, ServiceInfo

# Warn above this: a fraction of a short exposure (a few ms). A larger offset shifts the gyro
# window of a frame taken on another host by that much, and `now(-2s)` queries with it.
CLOCK_WARN_NS = 2_000_000
DEFAULT_SAMPLES = 5


@dataclass(frozen=True, slots=True)
class ClockEstimate:
    """The best of several samples for one service (and so for its host)."""

    service: str
    host: str
    offset_ns: int
    round_trip_ns: int
    samples: int

    @property
    def error_ns(self) -> int:
        """The true offset lies within ``offset_ns ± error_ns``."""
        return self.round_trip_ns // 2


class InfoSource(Protocol):
    """What the estimator needs of a ``middleware.Node``."""

    def live_services(self, *, timeout_s: float = ...) -> list[str]: ...

    def service_info(self, service: str, *, timeout_s: float = ...) -> ServiceInfo: ...


def best_sample(samples: Iterable[ClockSample]) -> ClockSample:
    """The sample with the shortest round trip; ConfigError if there is none."""
    chosen = min(samples, key=lambda s: s.round_trip_ns, default=None)
    if chosen is None:
        raise ConfigError("no clock samples to choose from")
    return chosen


def estimate_clocks(
    node: InfoSource,
    services: Sequence[str] | None = None,
    *,
    samples: int = DEFAULT_SAMPLES,
    timeout_s: float = 1.0,
    budget_s: float | None = None,
    monotonic: Callable[[], float] = time.monotonic,
) -> list[ClockEstimate]:
    """Ask each live service (or those named) ``samples`` times; keep the min-RTT sample.

    A service that stops answering keeps the samples it gave; one that never answers is
    left out. ``budget_s``: all the asking together ends by then (no question is asked
    after it, none waits past it), round by round, so that every service is asked once
    before any is asked again: the names are any peer's to add (a liveliness token and an
    ``@info`` answer each), and a peer naming 20 services that never answer their own
    questions kept ``framegate ls`` asking for 153 s (20 x 5 timeouts).
    """
    if samples < 1:
        raise ConfigError(f"samples must be >= 1, got {samples}")
    names = list(services) if services is not None else node.live_services(timeout_s=timeout_s)
    deadline = None if budget_s is None else monotonic() + budget_s
    taken: dict[str, list[ClockSample]] = {name: [] for name in names}
    hosts: dict[str, str] = {}
    for _ in range(samples):
        for name in names:
            wait_s = timeout_s if deadline is None else min(timeout_s, deadline - monotonic())
            if wait_s <= 0:
                break
            try:
                info = node.service_info(name, timeout_s=wait_s)
            except FramegateError:
                continue
            if info.clock_offset_ns is None or info.round_trip_ns is None:
                continue
            hosts[name] = info.host
            taken[name].append(ClockSample(info.clock_offset_ns, info.round_trip_ns))
    out = []
    for name in names:
        if taken[name]:
            chosen = best_sample(taken[name])
            out.append(
                ClockEstimate(
                    name, hosts[name], chosen.offset_ns, chosen.round_trip_ns, len(taken[name])
                )
            )
    return out


def clock_warning(estimate: ClockEstimate, threshold_ns: int = CLOCK_WARN_NS) -> str | None:
    """A one-line warning when the offset exceeds ``threshold_ns`` or cannot be bounded by it."""
    where = f"{estimate.service} (host {estimate.host})"
    offset_ms = estimate.offset_ns / 1e6
    error_ms = estimate.error_ns / 1e6
    if abs(estimate.offset_ns) > threshold_ns:
        return (
            f"clock of {where} is {offset_ms:+.1f} ms (±{error_ms:.1f}) off ours, more than "
            f"{threshold_ns / 1e6:g} ms: frames and gyro samples from different hosts will "
            "not line up; synchronise both hosts with chrony or NTP"
        )
    if estimate.error_ns > threshold_ns:
        return (
            f"clock of {where} cannot be checked to {threshold_ns / 1e6:g} ms: the shortest "
            f"round trip was {estimate.round_trip_ns / 1e6:.1f} ms"
        )
    return None
