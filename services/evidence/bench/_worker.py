"""A benchmark worker process: ``python -m services.evidence.bench._worker ROLE PARAMS``.

The process runs one role of ``_raw`` (the baseline) or ``_fg`` (framegate). Every role owns
its session through ``with``, so the session is always closed (an open Zenoh session can
keep a process alive); SIGTERM ends the role through KeyboardInterrupt for the same reason.
"""

from __future__ import annotations

import json
import signal
import sys
from collections.abc import Callable
from types import FrameType
from typing import Any

from ._fg import ROLES as FG_ROLES
from ._floods import ROLES as FLOOD_ROLES
from ._raw import ROLES as RAW_ROLES
from ._ros2 import ROLES as ROS2_ROLES
from ._serve import profiled

ROLES: dict[str, Callable[[dict[str, Any]], None]] = {
    **RAW_ROLES,
    **FG_ROLES,
    **ROS2_ROLES,
    **FLOOD_ROLES,
}


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print("usage: python -m services.evidence.bench._worker ROLE PARAMS_JSON", file=sys.stderr)
        return 2

    def on_sigterm(_signum: int, _frame: FrameType | None) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_sigterm)
    role, params = argv[0], json.loads(argv[1])
    if role not in ROLES:
        print(f"unknown role {role!r}; known roles: {', '.join(sorted(ROLES))}", file=sys.stderr)
        return 2
    try:
        with profiled(role):
            ROLES[role](params)
    except KeyboardInterrupt:
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
