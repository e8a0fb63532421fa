"""One launcher per deploy file, host and rendezvous: a second ``launch`` refuses at once.

Without it a second launcher of a running deploy file would see every service name taken
("already offered by pid ...") and restart its services for ever with back-off, starving
the first launcher's camera. The lock is an ``flock`` on a file in the user's runtime
directory, keyed by the deploy file's absolute path, the host and where its services meet
(the rendezvous port, or the endpoints, Zenoh config and namespace): the same file launched
against another rendezvous is another set of services and may run beside it. The kernel
drops the lock when its holder dies however it dies, so a stale file of a dead launcher is
simply taken over. The file holds the holder's pid, for the refusal message.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import tempfile
from pathlib import Path
from types import TracebackType

from middleware import ConfigError, NetworkConfig

RUNTIME_DIR_ENV = "FRAMEGATE_RUNTIME_DIR"


def runtime_dir() -> Path:
    """``$FRAMEGATE_RUNTIME_DIR``, else ``$XDG_RUNTIME_DIR/framegate``, else a per-user
    directory under the system's temporary directory."""
    if explicit := os.environ.get(RUNTIME_DIR_ENV):
        return Path(explicit)
    if xdg := os.environ.get("XDG_RUNTIME_DIR"):
        return Path(xdg) / "framegate"
    return Path(tempfile.gettempdir()) / f"framegate-{os.getuid()}"


def meeting_point(network: NetworkConfig | None) -> str:
    """Where a launch's services meet, as the lock's key sees it ('' for the default)."""
    if network is None:
        network = NetworkConfig()
    if network.uses_local_default:
        where = f"rendezvous tcp/127.0.0.1:{network.local_port}"
    else:
        parts = [*network.connect, *network.listen, str(network.config_file or "")]
        where = " ".join(sorted(parts))
    return f"{where} namespace {network.namespace}"


def lock_path(
    deploy_file: str | Path, host: str | None, network: NetworkConfig | None = None
) -> Path:
    key = f"{Path(deploy_file).resolve()}\0{host or ''}\0{meeting_point(network)}"
    digest = hashlib.sha256(key.encode()).hexdigest()[:20]
    return runtime_dir() / f"launch-{digest}.lock"


class LaunchLock:
    """Held while a launcher runs ``deploy_file`` for ``host`` on ``network``; ConfigError
    if another live launcher holds it (naming its pid)."""

    def __init__(
        self,
        deploy_file: str | Path,
        host: str | None = None,
        network: NetworkConfig | None = None,
    ) -> None:
        self.deploy_file = str(deploy_file)
        self.host = host
        self.network = network
        self.path = lock_path(deploy_file, host, network)
        self._fd: int | None = None

    def acquire(self) -> None:
        self.path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "?"
            os.close(fd)
            on = f" (host {self.host}, {meeting_point(self.network)})" if self.host else ""
            on = on or f" ({meeting_point(self.network)})"
            raise ConfigError(
                f"{self.deploy_file}{on} is already launched by pid {holder}; stop that "
                f"launcher first (kill {holder}), or give this one another deploy file"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd

    def release(self) -> None:
        if self._fd is None:
            return
        with contextlib.suppress(OSError):
            os.ftruncate(self._fd, 0)
        os.close(self._fd)  # closing drops the flock
        self._fd = None

    def __enter__(self) -> LaunchLock:
        self.acquire()
        return self

    def __exit__(
        self,
        _type: type[BaseException] | None,
        _exc: BaseException | None,
        _tb: TracebackType | None,
    ) -> None:
        self.release()
