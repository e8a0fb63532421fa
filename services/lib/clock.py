"""Clock offset between this host and each service's host, NTP-style (paper §4.1).

Buffers are keyed by each host's wall clock, so frames and gyro samples from different hosts
only line up if those clocks agree. One sample: we read our clock before (t0) and after (t3)
an ``@info`` query; the service read its clock (t) somewhere in between, so
``offset = t - (t0 + t3) / 2`` with an error of at most ``(t3 - t0) / 2``. Of several
samples the one with the shortest round trip has the tightest bound (NTP's clock filter):
a sample delayed by a busy link or a slow reply is simply outvoted.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
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
) -> list[ClockEstimate]:
    """Ask each live service (or those named) ``samples`` times; keep the min-RTT sample.

    A service that stops answering keeps the samples it gave; one that never answers is
    left out.
    """
    if samples < 1:
        raise ConfigError(f"samples must be >= 1, got {samples}")
    names = list(services) if services is not None else node.live_services(timeout_s=timeout_s)
    out = []
    for name in names:
        taken: list[ClockSample] = []
        host = ""
        for _ in range(samples):
            try:
                info = node.service_info(name, timeout_s=timeout_s)
            except FramegateError:
                continue
            if info.clock_offset_ns is None or info.round_trip_ns is None:
                continue
            host = info.host
            taken.append(ClockSample(info.clock_offset_ns, info.round_trip_ns))
        if taken:
            chosen = best_sample(taken)
            out.append(
                ClockEstimate(name, host, chosen.offset_ns, chosen.round_trip_ns, len(taken))
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
