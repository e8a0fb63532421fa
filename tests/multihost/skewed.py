"""A service whose wall clock runs ``--skew-ms`` ahead (test helper for clock-offset checks).

    ip netns exec NS python -m tests.multihost.skewed --skew-ms 40 --name skewed \
        --connect tcp/127.0.0.1:7447

Namespaces share the kernel's clock and name, so a host with a wrong clock is played by one
process whose ``time.time_ns`` is shifted and whose host name is its own: everything
framegate stamps in it (``@info``'s ``clock_ns``, element keys) is off by the skew. Prints
``ready`` once it is offering. The clock is shifted before ``middleware`` is imported, so
that framegate's process clock starts shifted (a host whose clock is simply wrong), rather
than seeing the shift as a step of the system clock.
"""

from __future__ import annotations

import argparse
import signal
import socket
import threading
import time
from types import FrameType


def main(argv: list[str] | None = None) -> int:
    skew = argparse.ArgumentParser(add_help=False)
    skew.add_argument("--skew-ms", type=float, required=True, help="how far ahead the clock is")
    skew_ns = int(skew.parse_known_args(argv)[0].skew_ms * 1e6)
    real_time_ns = time.time_ns
    time.time_ns = lambda: real_time_ns() + skew_ns  # the whole process sees the wrong clock

    from middleware import Node, add_network_arguments, network_from_args

    parser = argparse.ArgumentParser(prog="skewed", parents=[skew])
    add_network_arguments(parser)
    parser.add_argument("--name", default="skewed", help="service name")
    args = parser.parse_args(argv)
    # A separate host has a name of its own (`ls` flags offsets between hosts only).
    socket.gethostname = lambda: "skewed-host"

    stop = threading.Event()

    def on_term(_signum: int, _frame: FrameType | None) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, on_term)
    with Node(args.name, network_from_args(args)) as node:
        node.offer("ticks")
        print("ready", flush=True)
        stop.wait()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
