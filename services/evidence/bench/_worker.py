"""A benchmark worker process: ``python -m services.evidence.bench._worker ROLE PARAMS``.

The process runs one role of ``_raw`` (the baseline) or ``_fg`` (framegate). Every role owns
its session through ``with``, so the session is always closed (an open Zenoh session can
keep a process alive); SIGTERM ends the role through KeyboardInterrupt for the same reason.
"""

from __future__ import annotations

import json
import signal
import sys
from collections.abc import Callable, Iterator
from importlib import import_module
from types import FrameType
from typing import Any

from ._serve import profiled

# The modules whose ``ROLES`` a worker runs, the lightest first: a worker imports only as
# far as its role is found, so the raw baseline's processes import Zenoh and not framegate
# (a quick run starts a hundred-odd workers; importing every role module cost each ~0.5 s
# of CPU).
ROLE_MODULES = ("._raw", "._floods", "._fg", "._ros2")

Role = Callable[[dict[str, Any]], None]


def _roles() -> Iterator[dict[str, Role]]:
    for name in ROLE_MODULES:
        yield import_module(name, __package__).ROLES


def find_role(role: str) -> Role | None:
    """The function of ``role``, importing no role module past the one that defines it."""
    return next((roles[role] for roles in _roles() if role in roles), None)


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print("usage: python -m services.evidence.bench._worker ROLE PARAMS_JSON", file=sys.stderr)
        return 2

    def on_sigterm(_signum: int, _frame: FrameType | None) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_sigterm)
    role, params = argv[0], json.loads(argv[1])
    function = find_role(role)
    if function is None:
        known = sorted(name for roles in _roles() for name in roles)
        print(f"unknown role {role!r}; known roles: {', '.join(known)}", file=sys.stderr)
        return 2
    try:
        with profiled(role):
            function(params)
    except KeyboardInterrupt:
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
