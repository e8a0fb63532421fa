"""The put rate of ``info``/``ls`` is the true rate whatever the batch size and window cut."""

from __future__ import annotations

from collections import deque

import pytest

from middleware._rate import STALE_NS, put_rate_hz

MS = 1_000_000


def _window(batch: int, period_ns: int, puts: int, size: int = 64) -> list[int]:
    """The last ``size`` per-element put times of ``puts`` batches of ``batch`` elements."""
    times: deque[int] = deque(maxlen=size)
    for k in range(puts):
        times.extend([k * period_ns] * batch)
    return list(times)


@pytest.mark.parametrize("batch", [1, 3, 7, 10, 20, 64])
def test_a_200_hz_stream_reads_200_hz_whatever_its_batches(batch: int) -> None:
    period_ns = batch * 5 * MS  # 200 elements/s in batches of `batch`
    times = _window(batch, period_ns, puts=50)
    now = times[-1]
    if batch == 64:  # one batch fills the window: no span to measure
        assert put_rate_hz(times, now) == 0.0
        return
    assert put_rate_hz(times, now) == pytest.approx(200.0)


def test_an_imu_in_batches_of_10_is_not_read_as_210_hz() -> None:
    # The window of 64 holds 4 elements of the oldest batch: counting them overstated it.
    times = _window(10, 50 * MS, puts=20)
    assert times.count(times[0]) == 4
    assert put_rate_hz(times, times[-1]) == pytest.approx(200.0)


def test_nothing_put_for_a_while_reads_0() -> None:
    times = _window(1, 10 * MS, puts=64)
    assert put_rate_hz(times, times[-1] + STALE_NS) > 0
    assert put_rate_hz(times, times[-1] + STALE_NS + 1) == 0.0
    assert put_rate_hz([], 0) == 0.0
