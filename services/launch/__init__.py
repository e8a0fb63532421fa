"""Deploy files, the one pipeline definition, the processes they mean, and the supervisor
that keeps them running."""

from ._deploy import (
    LOCAL_HOST,
    SERVICE_TYPES,
    Deployment,
    HostSpec,
    ServiceSpec,
    load_deployment,
    parse_deployment,
)
from ._lock import LaunchLock, lock_path, runtime_dir
from ._pipeline import (
    PIPELINE,
    ArgValue,
    free_port,
    pipeline,
    pipeline_args,
    pipeline_yaml,
    private_specs,
)
from ._plan import START_DELAY_S, process_specs, reaches_own_listener
from ._supervisor import ProcessSpec, Supervisor, exit_text

__all__ = [
    "LOCAL_HOST",
    "PIPELINE",
    "SERVICE_TYPES",
    "START_DELAY_S",
    "ArgValue",
    "Deployment",
    "HostSpec",
    "LaunchLock",
    "ProcessSpec",
    "ServiceSpec",
    "Supervisor",
    "exit_text",
    "free_port",
    "load_deployment",
    "lock_path",
    "parse_deployment",
    "pipeline",
    "pipeline_args",
    "pipeline_yaml",
    "private_specs",
    "process_specs",
    "reaches_own_listener",
    "runtime_dir",
]
