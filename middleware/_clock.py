"""One clock-offset sample, NTP-style: the formula every offset in framegate comes from."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class ClockSample:
    """One exchange: the remote clock minus ours, and the round trip that bounds its error."""

    offset_ns: int
    round_trip_ns: int

    @classmethod
    def from_times(cls, sent_ns: int, remote_ns: int, received_ns: int) -> ClockSample:
        """``remote - midpoint(sent, received)``: the remote read its clock somewhere in our
        [sent, received] window, so the error is at most half the round trip."""
        return cls(remote_ns - (sent_ns + received_ns) // 2, received_ns - sent_ns)
