"""The put rate of ``info``/``ls`` is the true rate whatever the batch size and window cut."""

from __future__ import annotations

from collections import deque

import pytest

from middleware._rate import STALE_NS, put_rate_hz

MS = 1_000_000


def _window(batch: int, period_ns: int, puts: int, size: int = 64) -> list[tuple[int, int]]:
    """The last ``size`` put events of ``puts`` batches of ``batch`` elements."""
    events: deque[tuple[int, int]] = deque(maxlen=size)
    for k in range(puts):
        events.append((k * period_ns, batch))
    return list(events)


@pytest.mark.parametrize("batch", [1, 3, 7, 10, 20, 64, 65, 1000])
def test_a_200_hz_stream_reads_200_hz_whatever_its_batches(batch: int) -> None:
    period_ns = batch * 5 * MS  # 200 elements/s in batches of `batch`
    events = _window(batch, period_ns, puts=50)
    assert put_rate_hz(events, events[-1][0]) == pytest.approx(200.0)


def test_an_imu_in_batches_of_10_is_not_read_as_210_hz() -> None:
    # The oldest batch was put before the span began: counting it overstated the rate.
    events = _window(10, 50 * MS, puts=100)
    assert put_rate_hz(events, events[-1][0]) == pytest.approx(200.0)


def test_uneven_batches_count_their_elements() -> None:
    # 10, 30, 10, 30 ... every 100 ms: 200 elements/s.
    events = [(k * 100 * MS, 10 if k % 2 else 30) for k in range(40)]
    assert put_rate_hz(events, events[-1][0]) == pytest.approx(200.0, rel=0.03)


def test_one_put_or_one_instant_has_no_rate() -> None:
    assert put_rate_hz([(5, 1000)], 5) == 0.0
    assert put_rate_hz([(5, 10), (5, 10)], 5) == 0.0


def test_nothing_put_for_a_while_reads_0() -> None:
    events = _window(1, 10 * MS, puts=64)
    assert put_rate_hz(events, events[-1][0] + STALE_NS) > 0
    assert put_rate_hz(events, events[-1][0] + STALE_NS + 1) == 0.0
    assert put_rate_hz([], 0) == 0.0
