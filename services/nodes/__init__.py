"""The service processes (camera, gyro, mediator, detector, your own vision code, the ROS 2
bridge) and their one registry.

``SERVICES`` lists the service types; ``service(name)`` imports only that one's module and
returns its :class:`~services.nodes._contract.Service`, so ``framegate ls`` never pays for
OpenCV. ``framegate run``, ``launch`` and the deploy-file validator all go through here.
"""

from __future__ import annotations

import importlib

from ._contract import AnyService, Service
from ._runtime import exit_with_parent

# Service type -> the module that defines its SERVICE (a _contract.Service).
_MODULES = {
    "camera": "services.nodes.camera",
    "gyro": "services.nodes.gyro",
    "mediator": "services.nodes.mediator",
    "detector": "services.nodes.detector",
    "vision": "services.nodes.vision",
    "ros2": "services.nodes.ros2",
}
SERVICES: tuple[str, ...] = tuple(_MODULES)


def service(name: str) -> AnyService:
    """The service of type ``name`` (KeyError for an unknown type: check ``SERVICES``)."""
    module = importlib.import_module(_MODULES[name])
    svc: AnyService = module.SERVICE
    return svc


def describe(name: str) -> str:
    """First paragraph of the service module's docstring, on one line (for ``framegate run
    --help``)."""
    module = importlib.import_module(_MODULES[name])
    # Docstrings use reST literals (``frame``); a terminal shows them as plain words.
    text = (module.__doc__ or name).strip().split("\n\n")[0].replace("``", "")
    return " ".join(text.split())


__all__ = ["SERVICES", "Service", "describe", "exit_with_parent", "service"]
