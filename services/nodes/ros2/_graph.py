"""The bridge's first look at the ROS 2 side: is a ROS 2 router there, and what is the graph.

Two small machines fed the time and what the session says, with no thread and no wait
inside, so a test drives them by calling them:

- :class:`RouterWatch` warns once when no ROS 2 router answers within ``ROUTER_WAIT_S`` (as
  rmw_zenoh does: its nodes see no other node without one), then says when one does; Zenoh
  keeps retrying meanwhile.
- :class:`GraphSettle`: once connected, the graph is taken as it is, so a publisher announced
  after that started after the bridge, and its first lost samples are counted. Just after
  connecting, a query of the graph may miss tokens the router already holds (seen: its own
  session's publisher): a second look ``SECOND_LOOK_S`` later is joined to the first, so a
  publisher that was there is never taken for a new one. One that starts in between is
  counted from its first sample seen, as one that was there.

:class:`StartWatch` runs both on the node's executor: a deadline every ``LOOK_S`` asks the
session how many routers it has (a local count, no round trip) until one is there; each
look at the graph is a liveliness query whose end Zenoh's thread only hands to the executor
(``Node.at``), so no handler of the node waits for the ROS 2 router's answer.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable
from typing import Protocol

from middleware import Node

from ._link import RosLink
from ._sequence import SequenceWatch

# How long the bridge waits for the ROS 2 router before it says none answers.
ROUTER_WAIT_S = 3.0
# How often the bridge asks its session whether a ROS 2 router is there yet.
LOOK_S = 0.1
# How long after the first look at the ROS graph the bridge looks again.
SECOND_LOOK_S = 0.5


class _Timer(Protocol):
    """What ``Node.every`` and ``Node.at`` return."""

    def cancel(self) -> None: ...


class RouterWatch:
    """Says once that no ROS 2 router answers, and then that one does (see the module)."""

    def __init__(
        self, routers: Callable[[], int], where: str, log: logging.Logger, start_ns: int
    ) -> None:
        self._routers = routers
        self._where = where
        self._log = log
        self._deadline_ns = start_ns + int(ROUTER_WAIT_S * 1e9)
        self.warned = False
        self.connected = False

    def on_time(self, now_ns: int) -> bool:
        """One look (monotonic ``now_ns``); True once a router is there (nothing left to
        say: the caller stops looking)."""
        if self.connected:
            return True
        if self._routers() > 0:
            self.connected = True
            if self.warned:
                self._log.info("ros2: connected to the ROS 2 router at %s", self._where)
            return True
        if not self.warned and now_ns >= self._deadline_ns:
            self.warned = True
            self._log.warning(
                "ros2: no ROS 2 router at %s yet (is rmw_zenohd running? 'ros2 run "
                "rmw_zenoh_cpp rmw_zenohd'); nothing reaches ROS 2 until one answers, still "
                "trying",
                self._where,
            )
        return False


class GraphSettle:
    """Joins two looks at the ROS graph, then tells the sequence watches it is known."""

    def __init__(self, watches: list[SequenceWatch], node_name: str, log: logging.Logger):
        self._watches = watches
        self._node_name = node_name
        self._log = log
        self.tokens: set[str] = set()
        self.looks = 0
        self.settled = False

    def looked(self, tokens: Iterable[str]) -> bool:
        """One look's liveliness tokens; True: look once more (``SECOND_LOOK_S`` later)."""
        if self.settled:
            return False
        self.tokens.update(tokens)
        self.looks += 1
        if self.looks < 2:
            return True
        for token in self.tokens:
            for watch in self._watches:
                watch.announce(token)
        for watch in self._watches:
            watch.settle()
        self.settled = True
        self._log.info(
            "ros2: ROS graph taken by %s (%d entities); the first samples of publishers "
            "starting from now are counted if lost",
            self._node_name,
            len(self.tokens),
        )
        return False


class StartWatch:
    """:class:`RouterWatch` and :class:`GraphSettle` as a timer and deadlines on ``node``'s
    executor (see the module docstring); ``close`` before the link closes."""

    def __init__(
        self,
        node: Node,
        link: RosLink,
        watches: list[SequenceWatch],
        where: str,
        log: logging.Logger,
    ) -> None:
        self._node, self._link = node, link
        self.router = RouterWatch(link.routers, where, log, time.monotonic_ns())
        self.settle = GraphSettle(watches, link.identity.node_name, log)
        self._closed = False
        self._timer: _Timer = node.at(time.monotonic_ns() + int(LOOK_S * 1e9), self._tick)

    def _tick(self, now_ns: int) -> None:
        # One-shot deadlines, each set on the executor by the one before: a tick never needs
        # the handle that the constructor's thread may not have stored yet.
        if self._closed:
            return
        if not self.router.on_time(now_ns):
            self._timer = self._node.at(now_ns + int(LOOK_S * 1e9), self._tick)
            return
        self._look(now_ns)

    def _look(self, _now_ns: int) -> None:
        if not self._closed:
            self._link.ask_graph(self._answered)

    def _answered(self, tokens: list[str]) -> None:
        """(Zenoh's thread, or the executor when Zenoh refused the query) Hand on."""
        self._node.at(time.monotonic_ns(), lambda _now_ns: self._looked(tokens))

    def _looked(self, tokens: list[str]) -> None:
        if self._closed or not self.settle.looked(tokens):
            return
        again_ns = time.monotonic_ns() + int(SECOND_LOOK_S * 1e9)
        self._timer = self._node.at(again_ns, self._look)

    def close(self) -> None:
        """Stop looking (the bridge is stopping; an answer still to come is ignored)."""
        self._closed = True
        self._timer.cancel()
