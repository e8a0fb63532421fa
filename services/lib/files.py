"""Files the CLI writes: created fresh, never through a symbolic link, never over a file unasked.

``query --save DIR`` and ``record -o FILE`` often write into shared places such as ``/tmp``,
where another local user can plant a symlink (``/tmp/frames/1700.png`` → ``~/.bashrc``) or
a file of their own before we get there. So every file is created with
``O_CREAT | O_EXCL | O_NOFOLLOW``: an existing name, link or not, is refused rather than
followed or truncated. Overwriting (``--force``/``--overwrite``) removes an existing
*regular* file first and then creates exclusively, so a link planted in between is still
refused. A save directory that already exists must be a real directory owned by this user,
and files go in relative to its open descriptor, so it cannot be swapped for a link midway.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import BinaryIO

from middleware import ConfigError, FramegateError

_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
_CLOEXEC = getattr(os, "O_CLOEXEC", 0)
_CREATE_FLAGS = os.O_WRONLY | os.O_CREAT | os.O_EXCL | _NOFOLLOW | _CLOEXEC
_DIRECTORY_FLAGS = os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) | _NOFOLLOW | _CLOEXEC


class OutputError(FramegateError):
    """A file we were asked to write cannot be written (disk full, permissions, encoding)."""


def create_file(
    path: Path | str,
    *,
    overwrite: bool = False,
    dir_fd: int | None = None,
    shown: str | None = None,
    overwrite_flag: str = "--force",
) -> BinaryIO:
    """A new file opened for binary writing; ConfigError if the name exists or is a link.

    With ``overwrite``, an existing regular file is replaced; a link, directory or device
    never is. ``dir_fd`` makes ``path`` relative to an open directory; ``shown`` is the name
    used in messages.
    """
    name = shown if shown is not None else str(path)
    if overwrite:
        _remove_regular_file(path, dir_fd, name)
    try:
        fd = os.open(path, _CREATE_FLAGS, 0o644, dir_fd=dir_fd)
    except FileExistsError:
        if _is_link(path, dir_fd):
            raise ConfigError(
                f"{name} is a symbolic link; refusing to write through it (remove it, "
                "or choose another name)"
            ) from None
        if _is_directory(path, dir_fd):
            raise ConfigError(f"{name} is a directory; give a file path") from None
        raise ConfigError(
            f"{name} exists; choose another name or pass {overwrite_flag} to replace it"
        ) from None
    except OSError as exc:
        raise ConfigError(f"cannot create {name}: {exc.strerror}") from exc
    return os.fdopen(fd, "wb")


def open_directory(path: Path) -> int:
    """An open descriptor of directory ``path``, created if missing (parents too).

    An existing ``path`` must be a directory, not a link, owned by this user: someone else's
    directory in ``/tmp`` is theirs to fill with links. Close the descriptor when done.
    """
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        os.mkdir(path)
    except FileExistsError:
        pass
    except OSError as exc:
        raise ConfigError(f"cannot create directory {path}: {exc.strerror}") from exc
    try:
        fd = os.open(path, _DIRECTORY_FLAGS)
    except OSError as exc:
        if _is_link(path, None):
            raise ConfigError(
                f"{path} is a symbolic link; refusing to write through it "
                "(choose the real directory)"
            ) from exc
        raise ConfigError(f"cannot open directory {path}: {exc.strerror}") from exc
    owner = os.fstat(fd).st_uid
    if hasattr(os, "getuid") and owner != os.getuid():
        os.close(fd)
        raise ConfigError(
            f"{path} belongs to another user (uid {owner}); choose a directory of your own"
        )
    return fd


def _is_link(path: Path | str, dir_fd: int | None) -> bool:
    try:
        return stat.S_ISLNK(os.lstat(path, dir_fd=dir_fd).st_mode)
    except OSError:
        return False


def _is_directory(path: Path | str, dir_fd: int | None) -> bool:
    try:
        return stat.S_ISDIR(os.lstat(path, dir_fd=dir_fd).st_mode)
    except OSError:
        return False


def _remove_regular_file(path: Path | str, dir_fd: int | None, name: str) -> None:
    try:
        mode = os.lstat(path, dir_fd=dir_fd).st_mode
    except FileNotFoundError:
        return
    except OSError as exc:
        raise ConfigError(f"cannot inspect {name}: {exc.strerror}") from exc
    if stat.S_ISLNK(mode):
        raise ConfigError(f"{name} is a symbolic link; refusing to replace it (remove it first)")
    if stat.S_ISDIR(mode):
        raise ConfigError(f"{name} is a directory; give a file path")
    if not stat.S_ISREG(mode):
        raise ConfigError(f"{name} is not a regular file; refusing to replace it")
    try:
        os.unlink(path, dir_fd=dir_fd)
    except OSError as exc:
        raise ConfigError(f"cannot replace {name}: {exc.strerror}") from exc
