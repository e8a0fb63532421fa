"""The put rate of ``info``/``ls`` is the true rate whatever the batch size and window cut."""

from __future__ import annotations

import random

import pytest

from middleware._rate import MERGE_NS, STALE_NS, WINDOW, PutRate

MS = 1_000_000


def _rate(events: list[tuple[int, int]]) -> PutRate:
    """A window fed ``(monotonic ns, elements)`` per put, in order."""
    rate = PutRate()
    for t, n in events:
        rate.add(t, n)
    return rate


def _batches(batch: int, period_ns: int, puts: int) -> list[tuple[int, int]]:
    return [(k * period_ns, batch) for k in range(puts)]


@pytest.mark.parametrize("batch", [1, 3, 7, 10, 20, 64, 65, 1000])
def test_a_200_hz_stream_reads_200_hz_whatever_its_batches(batch: int) -> None:
    period_ns = batch * 5 * MS  # 200 elements/s in batches of `batch`
    events = _batches(batch, period_ns, puts=50)
    assert _rate(events).hz(events[-1][0]) == pytest.approx(200.0)


def test_an_imu_in_batches_of_10_is_not_read_as_210_hz() -> None:
    # The oldest batch was put before the span began: counting it overstated the rate.
    events = _batches(10, 50 * MS, puts=100)
    assert _rate(events).hz(events[-1][0]) == pytest.approx(200.0)


def test_uneven_batches_count_their_elements() -> None:
    # 10, 30, 10, 30 ... every 100 ms: 200 elements/s.
    events = [(k * 100 * MS, 10 if k % 2 else 30) for k in range(40)]
    assert _rate(events).hz(events[-1][0]) == pytest.approx(200.0, rel=0.03)


def test_single_puts_in_bursts_read_their_mean_rate() -> None:
    """500 single puts a second, made in bursts as a busy machine wakes a sleeper (``play``
    puts gyro samples one by one): 64 puts spanned 0.13 s and ``info`` read 270-612 Hz."""
    rng = random.Random(7)
    events, t = [], 0
    for _ in range(100):  # bursts of 5-45 puts 2 us apart, every 10-90 ms: mean 500/s
        n = rng.randrange(5, 46)
        events += [(t + i * 2_000, 1) for i in range(n)]
        t += n * 2 * MS
    rate = _rate(events)
    # The window spans at least WINDOW * MERGE_NS of it: the bursts average out.
    assert rate.hz(events[-1][0]) == pytest.approx(500.0, rel=0.1)
    assert WINDOW * MERGE_NS >= 3_000 * MS


def test_one_put_or_one_instant_has_no_rate() -> None:
    assert _rate([(5, 1000)]).hz(5) == 0.0
    assert _rate([(5, 10), (5, 10)]).hz(5) == 0.0


def test_nothing_put_for_a_while_reads_0() -> None:
    events = _batches(1, 10 * MS, puts=64)
    rate = _rate(events)
    assert rate.hz(events[-1][0] + STALE_NS) > 0
    assert rate.hz(events[-1][0] + STALE_NS + 1) == 0.0
    assert PutRate().hz(0) == 0.0
