"""A service's configuration written once: a frozen dataclass whose fields carry their help,
flag and default, from which the flags, the parsing and the deploy-file keys follow.

    @dataclass(frozen=True, slots=True)
    class GyroConfig:
        name: str = setting("gyro", "service name")
        batch: int = setting(10, "samples per message", parse=positive_int)

    add_flags(parser, GyroConfig)                  # --name, --batch (``framegate run gyro``)
    config = from_args(GyroConfig, parser.parse_args(argv))

A field's flag is ``--`` plus its name with dashes, unless ``flag`` says otherwise; extra
spellings go in ``aliases``. Booleans are switches (``--loop``); enums take their values
(an enum whose values are numbers, its names in lower case); ``parse`` is the argparse type
that checks a value (``services.lib.argtypes``). ``repeat`` makes a list flag (given several
times, or with several values: a deploy file's YAML list), ``count`` one that takes exactly
that many values; either becomes a tuple. ``env`` names an environment variable that
outranks the default (defaults -> deploy file -> environment -> flags); ``shown`` is the
default as help prints it, where the value itself would not read well; ``group`` puts the
flag under a heading in ``--help``; ``unset`` leaves the parsed value None when the flag is
not given, so a command can tell a flag given with its default's value from one left out.
A field without ``setting`` metadata (a nested config, e.g. the camera's source) is the
service's own to fill, as is a value that depends on another flag
(``from_args(..., field=value)``). A deploy file's service args are these flags' names, and
``framegate launch`` checks them with the same parser.
"""

from __future__ import annotations

import argparse
import dataclasses
import enum
import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

_KEY = "framegate.setting"


@dataclass(frozen=True, slots=True)
class Setting:
    """What a config field says about its flag."""

    help: str
    flag: str | None = None
    parse: Callable[[str], Any] | None = None
    aliases: tuple[str, ...] = ()
    choices: tuple[str, ...] | None = None  # for an enum: the values offered (None: all)
    dest: str | None = None  # the parsed args' attribute (default: the field's name)
    metavar: str | None = None
    repeat: bool = False  # a list: the flag may be given several times, each with values
    count: int | None = None  # exactly this many values (a 3x3 matrix: 9)
    env: str | None = None  # an environment variable that outranks the default
    shown: str | None = None  # the default as --help shows it (None: the value)
    group: str | None = None  # the --help heading the flag is listed under
    required: bool = False  # the command cannot run without it (the default is no value)
    # The parsed args hold None when the flag is not given (``from_args`` puts the default
    # in), so a command can tell a flag given with the default's value from one left out.
    unset: bool = False


def setting(
    default: Any,
    help: str,
    *,
    flag: str | None = None,
    parse: Callable[[str], Any] | None = None,
    aliases: tuple[str, ...] = (),
    choices: Iterable[str] | None = None,
    dest: str | None = None,
    metavar: str | None = None,
    repeat: bool = False,
    count: int | None = None,
    env: str | None = None,
    shown: str | None = None,
    group: str | None = None,
    required: bool = False,
    unset: bool = False,
) -> Any:
    """A config field with its default and how it is set from the command line."""
    meta = Setting(
        help,
        flag=flag,
        parse=parse,
        aliases=aliases,
        choices=tuple(choices) if choices is not None else None,
        dest=dest,
        metavar=metavar,
        repeat=repeat,
        count=count,
        env=env,
        shown=shown,
        group=group,
        required=required,
        unset=unset,
    )
    return dataclasses.field(default=default, metadata={_KEY: meta})


def settings(config_type: type) -> list[tuple[dataclasses.Field[Any], Setting]]:
    """The fields of ``config_type`` that are settings, in order."""
    out = []
    for f in dataclasses.fields(config_type):
        meta = f.metadata.get(_KEY)
        if isinstance(meta, Setting):
            out.append((f, meta))
    return out


def flag_of(f: dataclasses.Field[Any], meta: Setting) -> str:
    return meta.flag or "--" + f.name.replace("_", "-")


def add_flags(
    parser: argparse.ArgumentParser,
    config_type: type,
    *,
    skip: Iterable[str] = (),
    choices: dict[str, list[str]] | None = None,
) -> None:
    """One flag per setting of ``config_type``, except the fields named in ``skip``;
    ``choices`` narrows a field's choices for this parser (a gyro has no device)."""
    skipped = set(skip)
    narrowed = choices or {}
    groups: dict[str, argparse._ArgumentGroup] = {}
    for f, meta in settings(config_type):
        if f.name in skipped:
            continue
        kwargs = _flag_kwargs(f, meta)
        if f.name in narrowed:
            kwargs["choices"] = narrowed[f.name]
        where: argparse.ArgumentParser | argparse._ArgumentGroup = parser
        if meta.group is not None:
            if meta.group not in groups:
                groups[meta.group] = parser.add_argument_group(meta.group)
            where = groups[meta.group]
        where.add_argument(flag_of(f, meta), *meta.aliases, **kwargs)


def _flag_kwargs(f: dataclasses.Field[Any], meta: Setting) -> dict[str, Any]:
    """``add_argument``'s keywords for one setting."""
    default = f.default
    kwargs: dict[str, Any] = {"dest": meta.dest or f.name, "help": meta.help}
    if meta.required:
        kwargs["required"] = True
    if meta.metavar is not None:
        kwargs["metavar"] = meta.metavar
    if isinstance(default, bool):
        kwargs["action"] = "store_true"
        return kwargs
    if meta.env is not None and os.environ.get(meta.env):
        # A string default goes through ``type`` as a flag's value would: a bad value in
        # the environment is refused by name, as a bad flag is.
        default = os.environ[meta.env]
    if isinstance(f.default, enum.Enum):
        kwargs["choices"] = list(meta.choices or [_spelling(m) for m in type(f.default)])
        default = _spelling(default) if isinstance(default, enum.Enum) else default
    else:
        if meta.parse is not None:
            kwargs["type"] = meta.parse
        if meta.choices is not None:
            kwargs["choices"] = list(meta.choices)
    if meta.repeat:
        # No default list: argparse would extend it instead of replacing it.
        kwargs.update(action="extend", nargs="+", default=None)
    else:
        kwargs["default"] = None if meta.unset else default
        if meta.count is not None:
            kwargs["nargs"] = meta.count
    shown = meta.shown
    if shown is None and meta.unset:
        shown = str(default)
    if shown is None and meta.env is not None:
        shown = f"${meta.env} or {f.default}"
    if shown is None and meta.repeat and isinstance(f.default, tuple) and f.default:
        shown = " ".join(str(v) for v in f.default)
    if shown is not None:
        kwargs["help"] += f" (default {shown})"
    elif f.default not in (None, ()) and not isinstance(f.default, bool):
        kwargs["help"] += " (default %(default)s)"
    return kwargs


def _spelling(member: enum.Enum) -> str:
    """How a flag spells an enum member: its value, or for a number its name in lower case."""
    return member.value if isinstance(member.value, str) else member.name.lower()


def from_args(config_type: type[Any], args: argparse.Namespace, **given: Any) -> Any:
    """The config the parsed flags describe; ``given`` fills the fields that are not
    settings (or overrides them). A setting without a flag here (skipped) keeps its
    default."""
    values: dict[str, Any] = {}
    for f, meta in settings(config_type):
        if f.name in given:
            continue
        value = getattr(args, meta.dest or f.name, f.default)
        if isinstance(f.default, enum.Enum) and not isinstance(value, enum.Enum):
            value = next(m for m in type(f.default) if _spelling(m) == value)
        elif (meta.repeat or meta.unset) and value is None:
            value = f.default  # not given
        if isinstance(value, list):
            value = tuple(value)  # configs are frozen: no lists inside
        values[f.name] = value
    return config_type(**values, **given)
