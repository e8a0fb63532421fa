"""The answers to one ``@info/*`` query (``Node.services``), taken within bounds.

Any peer can answer ``@info/*`` with any number of replies under any names, each a valid
description of up to ``MAX_REPLY_BYTES``: a peer answering with 100 descriptions of 2.4 MB
(30,000 subscriptions each) kept ``framegate ls`` decoding for 12-20 s, ~265 MB, and
``launch --status`` printed no status line meanwhile. So per query:

- at most ``MAX_DESCRIPTIONS`` replies, and ``MAX_DESCRIPTION_BYTES`` of them in all, are
  kept (copied) to be decoded; the rest are counted, never copied;
- replies for services that hold no liveliness token (a real service always holds its
  token; a made-up one need not) take at most ``TOKENLESS_DESCRIPTIONS`` and
  ``TOKENLESS_BYTES`` of that, and are decoded after those of token holders: a flood of
  made-up descriptions cannot push a real service out (a peer that declares a token for
  each made-up name as well still can: what is left of the caps is then first come);
- nothing is decoded after the query's deadline (its timeout): what is kept and not yet
  decoded then is counted, not decoded.

- one reply per replying session and name is kept (``replier``): a session answering one
  name again and again takes one place, not the caps, so a single rogue session cannot push
  out the real holder of a name (the one-producer-per-name check, ``_service``, reads its
  name's answers so).

One line per kind of reply left out (``reasons``) says how many, so ``ls`` names them; and
one names the token holders that gave no description by the deadline (a bare token, or a
service whose answer came late: under a churn of thousands of tokens a second, ``ls`` left
out real services with no word).
``ask`` sends the query whose replies an intake takes: every ``@info`` read of framegate that
keeps more than one answer per session goes through here (``service_info`` keeps each
session's first answer only: ``_discovery.Answers``).

Threads: ``offer`` and ``end`` run on Zenoh's threads: a remote peer's reply on the thread
of the link it came on, but the reply of a queryable of the asking session itself on the
*asking* thread, inside ``get``, before the asker holds anything to read from (so a bounded
FIFO channel parks the asker for good once replies outnumber its room, as liveliness
replies did: ``_liveliness``). ``offer`` never blocks: it keeps or counts, at once. ``take``
runs on the asking thread and waits, with the deadline, for what ``offer`` kept. ``_cond``
guards the kept replies and the counts.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Collection
from dataclasses import dataclass
from typing import Protocol

import zenoh

from ._clock import now_ns
from ._decode import MAX_REPLY_BYTES, listing

# Replies of one ``@info/*`` query kept to be decoded at most, and their bytes in all: a
# deployment's descriptions are a few KiB each (one buffer's is at most 512 KiB), so these
# leave room for dozens of services and bound the decoding to seconds on a loaded machine.
MAX_DESCRIPTIONS = 64
MAX_DESCRIPTION_BYTES = 16 << 20
# Of those, for services holding no liveliness token at most (a fresh session that has not
# yet seen a real service's token still lists it).
TOKENLESS_DESCRIPTIONS = 16
TOKENLESS_BYTES = 4 << 20
# Names of left-out replies a reason line lists at most.
_NAMED = 5
# With ``every_live``, once every live name has answered, replies are still taken for as long
# again as that took (at least this long): the query ends there, not at its timeout.
_HEARD_SLACK_S = 0.05


def heard_end(asked: float, heard: float) -> float:
    """When a query of descriptions asked at ``asked`` ends, all it waits for having come at
    ``heard`` (monotonic seconds): as long again after, so that a second answer in the same
    name (a peer's, or the service's own behind a peer's) is still taken beside the first."""
    return heard + max(heard - asked, _HEARD_SLACK_S)


# (session, name) pairs remembered to tell a repeated answer, at most (a flood of distinct
# names would otherwise grow the set): beyond, a repeated answer is held to the caps above
# like any other.
_REMEMBERED = 4 * MAX_DESCRIPTIONS


@dataclass(frozen=True)
class Kept:
    """A kept reply: the service it names, its payload, when it came (ns, local clock), and
    the Zenoh session that sent it ("" when not told)."""

    name: str
    raw: bytes
    arrived_ns: int
    replier: str = ""


class Payload(Protocol):
    """What ``offer`` reads of a reply's payload (``zenoh.ZBytes``)."""

    def __len__(self) -> int: ...

    def to_bytes(self) -> bytes: ...


class _LeftOut:
    """Replies of one kind left out: how many, and the first few names (a peer may send
    millions of replies in one query's time: their names are not all kept)."""

    def __init__(self) -> None:
        self.count = 0
        self.names: list[str] = []

    def add(self, name: str) -> None:
        self.count += 1
        if len(self.names) < _NAMED:
            self.names.append(name)

    def listing(self) -> str:
        shown = listing(self.names, _NAMED)
        rest = self.count - len(self.names)
        return shown + (f" and {rest} more" if rest > 0 else "")


class InfoIntake:
    """The replies of one ``@info/*`` query waiting to be decoded, within the bounds above."""

    def __init__(
        self,
        deadline: float,
        live: Collection[str],
        *,
        monotonic: Callable[[], float] = time.monotonic,
        every_live: bool = False,
    ) -> None:
        self._deadline = deadline
        self._live = frozenset(live)
        self._monotonic = monotonic
        # ``every_live``: the query ends (``_heard_end``) once each name of ``live`` has
        # answered, not at its timeout: any peer can declare a queryable on ``@info/*`` that
        # takes each query and never finalizes it, and ``ls`` and ``info`` waited that long
        # (the held queries of the named-session case, ``_discovery``, but asked of no one
        # session). The slack after lets a second answer in a live name (a peer's, or the
        # service's own behind a peer's) arrive to be listed beside the first.
        self._every_live = every_live and bool(self._live)
        self._asked = monotonic()
        self._heard_end: float | None = None
        self._cond = threading.Condition()
        # [0]: of services holding their token, [1]: of the others (taken after [0])
        self._kept: tuple[deque[Kept], deque[Kept]] = (deque(), deque())
        self._count = [0, 0]
        self._bytes = [0, 0]
        self._ended = False
        self._closed = False
        self._too_large = _LeftOut()
        self._over_cap = _LeftOut()
        self._tokenless = _LeftOut()
        self._late = _LeftOut()
        self._repeated = _LeftOut()
        self._answered: set[tuple[str, str]] = set()  # (replier, name) kept or counted
        self._live_heard: set[str] = set()  # names of ``live`` that replied (bounded by it)

    # -- Zenoh's threads -------------------------------------------------------------------
    def offer(self, name: str, payload: Payload, arrived_ns: int, replier: str = "") -> None:
        """Keep ``name``'s reply (copied) if the bounds allow; else count it. Never blocks.
        ``replier``: the session that sent it; its further replies for ``name`` are counted."""
        size = len(payload)
        with self._cond:
            if self._closed:
                return
            if name in self._live:
                self._live_heard.add(name)
                if self._every_live and self._heard_end is None and self._live_heard == self._live:
                    self._heard_end = heard_end(self._asked, self._monotonic())
                    self._cond.notify()
            if replier:
                if (replier, name) in self._answered:
                    self._repeated.add(name)
                    return
                if len(self._answered) < _REMEMBERED:
                    self._answered.add((replier, name))
            if size > MAX_REPLY_BYTES:
                self._too_large.add(name)
                return
            tokenless = int(name not in self._live)
            count, used = sum(self._count), sum(self._bytes)
            if count >= MAX_DESCRIPTIONS or used + size > MAX_DESCRIPTION_BYTES:
                self._over_cap.add(name)
                return
            if tokenless and (
                self._count[1] >= TOKENLESS_DESCRIPTIONS or self._bytes[1] + size > TOKENLESS_BYTES
            ):
                self._tokenless.add(name)
                return
            self._count[tokenless] += 1
            self._bytes[tokenless] += size
        raw = payload.to_bytes()  # outside the lock: a copy of up to 4 MiB
        with self._cond:
            if not self._closed:
                self._kept[tokenless].append(Kept(name, raw, arrived_ns, replier))
                self._cond.notify()

    def end(self) -> None:
        """The query ended (all answered, or its timeout)."""
        with self._cond:
            self._ended = True
            self._cond.notify()

    # -- the asking thread -----------------------------------------------------------------
    def take(self) -> Kept | None:
        """The next kept reply (name, payload, when it came), token holders' first; None once
        the query has ended (with ``every_live``: every live name answered, and the slack
        after passed) and all are taken, or at the deadline (the rest counted late)."""
        with self._cond:
            while True:
                now = self._monotonic()
                if now >= self._deadline:
                    self._close()
                    return None
                for kept in self._kept:
                    if kept:
                        return kept.popleft()
                ends = self._deadline
                if self._heard_end is not None:
                    ends = min(ends, self._heard_end)
                if self._ended or now >= ends:
                    self._close()
                    return None
                self._cond.wait(ends - now)

    def _close(self) -> None:
        self._closed = True
        for kept in self._kept:
            for left in kept:
                self._late.add(left.name)
            kept.clear()

    def reasons(self) -> list[str]:
        """One line per kind of reply left out, naming a few and saying how many."""
        with self._cond:
            out = []
            if self._too_large.count:
                out.append(
                    f"{self._too_large.count} descriptions of more than {MAX_REPLY_BYTES} bytes "
                    f"each, not read ({self._too_large.listing()})"
                )
            if self._over_cap.count:
                out.append(
                    f"{self._over_cap.count} descriptions beyond the {MAX_DESCRIPTIONS} (and "
                    f"{MAX_DESCRIPTION_BYTES >> 20} MiB) read per query, not read "
                    f"({self._over_cap.listing()})"
                )
            if self._tokenless.count:
                out.append(
                    f"{self._tokenless.count} descriptions of services holding no liveliness "
                    f"token beyond the {TOKENLESS_DESCRIPTIONS} (and {TOKENLESS_BYTES >> 20} MiB) "
                    f"read per query, not read ({self._tokenless.listing()})"
                )
            if self._repeated.count:
                out.append(
                    f"{self._repeated.count} further descriptions of a name from a session "
                    f"that had already answered for it, not read ({self._repeated.listing()})"
                )
            silent = sorted(self._live - self._live_heard)
            if silent:
                out.append(
                    f"{len(silent)} live services (holding their liveliness token) gave no "
                    f"description within the query's timeout ({listing(silent, _NAMED)})"
                )
            if self._late.count:
                out.append(
                    f"{self._late.count} descriptions not decoded by the query's deadline "
                    f"({self._late.listing()})"
                )
            return out


def ask(session: zenoh.Session, keyexpr: str, intake: InfoIntake, *, timeout_s: float) -> None:
    """Send the ``@info`` query ``keyexpr`` whose replies go to ``intake`` (then ``take``
    them). A callback, never a bounded channel: Zenoh delivers the replies of this session's
    own queryables on this thread, inside ``get``, and a full channel parks it for good; a
    channel also holds every reply whole until it is read, as big as a peer makes it.
    Raises what ``get`` raises (``ZError``)."""

    def on_reply(reply: zenoh.Reply) -> None:  # (Zenoh's thread, or this one) never waits
        if reply.ok is not None:
            who = reply.replier_id
            replier = str(who.zid) if who is not None else ""
            name = str(reply.ok.key_expr).rsplit("/", 1)[-1]
            intake.offer(name, reply.ok.payload, now_ns(), replier)

    session.get(
        keyexpr,
        zenoh.handlers.Callback(on_reply, intake.end, indirect=False),
        consolidation=zenoh.ConsolidationMode.NONE,
        timeout=timeout_s,
    )
