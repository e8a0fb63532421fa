"""Files the CLI writes are created exclusively and never through a planted symlink."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from middleware import ConfigError, Node
from services.lib.files import create_file, open_directory
from tests.conftest import run_framegate
from tests.services.cli.conftest import MS, Cli, put_frame

SECOND = 1_000_000_000


def test_create_file_refuses_a_planted_symlink_and_leaves_its_target_alone(tmp_path: Path) -> None:
    victim = tmp_path / "victim"
    victim.write_bytes(b"precious")
    (tmp_path / "out.bin").symlink_to(victim)
    for overwrite in (False, True):
        with pytest.raises(ConfigError, match="symbolic link"):
            create_file(tmp_path / "out.bin", overwrite=overwrite)
    assert victim.read_bytes() == b"precious"


def test_create_file_refuses_a_dangling_symlink(tmp_path: Path) -> None:
    (tmp_path / "out.bin").symlink_to(tmp_path / "not-yet")
    with pytest.raises(ConfigError, match="symbolic link"):
        create_file(tmp_path / "out.bin")
    assert not (tmp_path / "not-yet").exists()


def test_create_file_refuses_an_existing_file_unless_told_to_overwrite(tmp_path: Path) -> None:
    path = tmp_path / "out.bin"
    path.write_bytes(b"old")
    with pytest.raises(ConfigError, match="exists; choose another name or pass --force"):
        create_file(path)
    assert path.read_bytes() == b"old"
    with create_file(path, overwrite=True) as out:
        out.write(b"new")
    assert path.read_bytes() == b"new"


def test_a_directory_is_never_replaced_and_is_named_as_one(tmp_path: Path) -> None:
    (tmp_path / "out.bin").mkdir()
    # It said "exists; ... pass --force", and then with --force "not a regular file".
    for overwrite in (False, True):
        with pytest.raises(ConfigError, match=r"out\.bin is a directory; give a file path"):
            create_file(tmp_path / "out.bin", overwrite=overwrite)
    assert (tmp_path / "out.bin").is_dir()


@pytest.mark.parametrize("overwrite", [(), ("--overwrite",)])
def test_record_into_a_directory_says_to_give_a_file_path(
    tmp_path: Path, overwrite: tuple[str, ...]
) -> None:
    result = run_framegate("record", "camera/images", "-o", str(tmp_path), *overwrite)
    assert result.returncode == 1, result
    assert result.stderr == (
        f"error: {tmp_path} is a directory; give a file path, e.g. -o {tmp_path / 'run.mcap'}\n"
    )


def test_open_directory_refuses_a_symlinked_directory(tmp_path: Path) -> None:
    (tmp_path / "real").mkdir()
    (tmp_path / "saved").symlink_to(tmp_path / "real")
    with pytest.raises(ConfigError, match="symbolic link"):
        open_directory(tmp_path / "saved")


def test_open_directory_creates_missing_parents(tmp_path: Path) -> None:
    fd = open_directory(tmp_path / "a" / "b")
    try:
        with create_file("x.xml", dir_fd=fd) as out:
            out.write(b"<x/>")
    finally:
        os.close(fd)
    assert (tmp_path / "a" / "b" / "x.xml").read_bytes() == b"<x/>"


@pytest.mark.integration
def test_query_save_and_record_refuse_planted_symlinks(
    service: Node, cli: Cli, tmp_path: Path
) -> None:
    images = service.offer("images", kind="frame")
    base = (time.time_ns() // SECOND - 60) * SECOND
    put_frame(images, base, 1)
    put_frame(images, base + 100 * MS, 2)
    victim = tmp_path / "victim"
    victim.write_bytes(b"precious")
    saved = tmp_path / "saved"
    saved.mkdir()
    (saved / f"{base + 100 * MS}.xml").symlink_to(victim)  # the attacker's link
    (tmp_path / "run.mcap").symlink_to(victim)
    query, record = cli.run_many(
        [
            ("query", "cam/images", "--last", "2", "--save", str(saved), "--force"),
            ("record", "cam/images", "-o", str(tmp_path / "run.mcap"), "--count", "1",
             "--overwrite"),
        ]
    )  # fmt: skip
    for result in (query, record):
        assert result.returncode == 1, result.describe()
        assert "symbolic link" in result.stderr and "Traceback" not in result.stderr
        assert len(result.stderr.strip().splitlines()) == 1, result.describe()
    assert victim.read_bytes() == b"precious"


def test_query_prints_one_line_for_an_out_of_range_time(cli: Cli) -> None:
    result = cli.run("query", "cam/images", "--from", "now(-99999999999999999999s)")
    assert result.returncode == 1, result.describe()
    assert result.stderr.startswith("error: bad time") and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
