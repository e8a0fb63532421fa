"""A config written once: the flags and their parsing follow from the fields."""

from __future__ import annotations

import argparse
import enum
from dataclasses import dataclass
from typing import Any

import pytest

from services.lib.argtypes import non_negative_int, positive_int
from services.lib.settings import add_flags, from_args, setting


class Colour(enum.Enum):
    RED = "red"
    BLUE = "blue"


class Level(enum.IntEnum):
    LOW = 1
    VERY_HIGH = 2


@dataclass(frozen=True, slots=True)
class Base:
    name: str = setting("base", "service name")
    queue: int = setting(2, "queue size", parse=positive_int)


@dataclass(frozen=True, slots=True)
class Example(Base):
    name: str = setting("example", "service name")
    loop: bool = setting(False, "play again")
    colour: Colour = setting(Colour.RED, "a colour")
    level: Level = setting(Level.LOW, "a level", group="levels")
    peers: tuple[str, ...] = setting(("here",), "peers", repeat=True, metavar="PEER")
    matrix: tuple[float, ...] | None = setting(None, "four numbers", parse=float, count=4)
    domain: int = setting(0, "a domain", parse=non_negative_int, env="EXAMPLE_DOMAIN")
    period_ms: float = setting(1000.0 / 3.0, "a period", shown="3 Hz")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(exit_on_error=False)
    add_flags(parser, Example)
    return parser


def _config(*argv: str) -> Any:
    return from_args(Example, _parser().parse_args(list(argv)))


def test_no_flags_give_the_fields_defaults() -> None:
    assert _config() == Example()


def test_a_subclass_keeps_the_base_flags_and_may_change_their_defaults() -> None:
    assert _config().name == "example"
    assert _config("--queue", "5").queue == 5


def test_each_kind_of_field_is_parsed_to_its_type() -> None:
    config = _config(
        "--loop",
        "--colour", "blue",
        "--level", "very_high",
        "--peers", "a", "b", "--peers", "c",
        "--matrix", "1", "0", "0", "1",
    )  # fmt: skip
    assert config.loop is True
    assert config.colour is Colour.BLUE
    assert config.level is Level.VERY_HIGH  # a number enum is spelled by its name
    assert config.peers == ("a", "b", "c")  # a tuple, so the config stays frozen all through
    assert config.matrix == (1.0, 0.0, 0.0, 1.0)


@pytest.mark.parametrize(
    "argv",
    [
        ["--queue", "0"],
        ["--level", "1"],
        ["--matrix", "1", "2"],
        ["--domain", "-1"],
    ],
)
def test_bad_values_are_refused_by_the_flag(argv: list[str]) -> None:
    with pytest.raises((argparse.ArgumentError, SystemExit)):
        _config(*argv)


def test_the_environment_outranks_the_default_and_the_flag_outranks_both(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("EXAMPLE_DOMAIN", "7")
    assert _config().domain == 7
    assert _config("--domain", "3").domain == 3
    monkeypatch.setenv("EXAMPLE_DOMAIN", "-2")
    with pytest.raises((argparse.ArgumentError, SystemExit)):
        _config()


def test_help_shows_each_default_and_groups_flags() -> None:
    text = " ".join(_parser().format_help().split())
    assert "queue size (default 2)" in text
    assert "a colour (default red)" in text
    assert "a period (default 3 Hz)" in text
    assert "a domain (default $EXAMPLE_DOMAIN or 0)" in text
    assert "peers (default here)" in text
    assert "levels: --level {low,very_high}" in text
    assert "play again (default" not in text  # a switch has no default to show
