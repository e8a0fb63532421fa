"""The pipeline, defined once: the paper's Fig. 5 as the services and flags deploy/local.yaml
lists, and the per-use overrides demo, soak, experiment and the tests apply to it.

    deployment = pipeline({"detector": {"service_factor": None}, "mediator": None})

A private run (soak, faults, the bench's working point, the experiment, tests) starts a
deployment's processes meeting only each other on a loopback port of their own
(``free_port``, ``private_specs``).

An override maps a service to the args to change (a value of None drops that flag), or to
None to leave the service out. ``tests/services/launch/test_pipeline_definition.py`` checks
that deploy/local.yaml says the same as ``pipeline()``.
"""

from __future__ import annotations

import random
import socket
from collections.abc import Mapping
from dataclasses import replace

import yaml

from middleware import ConfigError, NetworkConfig

from ._deploy import LOCAL_HOST, Deployment, HostSpec, ServiceSpec
from ._plan import process_specs
from ._supervisor import ProcessSpec

ArgValue = str | int | float | bool | None
# Service name (= its type) -> its args, as in deploy/local.yaml.
PIPELINE: Mapping[str, Mapping[str, ArgValue]] = {
    "camera": {"source": "sim", "seed": 1, "loop": True},
    "gyro": {"source": "sim", "seed": 1, "loop": True},
    "mediator": {"policy": "paper", "b0": 5.0},
    # The paper's detector needed ~1.6 frame periods per frame: emulate that load.
    "detector": {"input": "mediator/images", "queue": 2, "service_factor": 1.6},
}
Overrides = Mapping[str, Mapping[str, ArgValue] | None]


def pipeline_args(overrides: Overrides | None = None) -> dict[str, dict[str, ArgValue]]:
    """Each service's args after ``overrides`` (see the module docstring)."""
    overrides = overrides or {}
    unknown = set(overrides) - set(PIPELINE)
    if unknown:
        raise ConfigError(
            f"no pipeline service {', '.join(sorted(unknown))}; use: {', '.join(PIPELINE)}"
        )
    out: dict[str, dict[str, ArgValue]] = {}
    for name, args in PIPELINE.items():
        if name in overrides and overrides[name] is None:
            continue
        merged = {**args, **(overrides.get(name) or {})}
        out[name] = {k: v for k, v in merged.items() if v is not None}
    return out


def to_argv(args: Mapping[str, ArgValue]) -> tuple[str, ...]:
    """Args as flags, the deploy-file way: ``seed: 1`` → ``--seed 1``, ``true`` → ``--flag``."""
    argv: list[str] = []
    for key, value in args.items():
        flag = "--" + key.replace("_", "-")
        if value is True:
            argv.append(flag)
        elif value is not False and value is not None:
            argv += [flag, str(value)]
    return tuple(argv)


def pipeline(
    overrides: Overrides | None = None, *, name: str = "pipeline", restart: bool = True
) -> Deployment:
    """The pipeline as a one-host deployment."""
    services = tuple(
        ServiceSpec(svc, svc, LOCAL_HOST, to_argv(args), restart=restart)
        for svc, args in pipeline_args(overrides).items()
    )
    return Deployment(name, {}, {LOCAL_HOST: HostSpec(LOCAL_HOST)}, services)


def pipeline_yaml(overrides: Overrides | None = None) -> str:
    """The pipeline as deploy-file text (for ``framegate launch``)."""
    services = {svc: {"args": args} for svc, args in pipeline_args(overrides).items()}
    return yaml.safe_dump({"version": 1, "services": services}, sort_keys=False)


# Network settings a caller's environment might carry; a private run's children must meet
# only each other.
CLEARED_ENV = ("FRAMEGATE_CONNECT", "FRAMEGATE_LISTEN", "FRAMEGATE_CONFIG", "FRAMEGATE_NAMESPACE")


# Ports handed out lie below the kernel's ephemeral range (32768 and up on Linux), where
# outgoing connections take theirs: a port the kernel picks for us (bind to 0) is one a
# connection elsewhere may take before our process listens on it (seen in a parallel test
# run: "Can not create a new TCP listener").
_PRIVATE_PORTS = range(20000, 32768)


def free_port() -> int:
    """A loopback TCP port nobody listens on right now (a private rendezvous)."""
    for port in random.sample(_PRIVATE_PORTS, 64):
        with socket.socket() as sock:
            try:
                sock.bind(("127.0.0.1", port))
            except OSError:
                continue  # taken: another
            return port
    with socket.socket() as sock:  # the whole sample taken: any port the kernel gives
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def private_specs(
    deployment: Deployment, port: int, *, start_at_ns: int | None = None
) -> list[ProcessSpec]:
    """The deployment's processes on this host, meeting only each other (and a client
    ``Node(network=NetworkConfig(local_port=port))``) on the loopback rendezvous ``port``,
    whatever the caller's environment says."""
    specs = process_specs(deployment, None, NetworkConfig(local_port=port), start_at_ns=start_at_ns)
    extra = (("FRAMEGATE_LOCAL_PORT", str(port)), *((name, "") for name in CLEARED_ENV))
    return [replace(spec, env=(*spec.env, *extra)) for spec in specs]
