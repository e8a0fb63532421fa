"""What ``put`` checks of an element before it is stored: types, the horizon, and that its
metadata is valid for the buffer's kind and names the element's timestamp."""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import cast

from ._clock import now_ns
from ._errors import DuplicateTimestampError, SchemaError
from ._records import DataObject, data_object
from ._shapes import ShapeChecker
from ._xml import XmlLimits


class ElementCheck:
    """One buffer's element check; ``__call__`` returns the element or raises SchemaError."""

    def __init__(self, name: str, kind: str, xml_limits: XmlLimits, horizon_ns: int) -> None:
        self.name = name
        self.horizon_ns = horizon_ns
        self._horizon_at_ns = 0  # the largest stamp accepted without reading the clock
        # Validates each element's metadata, in full once per document shape.
        self._metadata = ShapeChecker(kind, xml_limits)

    def __call__(self, timestamp_ns: int, payload: bytes, metadata: bytes | str) -> DataObject:
        # The common case (int, bytes, bytes) costs three type checks; the rest is converted.
        if not (type(payload) is bytes and type(metadata) is bytes and type(timestamp_ns) is int):
            _check_types(timestamp_ns, payload, metadata)
            metadata = metadata.encode("utf-8") if isinstance(metadata, str) else bytes(metadata)
            payload = bytes(payload)
        meta: bytes = metadata  # type: ignore[assignment]
        if not 0 <= timestamp_ns < 2**63:
            _check_types(timestamp_ns, payload, meta)
        # The clock is read only when a stamp passes the last bound seen (stamps are near
        # now, so that is about once per horizon).
        if timestamp_ns > self._horizon_at_ns and timestamp_ns > self._horizon_now():
            raise SchemaError(
                f"timestamp {timestamp_ns} is {(timestamp_ns - now_ns()) / 1e9:.1f} s ahead "
                f"of this process's clock; {self.name} refuses elements more than "
                f"{self.horizon_ns / 1e9:g} s ahead (stamp with middleware.now_ns())"
            )
        declared = self._metadata.timestamp_ns(meta)
        if declared != timestamp_ns:
            raise SchemaError(
                f"metadata says timestamp_ns={declared} but the element's key is {timestamp_ns}"
            )
        return data_object(timestamp_ns, payload, meta)

    def many(self, elements: Sequence[tuple[int, bytes, bytes | str]]) -> tuple[DataObject, ...]:
        """``self(*element)`` for each element of a batch, the common case (every element
        plain bytes, stamped within the last horizon read) in two tight loops; otherwise
        each element goes through ``__call__``, which converts it or says what is wrong."""
        # Types and the horizon of the whole batch first, then its metadata in one call.
        horizon_ns = self._horizon_at_ns
        plain = all(
            [
                type(payload) is bytes
                and type(metadata) is bytes
                and type(timestamp_ns) is int
                and 0 <= timestamp_ns <= horizon_ns
                for timestamp_ns, payload, metadata in elements
            ]
        )
        if not plain:  # one element at a time, each converted or refused by ``__call__``
            return tuple([self(*element) for element in elements])
        checked = cast(Sequence[tuple[int, bytes, bytes]], elements)
        declared = self._metadata.timestamps_ns([metadata for _, _, metadata in checked])
        out: list[DataObject] = []
        append = out.append
        for (timestamp_ns, payload, metadata), stamp in zip(checked, declared, strict=True):
            if stamp != timestamp_ns:
                self(timestamp_ns, payload, metadata)  # raises, naming the mismatch
            append(data_object(timestamp_ns, payload, metadata))
        return tuple(out)

    def batch(self, elements: Sequence[tuple[int, bytes, bytes | str]]) -> tuple[DataObject, ...]:
        """``many``, and the batch's timestamps strictly increasing (``put_many``)."""
        checked = self.many(elements)
        stamps = [e.timestamp_ns for e in checked]
        if stamps != sorted(set(stamps)):  # C speed for a batch; the loop only to name it
            for before, after in itertools.pairwise(stamps):
                if after <= before:
                    raise DuplicateTimestampError(
                        f"put_many: timestamp {after} follows {before} "
                        "in the batch; timestamps must strictly increase"
                    )
        return checked

    def _horizon_now(self) -> int:
        self._horizon_at_ns = now_ns() + self.horizon_ns
        return self._horizon_at_ns


def _check_types(timestamp_ns: object, payload: object, metadata: object) -> None:
    """Wrong-typed arguments get a message, not a TypeError from deep inside."""
    if not isinstance(timestamp_ns, int) or isinstance(timestamp_ns, bool):
        raise SchemaError(
            f"timestamp_ns must be an int (ns since the epoch), got {type(timestamp_ns).__name__}"
        )
    if not 0 <= timestamp_ns < 2**63:
        raise SchemaError(f"timestamp_ns {timestamp_ns} is outside 0 .. 2**63-1")
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise SchemaError(f"payload must be bytes, got {type(payload).__name__}")
    if not isinstance(metadata, bytes | bytearray | str):
        raise SchemaError(f"metadata must be XML as bytes or str, got {type(metadata).__name__}")
