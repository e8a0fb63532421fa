"""What a subscription says in its log about its registrations, bounded in rate.

Any peer can forge a producer's greeting on a subscription's notify key, as often as it
likes (the default profile): each one reads as the subscription registered again, and one
with a large ``base`` as a lapse. One log line each was one line per forged greeting (422
lines from 500 greetings sent in a second at the mediator). So each kind of news is logged
at once the first time, then at most once per ``NEWS_EVERY_NS``, in a line that adds up
what came meanwhile. The counts themselves (``missed_total``) are exact whatever is logged.
"""

from __future__ import annotations

import logging

# A subscription logs each kind of news at most this often (the first at once).
NEWS_EVERY_NS = 10_000_000_000


class News:
    """The log lines of one subscription's registrations and lapses. Not thread-safe: the
    caller holds the subscription's lock."""

    def __init__(self, name: str, log: logging.Logger) -> None:
        self._name = name
        self._log = log
        self._again = 0  # registrations again not logged yet
        self._lapses = 0  # lapses not logged yet, and the elements they missed
        self._lapsed = 0
        self._again_at: int | None = None  # when each kind was last logged (monotonic ns)
        self._lapsed_at: int | None = None

    def report(self, again: int, lapsed: int, now_ns: int) -> None:
        """``again`` registrations again and ``lapsed`` elements missed in lapses came;
        log what is due."""
        self._again += again
        if lapsed:
            self._lapses += 1
            self._lapsed += lapsed
        if self._again and _due(self._again_at, now_ns):
            self._log.info(
                "subscription to %s registered again (the producer restarted, or this "
                "subscription had lapsed)%s",
                self._name,
                _times(self._again),
            )
            self._again, self._again_at = 0, now_ns
        if self._lapses and _due(self._lapsed_at, now_ns):
            self._log.warning(
                "subscription to %s had lapsed: %d elements stored meanwhile were never "
                "notified (counted in missed)%s",
                self._name,
                self._lapsed,
                _times(self._lapses),
            )
            self._lapses, self._lapsed, self._lapsed_at = 0, 0, now_ns


def _due(last_ns: int | None, now_ns: int) -> bool:
    return last_ns is None or now_ns - last_ns >= NEWS_EVERY_NS


def _times(count: int) -> str:
    """What a line adds up, when more than one event: a forger's greetings, perhaps."""
    if count == 1:
        return ""
    return f" ({count} times since the last such line; a peer may be forging greetings)"
