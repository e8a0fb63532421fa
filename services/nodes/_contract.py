"""The one contract every service process keeps, so ``run``, ``launch`` and the deploy
validator treat camera, gyro, mediator and detector alike.

A service is a name, a frozen config dataclass, the flags that fill it, and ``run``::

    parser = argparse.ArgumentParser()
    svc.add_arguments(parser)
    config = svc.config_from_args(parser.parse_args(argv))   # an instance of svc.config_type
    code = svc.run(config, network, stop)                    # returns when ``stop`` is set

Every field of ``config_type`` has a flag of the same name (``retention_s`` →
``--retention-s``, nested source fields through ``--source`` & co.);
``tests/services/nodes/test_contract.py`` checks it for every registered service, so a
field cannot be added without a way to set it.
"""

from __future__ import annotations

import argparse
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, Protocol, TypeVar

from middleware import NetworkConfig

ConfigT = TypeVar("ConfigT")


class Service(Protocol[ConfigT]):
    """A service process: its type name, its config dataclass, its flags and its loop."""

    @property
    def name(self) -> str:
        """The service type (``camera``); also the default service name."""
        ...

    @property
    def config_type(self) -> type[ConfigT]:
        """The frozen dataclass ``config_from_args`` returns and ``run`` takes."""
        ...

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        """Add one flag per config field (``framegate run NAME --help``)."""
        ...

    def config_from_args(self, args: argparse.Namespace) -> ConfigT:
        """The config the parsed flags describe."""
        ...

    def run(self, config: ConfigT, network: NetworkConfig, stop: threading.Event) -> int:
        """Serve until ``stop`` is set (or the source ends); the process's exit code."""
        ...


AnyService = Service[Any]


@dataclass(frozen=True, slots=True)
class ServiceEntry(Generic[ConfigT]):
    """A service module's functions bundled as a :class:`Service` (one line per module)."""

    name: str
    config_type: type[ConfigT]
    add_arguments: Callable[[argparse.ArgumentParser], None]
    config_from_args: Callable[[argparse.Namespace], ConfigT]
    run: Callable[[ConfigT, NetworkConfig, threading.Event], int]
