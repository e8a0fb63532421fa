"""Gyro samples as they arrive on the wire, and the batches the blur estimate integrates."""

from __future__ import annotations

import itertools
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from middleware import SchemaError

from ._errors import QualityInputError

GYRO_DTYPE = np.dtype([("t", "<i8"), ("w", "<f8", (3,))])
"""One wire record: int64 timestamp_ns, then x, y, z in rad/s as float64, little-endian."""


@dataclass(frozen=True, slots=True, eq=False)
class GyroSamples:
    """Angular rates of the rigid camera/gyro body, in the gyro frame, on the gyro clock.

    ``t_ns`` (N,) strictly increasing; ``rates_rad_s`` (N, 3), right-hand rule.
    ``period_ns`` is the nominal sample period; 0 derives it as the median spacing.
    The arrays are copied and made read-only.
    """

    t_ns: npt.NDArray[np.int64]
    rates_rad_s: npt.NDArray[np.float64]
    period_ns: int = field(default=0)
    # Indices i where t_ns[i + 1] - t_ns[i] exceeds two nominal periods, found once here so
    # the per-frame coverage check usually costs nothing.
    _wide_steps: npt.NDArray[np.intp] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        t_ns = np.array(self.t_ns, dtype=np.int64)
        rates = np.array(self.rates_rad_s, dtype=np.float64)
        if t_ns.ndim != 1:
            raise QualityInputError(f"t_ns must be one-dimensional, got shape {t_ns.shape}")
        if rates.shape != (t_ns.size, 3):
            raise QualityInputError(
                f"rates_rad_s must have shape ({t_ns.size}, 3) to match t_ns, got {rates.shape}"
            )
        if t_ns.size > 1:
            steps = t_ns[1:] - t_ns[:-1]
            if not bool(np.all(steps > 0)):
                bad = int(np.argmax(steps <= 0)) + 1
                raise QualityInputError(
                    f"gyro timestamps must increase strictly; sample {bad} at "
                    f"{int(t_ns[bad])} ns follows {int(t_ns[bad - 1])} ns"
                )
        if not bool(np.all(np.isfinite(rates))):
            raise QualityInputError("gyro rates contain NaN or infinity; drop those samples first")
        period_ns = int(self.period_ns)
        if period_ns < 0:
            raise QualityInputError(f"period_ns must be >= 0 (0 = derive), got {period_ns}")
        steps = t_ns[1:] - t_ns[:-1]
        if period_ns == 0 and t_ns.size > 1:
            period_ns = int(np.median(steps))
        wide = np.flatnonzero(steps > 2 * period_ns)
        t_ns.setflags(write=False)
        rates.setflags(write=False)
        object.__setattr__(self, "t_ns", t_ns)
        object.__setattr__(self, "rates_rad_s", rates)
        object.__setattr__(self, "period_ns", period_ns)
        object.__setattr__(self, "_wide_steps", wide)

    @property
    def wide_steps(self) -> npt.NDArray[np.intp]:
        """Indices i where ``t_ns[i + 1] - t_ns[i]`` exceeds two nominal periods."""
        return self._wide_steps

    def __len__(self) -> int:
        return int(self.t_ns.size)

    @property
    def start_ns(self) -> int | None:
        """Time of the first sample, or None when empty."""
        return int(self.t_ns[0]) if self.t_ns.size else None

    @property
    def end_ns(self) -> int | None:
        """Time of the last sample, or None when empty."""
        return int(self.t_ns[-1]) if self.t_ns.size else None

    @classmethod
    def empty(cls) -> GyroSamples:
        """No samples (every exposure is then uncovered)."""
        return cls(np.empty(0, np.int64), np.empty((0, 3), np.float64))

    @classmethod
    def from_bytes(
        cls, payload: bytes | bytearray | memoryview, *, period_ns: int = 0
    ) -> GyroSamples:
        """Decode a ``gyro`` payload: 32-byte records of ``GYRO_DTYPE``.

        Raises SchemaError when the payload does not match that layout.
        """
        size = memoryview(payload).nbytes
        if size % GYRO_DTYPE.itemsize:
            raise SchemaError(
                f"gyro payload is {size} bytes, not a multiple of the "
                f"{GYRO_DTYPE.itemsize}-byte record (int64 t_ns, 3 x float64 rad/s)"
            )
        records = np.frombuffer(payload, dtype=GYRO_DTYPE)
        try:
            return cls(records["t"], records["w"], period_ns)
        except ValueError as exc:
            raise SchemaError(f"gyro payload is not usable: {exc}") from exc

    def to_bytes(self) -> bytes:
        """Encode as a ``gyro`` payload (the inverse of ``from_bytes``)."""
        records = np.empty(self.t_ns.size, dtype=GYRO_DTYPE)
        records["t"] = self.t_ns
        records["w"] = self.rates_rad_s
        return records.tobytes()

    @classmethod
    def concat(cls, batches: Iterable[GyroSamples]) -> GyroSamples:
        """Join batches into one time-ordered set.

        Batches may arrive out of order or overlap (a re-delivered batch); a timestamp seen
        twice keeps its first occurrence. The nominal period is kept when every batch
        states the same one, else derived again.
        """
        parts = [b for b in batches if len(b)]
        if not parts:
            return cls.empty()
        periods = {b.period_ns for b in parts}
        period_ns = periods.pop() if len(periods) == 1 else 0
        t_ns = np.concatenate([b.t_ns for b in parts])
        rates = np.concatenate([b.rates_rad_s for b in parts])
        in_order = all(a.t_ns[-1] < b.t_ns[0] for a, b in itertools.pairwise(parts))
        if in_order:
            # The usual case, called per frame: the parts are valid already.
            return cls._trusted(t_ns, rates, period_ns)
        unique_t, first = np.unique(t_ns, return_index=True)
        return cls._trusted(unique_t, rates[first], period_ns)

    @classmethod
    def _trusted(
        cls, t_ns: npt.NDArray[np.int64], rates: npt.NDArray[np.float64], period_ns: int
    ) -> GyroSamples:
        """Build from arrays known to be valid (strictly increasing, finite), skipping checks."""
        steps = t_ns[1:] - t_ns[:-1]
        if period_ns == 0 and t_ns.size > 1:
            period_ns = int(np.median(steps))
        t_ns.setflags(write=False)
        rates.setflags(write=False)
        samples = object.__new__(cls)
        object.__setattr__(samples, "t_ns", t_ns)
        object.__setattr__(samples, "rates_rad_s", rates)
        object.__setattr__(samples, "period_ns", period_ns)
        object.__setattr__(samples, "_wide_steps", np.flatnonzero(steps > 2 * period_ns))
        return samples

    def since(self, t_ns: int) -> GyroSamples:
        """Drop samples no exposure from ``t_ns`` on needs (keeps the last one at or before it)."""
        first = max(int(np.searchsorted(self.t_ns, t_ns, side="right")) - 1, 0)
        return GyroSamples._trusted(
            self.t_ns[first:].copy(), self.rates_rad_s[first:].copy(), self.period_ns
        )
