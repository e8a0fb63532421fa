"""Which ROS 2 stamp the bridge takes, pure: one gate per input stream.

A stamp is checked before the element is put and *remembered only once the element was
accepted* (stored, or refused by flow control, which only happens to an element whose stamp
the producer found valid). So one message stamped an hour ahead (or ``sec = 2**31 - 1``)
is a counted ``future-stamp`` and every later good message still passes; had it been
remembered, every good one after it would be ``out-of-order`` until that hour had passed.
The bound ahead is the bridge's ``--max-ahead-ms`` (1 s), which its buffers enforce too: a
message accepted 9 s ahead would hold back every later one for 9 s, at the buffer as here.

Reasons (counted skips): ``bad-stamp`` (zero, or fields out of range: see
``_cdr.stamp_ns``), ``future-stamp`` (beyond ``--max-ahead-ms`` of the bridge's clock,
the same bound its producers enforce), ``duplicate-stamp`` and ``out-of-order``
(not newer than the last accepted one).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Refusal:
    """Why a stamp is not taken: the skip reason and a one-line detail."""

    reason: str
    detail: str


class StampGate:
    """The time order of one input stream (one caller at a time)."""

    def __init__(self, horizon_ns: int, what: str) -> None:
        self._horizon_ns = horizon_ns
        self._what = what
        self.last_ns = 0

    def check(self, stamp_ns: int, now_ns: int) -> Refusal | None:
        """None when ``stamp_ns`` may be put now; nothing is remembered here."""
        if stamp_ns <= 0:
            return Refusal("bad-stamp", f"{self._what} header.stamp {stamp_ns} ns")
        if stamp_ns > now_ns + self._horizon_ns:
            return Refusal(
                "future-stamp",
                f"{self._what} stamp {stamp_ns} ns is {(stamp_ns - now_ns) / 1e9:.1f} s ahead "
                f"of this host's clock (at most {self._horizon_ns / 1e9:g} s is taken)",
            )
        if stamp_ns <= self.last_ns:
            reason = "duplicate-stamp" if stamp_ns == self.last_ns else "out-of-order"
            return Refusal(reason, f"{self._what} stamp {stamp_ns} ns after {self.last_ns} ns")
        return None

    def accept(self, stamp_ns: int) -> None:
        """Remember ``stamp_ns``: its element was accepted."""
        self.last_ns = max(self.last_ns, stamp_ns)
