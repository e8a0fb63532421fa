"""The four service processes and their one registry.

``SERVICES`` lists the service types; ``service(name)`` imports only that one's module and
returns its :class:`~services.nodes._contract.Service`, so ``framegate ls`` never pays for
OpenCV. ``framegate run``, ``launch`` and the deploy-file validator all go through here.
"""

from __future__ import annotations

import importlib
import threading
from dataclasses import dataclass
from typing import Any

from middleware import NetworkConfig

from ._contract import AnyService, Service

# Service type -> the module that defines its SERVICE.
_MODULES = {
    "camera": "services.nodes.camera",
    "gyro": "services.nodes.gyro",
    "mediator": "services.nodes.mediator",
    "detector": "services.nodes.detector",
}
SERVICES: tuple[str, ...] = tuple(_MODULES)


def service(name: str) -> AnyService:
    """The service of type ``name`` (KeyError for an unknown type: check ``SERVICES``)."""
    module = importlib.import_module(_MODULES[name])
    found = getattr(module, "SERVICE", None)
    if found is not None:
        svc: AnyService = found
        return svc
    # A module that still exposes the contract as module-level functions.
    return _ModuleService(
        name,
        module.MediatorConfig if name == "mediator" else type(None),
        module.add_arguments,
        module.config_from_args,
        module.run,
    )


def describe(name: str) -> str:
    """First line of the service module's docstring (for ``framegate run --help``)."""
    module = importlib.import_module(_MODULES[name])
    return (module.__doc__ or name).strip().splitlines()[0]


@dataclass(frozen=True, slots=True)
class _ModuleService:
    name: str
    config_type: type[Any]
    _add: Any
    _config: Any
    _run: Any

    def add_arguments(self, parser: Any) -> None:
        self._add(parser)

    def config_from_args(self, args: Any) -> Any:
        return self._config(args)

    def run(self, config: Any, network: NetworkConfig, stop: threading.Event) -> int:
        return int(self._run(config, network, stop))


__all__ = ["SERVICES", "Service", "describe", "service"]
