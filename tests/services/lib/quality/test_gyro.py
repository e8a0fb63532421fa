"""Gyro batches: the wire format, validation, joining batches."""

from __future__ import annotations

import numpy as np
import pytest

from middleware import SchemaError
from services.lib.quality import GYRO_DTYPE, GyroSamples


def _batch(start_ns: int, count: int, period_ns: int = 2_000_000) -> GyroSamples:
    t_ns = start_ns + period_ns * np.arange(count, dtype=np.int64)
    rates = np.column_stack([t_ns * 1e-9, -t_ns * 1e-9, np.full(count, 0.5)])
    return GyroSamples(t_ns, rates, period_ns)


def test_wire_records_are_32_little_endian_bytes() -> None:
    assert GYRO_DTYPE.itemsize == 32
    batch = GyroSamples(np.array([7]), np.array([[1.0, -2.0, 0.25]]))
    payload = batch.to_bytes()
    assert payload == (
        (7).to_bytes(8, "little") + np.array([1.0, -2.0, 0.25], dtype="<f8").tobytes()
    )


def test_bytes_round_trip() -> None:
    batch = _batch(1_000, 10)
    again = GyroSamples.from_bytes(batch.to_bytes())
    np.testing.assert_array_equal(again.t_ns, batch.t_ns)
    np.testing.assert_array_equal(again.rates_rad_s, batch.rates_rad_s)
    assert again.period_ns == 2_000_000
    assert again.t_ns.dtype == np.int64 and again.rates_rad_s.dtype == np.float64


def test_a_truncated_payload_is_a_schema_error() -> None:
    with pytest.raises(SchemaError, match="33 bytes, not a multiple of the 32-byte record"):
        GyroSamples.from_bytes(bytes(33))


def test_a_payload_with_unordered_times_is_a_schema_error() -> None:
    records = np.zeros(2, dtype=GYRO_DTYPE)
    records["t"] = [5, 5]
    with pytest.raises(SchemaError, match="increase strictly; sample 1 at 5 ns"):
        GyroSamples.from_bytes(records.tobytes())


def test_rates_must_be_n_by_3_and_finite() -> None:
    with pytest.raises(ValueError, match=r"shape \(2, 3\)"):
        GyroSamples(np.array([1, 2]), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="NaN or infinity"):
        GyroSamples(np.array([1, 2]), np.array([[0.0, np.nan, 0.0], [0.0, 0.0, 0.0]]))


def test_arrays_are_copied_and_read_only() -> None:
    t_ns = np.array([1, 2, 3])
    batch = GyroSamples(t_ns, np.zeros((3, 3)))
    t_ns[0] = 99
    assert batch.t_ns[0] == 1
    with pytest.raises(ValueError, match="read-only"):
        batch.t_ns[0] = 5


def test_the_nominal_period_is_the_median_spacing() -> None:
    # Jittered 500 Hz with one dropout: the median ignores both.
    t_ns = np.array([0, 2_000_000, 4_100_000, 6_000_000, 8_000_000, 20_000_000])
    assert GyroSamples(t_ns, np.zeros((6, 3))).period_ns == 2_000_000
    assert GyroSamples(t_ns, np.zeros((6, 3)), period_ns=1_000_000).period_ns == 1_000_000


def test_concat_orders_batches_and_drops_redelivered_samples() -> None:
    a, b, c = _batch(0, 5), _batch(10_000_000, 5), _batch(20_000_000, 5)
    joined = GyroSamples.concat([c, a, b, b])
    np.testing.assert_array_equal(joined.t_ns, np.arange(0, 30_000_000, 2_000_000))
    np.testing.assert_array_equal(joined.rates_rad_s[:, 2], 0.5)
    assert joined.period_ns == 2_000_000
    in_order = GyroSamples.concat([a, b, c])
    np.testing.assert_array_equal(in_order.t_ns, joined.t_ns)


def test_concat_of_nothing_is_empty() -> None:
    empty = GyroSamples.concat([])
    assert len(empty) == 0 and empty.start_ns is None and empty.end_ns is None


def test_since_keeps_the_sample_before_the_cut() -> None:
    batch = _batch(0, 10)
    kept = batch.since(5_000_000)
    assert kept.start_ns == 4_000_000 and kept.end_ns == 18_000_000
    assert len(batch.since(-1)) == 10
