"""Deploy files: which services run on which host, with what arguments.

    version: 1
    network: {connect: [...], listen: [...], namespace: framegate}   # every process
    hosts:                                                            # optional
      robot: {address: 10.0.0.2, network: {listen: [tcp/10.0.0.2:7447]}}
    services:
      camera: {type: camera, host: robot, restart: true, args: {source: sim}}

Errors name the file, the line and the bad key. ``args`` become the service's command-line
flags (``seed: 1`` → ``--seed 1``, ``true`` → ``--flag``), checked against its parser.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from middleware import ConfigError, NetworkConfig, check_name, checked_endpoints
from services.lib.argtypes import closest, did_you_mean
from services.nodes import SERVICES

LOCAL_HOST = "local"
SERVICE_TYPES = (*SERVICES, "router")
_TOP_KEYS = {"version", "network", "hosts", "services"}
_HOST_KEYS = {"address", "role", "network"}
_SERVICE_KEYS = {"type", "host", "restart", "args", "network"}
_NETWORK_KEYS = {"connect", "listen", "namespace", "config"}


@dataclass(frozen=True, slots=True)
class HostSpec:
    """A machine of the deployment."""

    name: str
    address: str | None = None
    role: str | None = None
    network: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class ServiceSpec:
    """One service process: its type, host, flags and restart policy."""

    name: str
    type: str
    host: str
    args: tuple[str, ...]
    restart: bool = True
    network: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class Deployment:
    """A parsed, validated deploy file."""

    path: str
    network: dict[str, Any]
    hosts: dict[str, HostSpec]
    services: tuple[ServiceSpec, ...]

    def for_host(self, host: str | None) -> list[ServiceSpec]:
        """Services assigned to ``host`` (None: the only host, or every service)."""
        if host is None:
            if len(self.hosts) > 1:
                names = ", ".join(sorted(self.hosts))
                raise ConfigError(
                    f"{self.path} names several hosts ({names}); pick one with --host"
                )
            return list(self.services)
        if host not in self.hosts:
            known = ", ".join(sorted(self.hosts))
            raise ConfigError(
                f"{self.path} has no host {host!r}{did_you_mean(host, self.hosts, quote=True)}; "
                f"its hosts are: {known}"
            )
        return [s for s in self.services if s.host == host]

    def network_for(self, spec: ServiceSpec, base: NetworkConfig | None = None) -> NetworkConfig:
        """Deployment network, then the host's, then the service's, over ``base``."""
        merged: dict[str, Any] = {}
        for layer in (self.network, self.hosts[spec.host].network, spec.network):
            merged.update(layer)
        config = base or NetworkConfig()
        return NetworkConfig(
            connect=tuple(merged.get("connect", config.connect)),
            listen=tuple(merged.get("listen", config.listen)),
            config_file=Path(merged["config"]) if "config" in merged else config.config_file,
            config_origin="" if "config" in merged else config.config_origin,
            namespace=merged.get("namespace", config.namespace),
            shared_memory=config.shared_memory,
            local_port=config.local_port,
        )


_YAML = (".yaml", ".yml")


def load_deployment(path: str | Path) -> Deployment:
    """Read and validate a deploy file; ConfigError names the line of any problem."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        near = ""
        if not path.exists() and path.parent.is_dir():  # deploy/local.yml for .yaml
            # Names compared without the suffix, which every candidate shares (it made
            # ``nosuch.yaml`` look like ``ros2.yaml``); the suffix alone may differ.
            siblings = {p.stem: p.name for p in path.parent.iterdir() if p.suffix in _YAML}
            hint = closest(path.stem, siblings)
            if hint is not None:
                near = f" (did you mean {siblings[hint]!r}?)"
        raise ConfigError(f"cannot read deploy file {path}: {exc.strerror}{near}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"{path} is no deploy file: not text (byte {exc.start} is not UTF-8); "
            "a deploy file is YAML, e.g. deploy/local.yaml"
        ) from None
    return parse_deployment(text, str(path))


class _NotScalar(ValueError):
    """A list or mapping where one value belongs: a signal inside ``_parse``, which knows the
    line but not the file; ``parse_deployment`` turns it into the ConfigError naming both
    (so it is no FramegateError of its own, and never leaves this module)."""


def parse_deployment(text: str, name: str = "<deploy>") -> Deployment:
    """Parse deploy-file text (see the module docstring)."""
    try:
        return _parse(text, name)
    except _NotScalar as exc:
        raise ConfigError(f"{name}:{exc}") from exc


def _parse(text: str, name: str) -> Deployment:
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        raise ConfigError(_yaml_error(name, exc)) from exc
    if root is None:
        raise ConfigError(f"{name}: the deploy file is empty; it needs a 'services' mapping")
    top = _mapping(root, name, "the top level", _TOP_KEYS)
    if "version" in top and _scalar(top["version"][1]) not in (1, "1"):
        version = _scalar(top["version"][1])
        raise ConfigError(
            f"{name}:{_line(top['version'][1])}: unsupported version {version!r}; "
            "this framegate reads version 1"
        )
    network = _network(top["network"][1], name) if "network" in top else {}
    hosts: dict[str, HostSpec] = {}
    if "hosts" in top:
        for host_name, (key_node, node) in _mapping(top["hosts"][1], name, "hosts").items():
            _check_name(host_name, "host", name, key_node)
            fields = _mapping(node, name, f"host {host_name!r}", _HOST_KEYS)
            hosts[host_name] = HostSpec(
                host_name,
                address=_opt_str(fields, "address"),
                role=_opt_str(fields, "role"),
                network=_network(fields["network"][1], name) if "network" in fields else {},
            )
    if not hosts:
        hosts[LOCAL_HOST] = HostSpec(LOCAL_HOST)
    if "services" not in top:
        raise ConfigError(f"{name}: no 'services' mapping; list the services to start")
    services = []
    listed = _mapping(top["services"][1], name, "services")
    if not listed:  # `launch` would start nothing and wait for a Ctrl-C
        where = _line(top["services"][1])
        raise ConfigError(f"{name}:{where}: services is empty; list the services to start")
    for svc_name, (key_node, node) in listed.items():
        _check_name(svc_name, "service", name, key_node)
        fields = (
            _mapping(node, name, f"service {svc_name!r}", _SERVICE_KEYS) if _is_map(node) else {}
        )
        kind = _text(fields["type"][1], name, "type") if "type" in fields else svc_name
        if kind not in SERVICE_TYPES:
            where = _line(fields["type"][1]) if "type" in fields else _line(key_node)
            raise ConfigError(
                f"{name}:{where}: service {svc_name!r} has unknown type {kind!r}"
                f"{did_you_mean(kind, SERVICE_TYPES, quote=True)}; "
                f"use one of: {', '.join(SERVICE_TYPES)}"
            )
        if "host" in fields:
            host = _text(fields["host"][1], name, "host")
            if host not in hosts:
                raise ConfigError(
                    f"{name}:{_line(fields['host'][1])}: service {svc_name!r} names host "
                    f"{host!r}, which is not under 'hosts' ({', '.join(sorted(hosts))})"
                    f"{did_you_mean(host, hosts, quote=True)}"
                )
        elif len(hosts) == 1:
            host = next(iter(hosts))
        else:
            raise ConfigError(
                f"{name}:{_line(key_node)}: service {svc_name!r} needs a 'host' "
                f"(one of {', '.join(sorted(hosts))})"
            )
        args = _args(fields["args"][1], name, svc_name) if "args" in fields else ()
        restart = _bool(fields["restart"][1], name, "restart") if "restart" in fields else True
        net = _network(fields["network"][1], name) if "network" in fields else {}
        services.append(ServiceSpec(svc_name, kind, host, args, restart, net))
    return Deployment(name, network, hosts, tuple(services))


def _yaml_error(name: str, exc: yaml.YAMLError) -> str:
    """One line: the file, the line and column where the parser gave up, and why (PyYAML's
    own message spans several lines and quotes the text)."""
    mark = getattr(exc, "problem_mark", None)
    problem = getattr(exc, "problem", None) or "unreadable"
    context = getattr(exc, "context", None)
    where = f":{mark.line + 1}:{mark.column + 1}" if mark is not None else ""
    because = f" ({context})" if context else ""
    return f"{name}{where}: not valid YAML: {problem}{because}"


def _is_map(node: yaml.Node) -> bool:
    return isinstance(node, yaml.MappingNode)


def _line(node: yaml.Node) -> int:
    return int(node.start_mark.line) + 1


def _mapping(
    node: yaml.Node, name: str, where: str, allowed: set[str] | None = None
) -> dict[str, tuple[yaml.Node, yaml.Node]]:
    if not _is_map(node):
        raise ConfigError(f"{name}:{_line(node)}: {where} must be a mapping (key: value)")
    out: dict[str, tuple[yaml.Node, yaml.Node]] = {}
    for key_node, value_node in node.value:
        key = str(key_node.value)
        if allowed is not None and key not in allowed:
            raise ConfigError(
                f"{name}:{_line(key_node)}: unknown key {key!r} in {where}"
                f"{did_you_mean(key, allowed, quote=True)}; "
                f"expected one of: {', '.join(sorted(allowed))}"
            )
        if key in out:
            raise ConfigError(f"{name}:{_line(key_node)}: key {key!r} appears twice in {where}")
        out[key] = (key_node, value_node)
    return out


def _scalar(node: yaml.Node) -> Any:
    if not isinstance(node, yaml.ScalarNode):
        shape = "a list" if isinstance(node, yaml.SequenceNode) else "a mapping"
        raise _NotScalar(
            f"{_line(node)}: expected a single value (a word or a number), got {shape}"
        )
    # Constructed from the node itself: an empty value (`seed:`) serialises to a document
    # that YAML cannot read back.
    return yaml.constructor.SafeConstructor().construct_object(node)


def _text(node: yaml.Node, name: str, key: str) -> str:
    """A value that must be given: an empty one (`host:`) is not the word 'None'."""
    value = _scalar(node)
    if value is None:
        raise ConfigError(f"{name}:{_line(node)}: {key} is empty; give it a value")
    return str(value)


def _bool(node: yaml.Node, name: str, key: str) -> bool:
    """A YAML boolean; a quoted "false" would otherwise read as true."""
    value = _scalar(node)
    if not isinstance(value, bool):
        raise ConfigError(
            f"{name}:{_line(node)}: {key} must be true or false (unquoted), got {value!r}"
        )
    return value


def _opt_str(fields: dict[str, tuple[yaml.Node, yaml.Node]], key: str) -> str | None:
    return str(_scalar(fields[key][1])) if key in fields else None


def _check_name(value: str, what: str, name: str, node: yaml.Node) -> None:
    # A trailing newline or other control character would look like another name in `ls`.
    if any(ord(c) < 0x20 or ord(c) == 0x7F for c in value):
        raise ConfigError(
            f"{name}:{_line(node)}: {what} name {value!r} contains a control character"
        )
    try:
        check_name(value, what)
    except ConfigError as exc:
        raise ConfigError(f"{name}:{_line(node)}: {exc}") from exc


def _network(node: yaml.Node, name: str) -> dict[str, Any]:
    fields = _mapping(node, name, "network", _NETWORK_KEYS)
    out: dict[str, Any] = {}
    for key, (_key_node, value) in fields.items():
        if key in ("connect", "listen"):
            items = value.value if isinstance(value, yaml.SequenceNode) else [value]
            out[key] = [_text(v, name, key) for v in items]
            # Checked here, not by each service at start (a restart loop): 0 only to listen.
            for item, endpoint in zip(items, out[key], strict=True):
                checked_endpoints(
                    [endpoint], f"{name}:{_line(item)}: {key}", lowest=int(key == "connect")
                )
        else:
            out[key] = _text(value, name, key)
    return out


def _args(node: yaml.Node, name: str, service: str) -> tuple[str, ...]:
    argv: list[str] = []
    for key, (_key_node, value) in _mapping(node, name, f"args of {service!r}").items():
        flag = "--" + key.replace("_", "-")
        if isinstance(value, yaml.SequenceNode):
            items = [str(_scalar(v)) for v in value.value]
            argv += [flag, *items]
            continue
        scalar = _scalar(value)
        if scalar is True:
            argv.append(flag)
        elif scalar is False or scalar is None:
            continue
        else:
            argv += [flag, str(scalar)]
    return tuple(argv)


def arg_lines(text: str, service: str) -> dict[str, int]:
    """Line of each ``args`` key of one service, for error messages after parsing, and as
    ``--config`` the line of the ``network: {config: ...}`` that applies to it (the file's,
    its host's or its own, the last one that names one)."""
    root: Any = yaml.compose(text, Loader=yaml.SafeLoader)
    lines: dict[str, int] = {}
    with contextlib.suppress(KeyError, AttributeError, TypeError, ValueError):
        top = {k.value: v for k, v in root.value}
        entry = {k.value: v for k, v in top["services"].value}[service]
        fields = {k.value: v for k, v in entry.value}
        named = fields["host"].value if "host" in fields else LOCAL_HOST
        host = {k.value: v for k, v in top["hosts"].value}.get(named) if "hosts" in top else None
        layers = (top, {k.value: v for k, v in host.value} if host is not None else {}, fields)
        for layer in layers:
            if "network" in layer:
                for key_node, _value in layer["network"].value:
                    if key_node.value == "config":
                        lines["--config"] = _line(key_node)
    try:
        services = {k.value: v for k, v in root.value if k.value == "services"}["services"]
        entry = {k.value: v for k, v in services.value}[service]
        args = {k.value: v for k, v in entry.value}["args"]
        for key_node, _value in args.value:
            lines["--" + str(key_node.value).replace("_", "-")] = _line(key_node)
    except (KeyError, AttributeError, TypeError):
        pass
    return lines
