"""A service's configuration written once: a frozen dataclass whose fields carry their help,
flag and default, from which the flags, the parsing and the deploy-file keys follow.

    @dataclass(frozen=True, slots=True)
    class GyroConfig:
        name: str = setting("gyro", "service name")
        batch: int = setting(10, "samples per message", parse=positive_int)

    add_flags(parser, GyroConfig)                  # --name, --batch (``framegate run gyro``)
    config = from_args(GyroConfig, parser.parse_args(argv))

A field's flag is ``--`` plus its name with dashes, unless ``flag`` says otherwise; extra
spellings go in ``aliases``. Booleans are switches (``--loop``); enums take their values;
``parse`` is the argparse type that checks a value (``services.lib.argtypes``). A field
without ``setting`` metadata (a nested config, e.g. the camera's source) is the service's
own to fill. A deploy file's service args are these flags' names (``deploy_keys``), and
``framegate launch`` checks them with the same parser.
"""

from __future__ import annotations

import argparse
import dataclasses
import enum
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


def setting(
    default: Any,
    help: str,
    *,
    flag: str | None = None,
    parse: Callable[[str], Any] | None = None,
    aliases: tuple[str, ...] = (),
    choices: Iterable[str] | None = None,
    dest: str | None = None,
) -> Any:
    """A config field with its default and how it is set from the command line."""
    chosen = tuple(choices) if choices is not None else None
    meta = Setting(help, flag, parse, aliases, chosen, dest)
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
    for f, meta in settings(config_type):
        if f.name in skipped:
            continue
        default = f.default
        names = [flag_of(f, meta), *meta.aliases]
        shown = "" if default is None or isinstance(default, bool) else " (default %(default)s)"
        kwargs: dict[str, Any] = {"dest": meta.dest or f.name, "help": meta.help + shown}
        if isinstance(default, bool):
            kwargs["action"] = "store_true"
        elif isinstance(default, enum.Enum):
            values = [m.value for m in type(default)]
            kwargs["choices"] = list(meta.choices or values)
            kwargs["default"] = default.value
        else:
            kwargs["default"] = default
            if meta.parse is not None:
                kwargs["type"] = meta.parse
            if meta.choices is not None:
                kwargs["choices"] = list(meta.choices)
        if f.name in narrowed:
            kwargs["choices"] = narrowed[f.name]
        parser.add_argument(*names, **kwargs)


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
            value = type(f.default)(value)
        values[f.name] = value
    return config_type(**values, **given)


def deploy_keys(config_type: type, *, skip: Iterable[str] = ()) -> set[str]:
    """The args a deploy file may give this service (its flags, as ``seed`` for ``--seed``)."""
    skipped = set(skip)
    keys = set()
    for f, meta in settings(config_type):
        if f.name not in skipped:
            for name in (flag_of(f, meta), *meta.aliases):
                keys.add(name.lstrip("-").replace("-", "_"))
    return keys
