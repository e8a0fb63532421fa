"""Turn a deployment into the processes to start on one host."""

from __future__ import annotations

import argparse
import errno
import ipaddress
import re
import socket
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import NoReturn

from middleware import ConfigError, FramegateError, NetworkConfig, endpoint_parts
from services.lib.argtypes import did_you_mean
from services.nodes import service
from services.nodes._vision_handler import checked_apart

from ._deploy import Deployment, ServiceSpec, arg_lines
from ._supervisor import ProcessSpec

# Replays on every process of one launch start at the same wall-clock instant.
START_DELAY_S = 2.0


def _check_args(
    spec: ServiceSpec, deployment: Deployment, text: str | None
) -> argparse.Namespace | None:
    """Parse a service's args with its own parser and make its config from them, as
    ``framegate run`` does; name the deploy-file line on error."""
    if spec.type == "router":
        if spec.args:
            raise ConfigError(f"{deployment.path}: router {spec.name!r} takes no args")
        return None
    # Exact keys only: `se: 1` must not pass as an abbreviation of --seed.
    parser = argparse.ArgumentParser(
        prog=spec.name, exit_on_error=False, add_help=False, allow_abbrev=False
    )
    service(spec.type).add_arguments(parser)

    def refuse(message: str) -> NoReturn:
        # argparse reports a missing required flag through ``error`` (print and exit),
        # exit_on_error or not: one line of ours instead.
        raise ConfigError(
            f"{deployment.path}: service {spec.name!r}: {message}"
            f" (see 'framegate run {spec.type} --help')"
        )

    parser.error = refuse  # type: ignore[method-assign]
    lines = arg_lines(text, spec.name) if text else {}
    try:
        _args, unknown = parser.parse_known_args(list(spec.args))
    except argparse.ArgumentError as exc:
        # A bad value (`rate: .nan`, `frames: -5`): name its line, so that the launcher
        # refuses the file at once instead of restarting a service that cannot start.
        line = lines.get(exc.argument_name or "")
        where = f":{line}" if line else ""
        raise ConfigError(
            f"{deployment.path}{where}: service {spec.name!r}: {exc}"
            f" (see 'framegate run {spec.type} --help')"
        ) from exc
    # Short flags too (-e tcp/...), and stray values: whatever the service would not take.
    if unknown:
        flag = next((u for u in unknown if u.startswith("-")), unknown[0])
        where = f":{lines[flag]}" if flag in lines else ""
        known = [o.lstrip("-").replace("-", "_") for a in parser._actions for o in a.option_strings]
        key = flag.lstrip("-").replace("-", "_")
        argv = list(spec.args)
        before = argv[argv.index(flag) - 1] if flag in argv[1:] else ""
        if not flag.startswith("-") and before.startswith("--") and before in lines:
            # A switch given a value (`loop: yes please`): name the switch and its line.
            where = f":{lines[before]}"
            switch = before[2:].replace("-", "_")
            what = f"takes true or false for {switch!r}, got {flag!r}"
        elif flag.startswith("-"):
            what = f"has no option {key!r}{did_you_mean(key, known)}"
        else:
            what = f"does not take the value {flag!r}"
        raise ConfigError(
            f"{deployment.path}{where}: service {spec.name!r} {what} "
            f"(see 'framegate run {spec.type} --help'; network settings go under 'network')"
        )
    # Then what `framegate run` does with the flags, so that each value is checked once, by
    # the service itself (a port past 65535 in `ros_connect` passed --check before).
    try:
        service(spec.type).config_from_args(_args)
    except FramegateError as exc:
        flag = next((f for f in re.findall(r"--[a-z0-9][a-z0-9-]*", str(exc)) if f in lines), "")
        where = f":{lines[flag]}" if flag else ""
        raise ConfigError(
            f"{deployment.path}{where}: service {spec.name!r}: {exc}"
            f" (see 'framegate run {spec.type} --help')"
        ) from exc
    return _args


def _check_files(
    spec: ServiceSpec,
    parsed: argparse.Namespace | None,
    net: NetworkConfig,
    where: str,
    lines: dict[str, int],
) -> None:
    """ConfigError naming the first file a service needs and cannot read, and the deploy
    file's line that names it: its Zenoh config with the certificates in it, a ROS 2 side's
    config, a camera description, a replayed dataset. A service that cannot start must not
    be started (and restarted) at all."""
    flag = "--config"
    try:
        try:
            net.check_files()
        except ConfigError as exc:
            config = net.config_file
            if config is None or config.exists():
                raise
            # A secure profile's certificates are made, not shipped: say how, and from where
            # (its paths are relative: from the directory that holds the script).
            maker = config.parent.parent / "make-certs.sh"
            bases = (Path.cwd(), *Path(where).resolve().parents)
            base = next((d for d in bases if (d / maker).is_file()), None)
            if base is None:
                raise
            make = f"{maker} {config.parent}"
            if base.resolve() != Path.cwd().resolve():
                make = (
                    f"cd {base} && {make}, and run launch from there (relative paths are "
                    "taken from the current directory)"
                )
            raise ConfigError(
                f"{exc}; make the certificates first: {make} (docs/security.md)"
            ) from exc
        if parsed is None:
            return
        flag = "--ros-config"
        if ros_config := getattr(parsed, "ros_config", None):
            NetworkConfig(config_file=Path(ros_config)).check_files()
        flag = "--camera-xml"
        if camera_xml := getattr(parsed, "camera_xml", None):
            from services.lib.camera_model import CameraModel
            from services.nodes.sources import check_device_only

            if (kind := getattr(parsed, "source", None)) is not None:  # a camera's source
                check_device_only(kind, camera_xml)

            try:
                CameraModel.from_xml(Path(camera_xml).read_bytes())
            except OSError as exc:
                message = f"cannot read camera description {camera_xml}: {exc.strerror}"
                raise ConfigError(message) from exc
            except FramegateError as exc:
                raise ConfigError(f"camera description {camera_xml}: {exc}") from exc
        flag = "--path"
        if getattr(parsed, "source", None) == "replay" and parsed.path:
            from services.lib.sim import DatasetError, read_dataset

            try:
                read_dataset(Path(parsed.path))
            except DatasetError as exc:
                raise ConfigError(f"dataset {parsed.path}: {exc}") from exc
        device = str(parsed.path or "") if getattr(parsed, "source", None) == "device" else ""
        if device.startswith("/") and not Path(device).exists():
            # A device file (an index or a URL is only known once opened).
            raise ConfigError(f"video device {device} does not exist on this host")
    except ConfigError as exc:
        line = f":{lines[flag]}" if flag in lines else ""
        named = (net.config_file, *(getattr(parsed, k, None) for k in _PATH_ARGS))
        hint = _relative_hint([str(p) for p in named if p], str(exc), Path(where))
        raise ConfigError(f"{where}{line}: service {spec.name!r}: {exc}{hint}") from exc


_PATH_ARGS = ("ros_config", "camera_xml", "path")
_INET = ("tcp", "tls", "udp", "quic")


def _foreign_address(endpoint: str) -> bool:
    """Whether ``endpoint`` names an IP address this machine does not have (a router of
    another host's share); host names, wildcards and other protocols are not judged."""
    proto, host, _port = endpoint_parts(endpoint)
    if proto not in _INET:
        return False
    try:
        address = ipaddress.ip_address(host.strip("[]"))
    except ValueError:
        return False
    if address.is_unspecified or address.is_loopback:
        return False
    failed = _bind_fails(address)
    return failed is not None and failed.errno == errno.EADDRNOTAVAIL


def _bind_fails(address: ipaddress.IPv4Address | ipaddress.IPv6Address) -> OSError | None:
    """Why a socket cannot bind to ``address`` (one of this machine's own, if it can)."""
    family = socket.AF_INET6 if address.version == 6 else socket.AF_INET
    with socket.socket(family, socket.SOCK_DGRAM) as probe:
        try:
            probe.bind((str(address), 0))
        except OSError as exc:
            return exc
    return None


_Address = ipaddress.IPv4Address | ipaddress.IPv6Address


def _addresses(host: str) -> set[_Address]:
    """The IP addresses ``host`` names (an address, or a name resolved); none if unknown."""
    host = host.strip("[]").split("%", 1)[0]
    try:
        return {ipaddress.ip_address(host)}
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(host, None, proto=socket.IPPROTO_TCP)
    except (OSError, UnicodeError):
        return set()
    return {ipaddress.ip_address(str(info[4][0]).split("%", 1)[0]) for info in infos}


def _is_here(address: _Address) -> bool:
    """Whether connecting to ``address`` reaches this machine."""
    return address.is_loopback or address.is_unspecified or _bind_fails(address) is None


def reaches_own_listener(connect: str, listen: str) -> bool:
    """Whether connecting to ``connect`` from this machine reaches its listener ``listen``:
    compared by protocol, port and address, not as text (``tls/localhost:7447`` reaches
    ``tls/[::]:7447``, ``tcp/localhost:P`` reaches ``tcp/127.0.0.1:P``). A wildcard listener
    takes every address of this machine, loopback included."""
    if connect == listen:
        return True
    proto, host, port = endpoint_parts(connect)
    listen_proto, listen_host, listen_port = endpoint_parts(listen)
    if proto != listen_proto or port != listen_port or proto not in _INET:
        return False
    if not port.isdigit() or int(port) == 0:
        return False  # port 0 listens on any free port: nothing to connect to
    targets, listening = _addresses(host), _addresses(listen_host)
    if any(a.is_unspecified for a in listening):
        return any(_is_here(a) for a in targets)
    return bool(targets & listening)


def _check_listens_here(spec: ServiceSpec, net: NetworkConfig, where: str) -> None:
    """ConfigError for a router of this machine's share that would listen on an address
    this machine lacks: it could never start, and would be restarted with backoff for ever."""
    for endpoint in net.listen:
        if _foreign_address(endpoint):
            raise ConfigError(
                f"{where}: service {spec.name!r}: cannot listen on {endpoint}: that address is "
                f"not one of this machine's (is this machine host {spec.host!r}? run each "
                "host's share on its own machine, or put this machine's address into the file)"
            )


def _relative_hint(paths: list[str], message: str, deploy_file: Path) -> str:
    """For a relative path a deploy file names that is missing from the current directory
    but found from the deploy file's directory or one above it: that relative paths are
    taken from the current directory, and where to run ``launch`` from instead."""
    for path in paths:
        if Path(path).is_absolute() or path not in message or Path(path).exists():
            continue
        found = next(
            (d for d in deploy_file.resolve().parents if (d / path).exists()),
            None,
        )
        if found is not None and found != Path.cwd().resolve():
            return (
                f" (relative paths are taken from the current directory, {Path.cwd()}; "
                f"it is in {found}: run launch from there)"
            )
    return ""


def _claim_ports(
    spec: ServiceSpec, net: NetworkConfig, taken: dict[str, str], deployment: Deployment
) -> None:
    """ConfigError when ``spec`` would listen on a fixed port another process of the same
    share listens on already (``taken``: endpoint -> service): one port takes one process,
    the rest could never start and would be restarted for ever."""
    from_config = not net.listen and net.config_file is not None
    for endpoint in net.listen_endpoints() if from_config else net.listen:
        if endpoint_parts(endpoint)[2] == "0":  # any free port: one each
            continue
        if (first := taken.setdefault(endpoint, spec.name)) == spec.name:
            continue
        if from_config:
            origin = f" (the listen endpoints of {net.config_name})"
        elif endpoint in deployment.network_for(spec).listen:
            origin = ""
        else:
            origin = " (set by --listen or FRAMEGATE_LISTEN)"
        raise ConfigError(
            f"{deployment.path}: services {first!r} and {spec.name!r} would both listen on "
            f"{endpoint}{origin}: one port takes one process, the others could never start; "
            "give each its own port, port 0 for any free one, or leave listen out (the "
            "loopback rendezvous)"
        )


def process_specs(
    deployment: Deployment,
    host: str | None,
    base: NetworkConfig,
    *,
    text: str | None = None,
    start_at_ns: int | None = None,
    override: Callable[[NetworkConfig], NetworkConfig] | None = None,
    here: bool = False,
) -> list[ProcessSpec]:
    """The processes of ``host``'s share, each with its network flags and a shared start.

    ``override`` applies what outranks the deploy file (environment, then flags). ``here``:
    the share is this machine's (a launch, or its ``--check``), so a router's listen
    addresses must be this machine's.
    """
    start = start_at_ns if start_at_ns is not None else time.time_ns() + int(START_DELAY_S * 1e9)
    out = []
    listening: dict[str, str] = {}  # fixed endpoint -> the service that listens there
    for spec in deployment.for_host(host):
        with checked_apart():  # the launcher runs no handler: it imports none
            parsed = _check_args(spec, deployment, text)
        net = deployment.network_for(spec, base)
        if override is not None:
            net = override(net)
        lines = arg_lines(text, spec.name) if text else {}
        if deployment.network_for(spec).config_file != net.config_file:
            lines.pop("--config", None)  # not the file's: a flag or a variable named it
        _check_files(spec, parsed, net, deployment.path, lines)
        if spec.type == "router":
            if not net.listen:
                # Loopback unless the deploy file says where: no wide listener by accident;
                # on the rendezvous port, as `framegate router` itself.
                net = replace(net, listen=(f"tcp/127.0.0.1:{net.local_port}",))
            # A file-wide ``connect`` names the router every process reaches: the router
            # itself does not connect to where it listens (it did, a link to itself), also
            # when the two are written differently (FRAMEGATE_CONNECT=tls/localhost:P).
            own = tuple(
                e for e in net.connect if not any(reaches_own_listener(e, x) for x in net.listen)
            )
            net = replace(net, connect=own)
            if here:
                _check_listens_here(spec, net, deployment.path)
            argv = [sys.executable, "-m", "services.cli", "router", *net.to_args()]
        else:
            argv = [
                sys.executable,
                "-m",
                "services.cli",
                "run",
                spec.type,
                "--name",
                spec.name,
                *spec.args,
                *net.to_args(),
            ]
        _claim_ports(spec, net, listening, deployment)
        out.append(
            ProcessSpec(
                spec.name,
                tuple(argv),
                restart=spec.restart,
                env=(("FRAMEGATE_START_AT_NS", str(start)),),
            )
        )
    return out
