"""When a frame was exposed, on the camera clock."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from middleware import field_text, validate_metadata

from ._errors import QualityInputError


@dataclass(frozen=True, slots=True)
class Exposure:
    """Exposure interval of one frame on the camera clock.

    With a rolling shutter ``start_ns`` is when row 0 starts; row r starts
    ``r * line_readout_ns`` later and every row is exposed for ``duration_ns``.
    """

    start_ns: int
    duration_ns: int

    def __post_init__(self) -> None:
        if self.duration_ns < 0:
            raise QualityInputError(f"exposure duration_ns must be >= 0, got {self.duration_ns}")

    @property
    def end_ns(self) -> int:
        """End of row 0's exposure."""
        return self.start_ns + self.duration_ns

    @classmethod
    def from_metadata(cls, root: Any) -> Exposure:
        """Read ``exposure_start_ns`` and ``exposure_ns`` from a validated ``frame`` root."""
        start = field_text(root, "exposure_start_ns")
        duration = field_text(root, "exposure_ns")
        if start is None or duration is None:
            raise QualityInputError("frame metadata lacks <exposure_start_ns> or <exposure_ns>")
        return cls(int(start), int(duration))

    @classmethod
    def from_xml(cls, data: bytes | str) -> Exposure:
        """Parse and validate a ``frame`` metadata document and read its exposure."""
        return cls.from_metadata(validate_metadata(data, "frame"))
