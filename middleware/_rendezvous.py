"""The loopback rendezvous's memory: which framegate processes on this host listen where.

The local default meets at ``tcp/127.0.0.1:<local_port>``, held by whichever process came
first. If that one is frozen (SIGSTOP, a debugger) its port still accepts connections but
never answers, so a newcomer that knew only the port would see nobody. So every process of
the rendezvous also leaves its own loopback endpoints in a per-user directory
(``$XDG_RUNTIME_DIR/framegate-<port>/<pid>-<n>``, one file per node, else
``/tmp/framegate-<uid>-<port>/``), and a
newcomer connects to the port *and* to the processes listed there that are still alive:
any live one lets it in, and Zenoh's gossip does the rest. Files of dead processes are
removed by whoever finds them; only loopback endpoints are ever written.
"""

from __future__ import annotations

import contextlib
import itertools
import os
from pathlib import Path

# Connect to at most this many listed peers (the most recent), besides the port itself.
MAX_PEERS = 16
# Each node of this process announces in a file of its own: ``<pid>-<n>``.
_numbers = itertools.count(1)


def directory(local_port: int) -> Path:
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    if runtime and Path(runtime).is_dir():
        return Path(runtime) / f"framegate-{local_port}"
    return Path(f"/tmp/framegate-{os.getuid()}-{local_port}")


def _pid(name: str) -> int | None:
    pid, _, number = name.partition("-")
    return int(pid) if pid.isdigit() and number.isdigit() else None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _live_entries(local_port: int) -> list[tuple[float, list[str]]]:
    """(mtime, loopback endpoints) of each node of the other live processes of the rendezvous,
    newest first."""
    folder = directory(local_port)
    found: list[tuple[float, list[str]]] = []
    with contextlib.suppress(OSError):
        for entry in folder.iterdir():
            pid = _pid(entry.name)
            if pid is None or pid == os.getpid():
                continue
            if not _alive(pid):
                with contextlib.suppress(OSError):
                    entry.unlink()
                continue
            with contextlib.suppress(OSError, UnicodeDecodeError):
                endpoints = [
                    e
                    for e in entry.read_text().split()
                    if e.startswith("tcp/127.0.0.1:") and e != f"tcp/127.0.0.1:{local_port}"
                ]
                found.append((entry.stat().st_mtime, endpoints))
    found.sort(reverse=True)
    return found


def known_peers(local_port: int) -> list[str]:
    """Loopback endpoints of live framegate processes of this rendezvous, newest first."""
    return [e for _, endpoints in _live_entries(local_port)[:MAX_PEERS] for e in endpoints]


def live_nodes(local_port: int) -> int:
    """How many nodes of other live processes of this rendezvous left their endpoints."""
    return len(_live_entries(local_port))


def announce(local_port: int, endpoints: list[str]) -> Path | None:
    """Leave one node's loopback endpoints for newcomers; the file (None if none).

    ``endpoints`` must be that node's own: a process may hold nodes of several rendezvous
    (a test, a tool), and listing another's endpoints here would join them together.
    """
    mine = [e for e in endpoints if e.startswith("tcp/127.0.0.1:")]
    if not mine:
        return None
    folder = directory(local_port)
    name = f"{os.getpid()}-{next(_numbers)}"
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        path = folder / name
        tmp = folder / f".{name}.tmp"
        tmp.write_text("\n".join(mine) + "\n")
        tmp.replace(path)
    except OSError:
        return None  # a read-only /tmp only costs the fallback
    return path


def withdraw(path: Path | None) -> None:
    if path is not None:
        with contextlib.suppress(OSError):
            path.unlink()
            path.parent.rmdir()  # only if this was the last one
