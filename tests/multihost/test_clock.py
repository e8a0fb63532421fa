"""services.lib.clock: NTP-style offsets from @info round trips, with a fake network and clock."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from middleware import ClockSample, ConfigError, NotFoundError, ServiceInfo
from services.lib.clock import (
    CLOCK_WARN_NS,
    ClockEstimate,
    best_sample,
    clock_warning,
    estimate_clocks,
)

MS = 1_000_000


class FakeNetwork:
    """Services on hosts whose clocks are ``offset_ns`` ahead of ours, reached with given
    one-way delays (out, back) per query; ``None`` in the delays means no answer."""

    def __init__(self, hosts: dict[str, tuple[int, list[tuple[int, int] | None]]]) -> None:
        self.now_ns = 1_800_000_000_000_000_000
        self.hosts = hosts
        self.delays: dict[str, Iterator[tuple[int, int] | None]] = {
            name: iter(delays) for name, (_offset, delays) in hosts.items()
        }

    def live_services(self, *, timeout_s: float = 1.0) -> list[str]:
        return sorted(self.hosts)

    def service_info(self, service: str, *, timeout_s: float = 2.0) -> ServiceInfo:
        delay = next(self.delays[service])
        if delay is None:
            raise NotFoundError(f"service {service!r} did not answer")
        out_ns, back_ns = delay
        sent = self.now_ns
        remote = sent + out_ns + self.hosts[service][0]
        self.now_ns = received = sent + out_ns + back_ns
        self.now_ns += 1 * MS  # time passes between queries
        sample = ClockSample.from_times(sent, remote, received)
        return ServiceInfo(
            service, f"host-{service}", 1, remote, (), sample.offset_ns, sample.round_trip_ns
        )


def test_symmetric_round_trip_gives_the_exact_offset() -> None:
    sample = ClockSample.from_times(1_000 * MS, 1_005 * MS + 500_000, 1_001 * MS)
    assert sample == ClockSample(offset_ns=5 * MS, round_trip_ns=1 * MS)


@settings(deadline=None)  # no wall-clock bound per example
@given(
    offset=st.integers(-(10**12), 10**12),
    out=st.integers(0, 10**9),
    back=st.integers(0, 10**9),
)
def test_true_offset_always_lies_within_half_the_round_trip(
    offset: int, out: int, back: int
) -> None:
    sent = 1_700_000_000_000_000_000
    sample = ClockSample.from_times(sent, sent + out + offset, sent + out + back)
    assert abs(sample.offset_ns - offset) <= sample.round_trip_ns // 2 + 1


def test_min_round_trip_sample_wins_over_delayed_ones() -> None:
    # A busy link delays the first and last answers one way only: their offsets are wrong
    # by milliseconds, the quick exchange in between is not.
    net = FakeNetwork(
        {"camera": (3 * MS, [(9 * MS, 1 * MS), (200_000, 300_000), (100_000, 5 * MS)])}
    )
    (estimate,) = estimate_clocks(net, samples=3)
    assert estimate.samples == 3
    assert estimate.round_trip_ns == 500_000
    assert abs(estimate.offset_ns - 3 * MS) <= estimate.error_ns
    first_alone = ClockSample.from_times(0, 9 * MS + 3 * MS, 10 * MS)
    assert abs(first_alone.offset_ns - 3 * MS) == 4 * MS  # what one sample would have said


def test_missing_answers_keep_the_others_and_a_silent_service_is_left_out() -> None:
    net = FakeNetwork(
        {
            "gyro": (-1 * MS, [None, (100_000, 100_000), None]),
            "mute": (0, [None, None, None]),
        }
    )
    estimates = estimate_clocks(net, samples=3)
    assert [e.service for e in estimates] == ["gyro"]
    assert estimates[0].samples == 1
    assert estimates[0].offset_ns == -1 * MS
    assert estimates[0].host == "host-gyro"


def test_named_services_are_asked_without_listing() -> None:
    net = FakeNetwork({"a": (0, [(1, 1)]), "b": (0, [(1, 1)])})
    assert [e.service for e in estimate_clocks(net, ["b"], samples=1)] == ["b"]


class SilentCrowd:
    """``count`` made-up services that never answer (each question waits its whole timeout
    on a fake monotonic clock), and one real service named last."""

    def __init__(self, count: int) -> None:
        self.now_s = 0.0
        self.asked = 0
        self.names = [f"fake{i:04d}" for i in range(count)] + ["real"]

    def live_services(self, *, timeout_s: float = 1.0) -> list[str]:
        return self.names

    def service_info(self, service: str, *, timeout_s: float = 2.0) -> ServiceInfo:
        assert timeout_s > 0
        self.asked += 1
        if service != "real":
            self.now_s += timeout_s
            raise NotFoundError(f"service {service!r} did not answer within {timeout_s} s")
        self.now_s += 0.001
        return ServiceInfo(service, "far", 1, 0, (), 3 * MS, MS)


def test_asking_a_crowd_that_never_answers_ends_within_the_budget() -> None:
    """A peer that names 1,000 services (tokens and wildcard answers) that never answer
    their own questions: the asking ends by its budget, not after 1,000 x 5 timeouts."""
    crowd = SilentCrowd(1000)
    estimate_clocks(crowd, samples=5, timeout_s=2.0, budget_s=4.0, monotonic=lambda: crowd.now_s)
    assert crowd.now_s <= 4.0 and crowd.asked <= 3


def test_every_service_is_asked_once_before_any_is_asked_again() -> None:
    crowd = SilentCrowd(3)
    (estimate,) = estimate_clocks(
        crowd, samples=5, timeout_s=1.0, budget_s=3.5, monotonic=lambda: crowd.now_s
    )
    assert (estimate.service, estimate.samples, estimate.offset_ns) == ("real", 1, 3 * MS)


def test_bad_sample_counts_are_refused() -> None:
    with pytest.raises(ConfigError, match="samples must be >= 1, got 0"):
        estimate_clocks(FakeNetwork({}), samples=0)
    with pytest.raises(ConfigError, match="no clock samples"):
        best_sample([])


def test_warning_names_host_offset_and_remedy_above_the_threshold() -> None:
    fine = ClockEstimate("camera", "robot", CLOCK_WARN_NS, 200_000, 5)
    assert clock_warning(fine) is None
    off = ClockEstimate("camera", "robot", 3 * MS, 200_000, 5)
    text = clock_warning(off)
    assert text is not None
    assert "camera (host robot)" in text
    assert "+3.0 ms (±0.1)" in text
    assert "chrony" in text
    behind = clock_warning(ClockEstimate("gyro", "robot", -5 * MS, 0, 1))
    assert behind is not None and "-5.0 ms" in behind


def test_warning_says_when_the_round_trip_is_too_long_to_tell() -> None:
    text = clock_warning(ClockEstimate("camera", "robot", 0, 10 * MS, 5))
    assert text is not None
    assert "cannot be checked to 2 ms" in text
    assert "10.0 ms" in text
