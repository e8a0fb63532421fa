"""Deploy files, the processes they mean, and the supervisor that keeps them running."""

from ._deploy import (
    LOCAL_HOST,
    SERVICE_TYPES,
    Deployment,
    HostSpec,
    ServiceSpec,
    load_deployment,
    parse_deployment,
)
from ._plan import process_specs
from ._supervisor import ProcessSpec, Supervisor

__all__ = [
    "LOCAL_HOST",
    "SERVICE_TYPES",
    "Deployment",
    "HostSpec",
    "ProcessSpec",
    "ServiceSpec",
    "Supervisor",
    "load_deployment",
    "parse_deployment",
    "process_specs",
]
