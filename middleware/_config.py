"""Network configuration: defaults → deploy/config file → environment → flags.

The embedded default needs no router and no multicast: the first framegate process on a
host listens on ``tcp/127.0.0.1:<local_port>`` (7447), later ones listen on a free loopback
port and connect to it; Zenoh's gossip then meshes them, so the first one may exit.
If a Zenoh router already holds that port, everyone simply connects to it.

Listening is loopback-only unless asked for. Zenoh's own peer default is ``tcp/[::]:0``,
every interface; a framegate process given only ``--connect`` (or a config file that names
no listen endpoints) instead listens on ``tcp/127.0.0.1:0``: local peers still mesh through
gossip (peers do not forward for each other, so each must be reachable), and nothing on the
network can open a connection to it. Listening wider takes an explicit ``--listen``,
``FRAMEGATE_LISTEN``, deploy-file ``listen`` or config-file ``listen/endpoints``.
``listening_endpoints()`` reports what a process actually listens on (``framegate ls``).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import socket
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import psutil
import zenoh

from ._errors import ConfigError
from ._rendezvous import known_peers

# Matched with fullmatch: "$" alone would also accept a trailing newline ("camera\n").
NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.\-]*")  # a plain key-expression chunk
DEFAULT_NAMESPACE = "framegate"
DEFAULT_LOCAL_PORT = 7447
# Where a process listens when nothing asks for more: loopback, so no other host can reach it.
LOOPBACK_PEER_LISTEN = "tcp/127.0.0.1:0"
# On the loopback rendezvous, how long zenoh.open waits for peers (Zenoh's default is 500 ms).
RENDEZVOUS_DELAY_MS = 50
# ... and how long a Node then waits, at most, until every live process of the rendezvous is
# connected (a frozen one never is).
RENDEZVOUS_WAIT_S = 0.5
# ... and how long a handshake with one of them may take. On loopback a live peer answers in
# milliseconds; a frozen one (SIGSTOP) never does, and closing a session waits for every
# handshake it started (Zenoh's default of 10 s made `framegate ls` exit 10 s late).
RENDEZVOUS_OPEN_TIMEOUT_MS = 1000
LOOPBACK_ROUTER_LISTEN = f"tcp/127.0.0.1:{DEFAULT_LOCAL_PORT}"


# Zenoh's errors end in the Rust source line that raised them (" at /root/.cargo/...rs:86."),
# and its config errors wrap the message in a Debug dump ('Json5Err(Message { msg: "..." })').
_RUST_LOCATION = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")
_DEBUG_MSG = re.compile(r'\bmsg: "((?:[^"\\]|\\.)*)"')
_DEBUG_LOCATION = re.compile(r"Location \{ line: (\d+), column: (\d+) \}")
ENDPOINT_FORM = "PROTOCOL/ADDRESS:PORT, e.g. tcp/192.168.1.10:7447"


def zenoh_message(exc: BaseException) -> str:
    """A Zenoh error as one line a person can read: its message without the Rust source
    locations and Debug wrapping Zenoh adds."""
    text = str(exc)
    where = ""
    if wrapped := _DEBUG_MSG.search(text):
        if at := _DEBUG_LOCATION.search(text):
            where = f" (line {at.group(1)}, column {at.group(2)})"
        text = wrapped.group(1).replace('\\"', '"')
    return " ".join(_RUST_LOCATION.sub("", text).split()).rstrip(".") + where


def check_name(value: str, what: str) -> str:
    """A service, buffer or namespace name must be one plain key-expression chunk."""
    if not NAME.fullmatch(value):
        raise ConfigError(
            f"bad {what} name {value!r}: use letters, digits, '_', '.', '-' "
            "(no '/', '*', '$', '@', '?', '#', spaces or control characters)"
        )
    return value


def _namespace(value: str, origin: str) -> str:
    """A namespace from a variable or flag; its error names where it came from."""
    try:
        return check_name(value, "namespace")
    except ConfigError as exc:
        raise ConfigError(f"{origin}: {exc}") from exc


@dataclass(frozen=True, slots=True)
class NetworkConfig:
    """How a process meets the others.

    With no ``connect``, ``listen`` or ``config_file`` the local rendezvous default is used.
    ``lease_ms`` bounds how long a silent peer (stopped process, cut link) is believed alive.
    """

    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: Path | None = None
    namespace: str = DEFAULT_NAMESPACE
    mode: str = "peer"
    multicast: bool = False
    lease_ms: int = 1000
    shared_memory: bool = True
    local_port: int = DEFAULT_LOCAL_PORT
    extra: tuple[tuple[str, str], ...] = field(default=())
    # Where ``config_file`` came from when not a flag or deploy file ("FRAMEGATE_CONFIG"),
    # so that an error about the file names the variable that set it.
    config_origin: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        check_name(self.namespace, "namespace")
        if self.mode not in ("peer", "client", "router"):
            raise ConfigError(f"bad mode {self.mode!r}: use peer, client or router")
        if not 0 < self.local_port < 65536:
            raise ConfigError(f"local port {self.local_port} is not a port number: use 1..65535")
        if self.lease_ms < 100:
            raise ConfigError(f"lease_ms {self.lease_ms} is too small; use >= 100")

    @property
    def uses_local_default(self) -> bool:
        """True when nothing says where to meet, so the loopback rendezvous is used."""
        return not (self.connect or self.listen or self.config_file)

    def with_env(self, environ: dict[str, str] | None = None) -> NetworkConfig:
        """Apply FRAMEGATE_CONNECT / _LISTEN (comma-separated), _CONFIG, _NAMESPACE, _LOCAL_PORT."""
        env = os.environ if environ is None else environ
        changes: dict[str, Any] = {}
        if env.get("FRAMEGATE_CONNECT"):
            connect = _split(env["FRAMEGATE_CONNECT"])
            changes["connect"] = checked_endpoints(connect, "FRAMEGATE_CONNECT")
        if env.get("FRAMEGATE_LISTEN"):
            listen = _split(env["FRAMEGATE_LISTEN"])
            changes["listen"] = checked_endpoints(listen, "FRAMEGATE_LISTEN", lowest=0)
        if env.get("FRAMEGATE_CONFIG"):
            changes["config_file"] = Path(env["FRAMEGATE_CONFIG"])
            changes["config_origin"] = "FRAMEGATE_CONFIG"
        if env.get("FRAMEGATE_NAMESPACE"):
            changes["namespace"] = _namespace(env["FRAMEGATE_NAMESPACE"], "FRAMEGATE_NAMESPACE")
        if env.get("FRAMEGATE_LOCAL_PORT"):
            changes["local_port"] = _port(env["FRAMEGATE_LOCAL_PORT"], "FRAMEGATE_LOCAL_PORT")
        return replace(self, **changes) if changes else self

    def with_args(self, args: argparse.Namespace) -> NetworkConfig:
        """Apply the shared connection flags (see ``add_network_arguments``)."""
        changes: dict[str, Any] = {}
        if getattr(args, "connect", None):
            changes["connect"] = checked_endpoints(args.connect, "--connect")
        if getattr(args, "listen", None):
            changes["listen"] = checked_endpoints(args.listen, "--listen", lowest=0)
        if getattr(args, "config", None):
            changes["config_file"] = Path(args.config)
            changes["config_origin"] = ""
        if getattr(args, "namespace", None):
            changes["namespace"] = _namespace(args.namespace, "--namespace")
        if getattr(args, "no_shm", False):
            changes["shared_memory"] = False
        return replace(self, **changes) if changes else self

    def to_args(self) -> list[str]:
        """The flags that reproduce this config in a child process."""
        out: list[str] = []
        for endpoint in self.connect:
            out += ["--connect", endpoint]
        for endpoint in self.listen:
            out += ["--listen", endpoint]
        if self.config_file:
            out += ["--config", str(self.config_file)]
        if self.namespace != DEFAULT_NAMESPACE:
            out += ["--namespace", self.namespace]
        if not self.shared_memory:
            out += ["--no-shm"]
        return out

    @property
    def config_name(self) -> str:
        """``Zenoh config PATH`` for messages, naming the variable that set it, if one did."""
        origin = f" (set by {self.config_origin})" if self.config_origin else ""
        return f"Zenoh config {self.config_file}{origin}"

    def zenoh_configs(self) -> list[zenoh.Config]:
        """Configs to try in order (the rendezvous default has two: hub, then spoke)."""
        if self.uses_local_default:
            hub = [f"tcp/127.0.0.1:{self.local_port}"]
            # Any live process of the rendezvous lets a newcomer in, not only the port's
            # holder (it may be frozen): see _rendezvous.
            peers = known_peers(self.local_port)
            configs = [
                self._build(listen=hub, connect=peers),
                self._build(listen=["tcp/127.0.0.1:0"], connect=hub + peers),
            ]
            for conf in configs:
                # Zenoh's open waits this long for peers to connect (500 ms by default);
                # here every peer is named, and Node waits for them itself (RENDEZVOUS_WAIT_S).
                _insert(conf, "scouting/delay", RENDEZVOUS_DELAY_MS)
                _insert(conf, "transport/unicast/open_timeout", RENDEZVOUS_OPEN_TIMEOUT_MS)
            return configs
        return [self._build(listen=list(self.listen), connect=list(self.connect))]

    def listen_endpoints(self) -> tuple[str, ...]:
        """The endpoints this configuration asks to listen on (its flags, else its file's)."""
        endpoints = _get(self.zenoh_configs()[0], "listen/endpoints")
        return (
            tuple(e for e in endpoints if isinstance(e, str)) if isinstance(endpoints, list) else ()
        )

    def check_files(self) -> None:
        """ConfigError naming the first file this configuration needs and cannot read: the
        Zenoh config file (which must also parse) and every TLS certificate and key it
        names. Zenoh itself reads the certificates only when a session opens."""
        if self.config_file is None:
            return
        conf = self.zenoh_configs()[0]  # ConfigError naming the file if it cannot be read
        try:
            tls = json.loads(conf.get_json("transport/link/tls"))
        except (zenoh.ZError, ValueError):
            return  # no TLS section: nothing more to read
        for key, value in sorted(tls.items() if isinstance(tls, dict) else ()):
            # *_base64 keys hold the certificate itself; the others name a file.
            if not isinstance(value, str) or not key.endswith(("_certificate", "_private_key")):
                continue
            try:
                with open(value, "rb"):
                    pass
            except OSError as exc:
                raise ConfigError(
                    f"cannot read {value}, the {key} of {self.config_name}: {exc.strerror or exc}"
                ) from exc

    def _build(self, *, listen: list[str], connect: list[str]) -> zenoh.Config:
        try:
            conf = (
                zenoh.Config.from_file(str(self.config_file))
                if self.config_file
                else zenoh.Config()
            )
        except zenoh.ZError as exc:
            raise ConfigError(f"cannot read {self.config_name}: {zenoh_message(exc)}") from exc
        except OSError as exc:
            raise ConfigError(f"cannot read {self.config_name}: {exc}") from exc
        settings: list[tuple[str, Any]] = []
        if not self.config_file:
            settings += [
                ("mode", self.mode),
                ("scouting/multicast/enabled", self.multicast),
                ("transport/link/tx/lease", self.lease_ms),
                # A link whose peer takes nothing for the lease is closed as a silent one is:
                # Zenoh's 5 s let a peer that stops reading (keeping its lease alive) hold a
                # flow-controlled put(wait_s=0) 5.0 s in the send of its notification.
                (_BLOCK_CLOSE_KEY, self.lease_ms * 1000),
                ("transport/shared_memory/enabled", self.shared_memory),
                (
                    "connect/retry",
                    {"period_init_ms": 100, "period_max_ms": 1000, "period_increase_factor": 2},
                ),
            ]
        else:
            # A file decides, except what the command itself stands for (a router is a router).
            if self.mode != "peer":
                settings.append(("mode", self.mode))
            if not self.shared_memory:
                settings.append(("transport/shared_memory/enabled", False))
            # A file that leaves the lease alone gets ours, not Zenoh's 10 s: peers believe a
            # process alive for the lease it announces, so a stopped `watch --flow-control
            # --config peer.json5` held the camera 10 s instead of 1 s.
            if _get(conf, "transport/link/tx/lease") == _get(_DEFAULTS, "transport/link/tx/lease"):
                settings.append(("transport/link/tx/lease", self.lease_ms))
        if listen:
            _check_endpoints(listen, "listen on")
            settings.append(("listen/endpoints", listen))
        elif (default_listen := _loopback_listen(conf, self.mode)) is not None:
            settings.append(("listen/endpoints", default_listen))
        if connect:
            _check_endpoints(connect, "connect to")
            settings.append(("connect/endpoints", connect))
        for key, value in settings:
            _insert(conf, key, value)
        for key, raw in self.extra:
            _insert_raw(conf, key, raw)
        return conf


def _loopback_listen(conf: zenoh.Config, mode: str) -> list[str] | None:
    """Loopback endpoints to listen on when nothing asked, or None to leave ``conf`` alone.

    None when a config file names its own listen endpoints (it asked) or the process is a
    client (clients never listen). A file that allows only other protocols (e.g. TLS) gets
    no listener at all rather than a plain-TCP one.
    """
    if _get(conf, "listen/endpoints") != _get(_DEFAULTS, "listen/endpoints"):
        return None
    effective = mode if mode != "peer" else (_get(conf, "mode") or "peer")
    if effective == "client":
        return None
    protocols = _get(conf, "transport/link/protocols")
    if isinstance(protocols, list) and "tcp" not in protocols:
        return []
    return [LOOPBACK_ROUTER_LISTEN if effective == "router" else LOOPBACK_PEER_LISTEN]


_DEFAULTS = zenoh.Config()


def _get(conf: zenoh.Config, key: str) -> Any:
    try:
        return json.loads(conf.get_json(key))
    except (zenoh.ZError, ValueError):
        return None


# Zenoh protocols carried on each OS transport: a `tls/[::]:7447` listener is, to the
# operating system, a TCP socket on port 7447.
_OVER = {"tcp": ("tls", "ws"), "udp": ("quic",)}


def _relabelled(endpoint: str, configured: Iterable[str]) -> str:
    """``tcp/[::]:7447`` as ``tls/[::]:7447`` when a configured endpoint names TLS on that
    port (the OS cannot tell; a user who asked for TLS must not read plain TCP)."""
    transport, _, address = endpoint.partition("/")
    port = address.rpartition(":")[2]
    for wanted in configured:
        protocol, _, rest = wanted.partition("/")
        if protocol in _OVER.get(transport, ()) and rest.split("#")[0].rpartition(":")[2] == port:
            return f"{protocol}/{address}"
    return endpoint


def listening_endpoints(configured: Iterable[str] = ()) -> list[str]:
    """What this process listens on, as Zenoh endpoints (``tcp/127.0.0.1:7447``), sorted.

    Read from the operating system (every listening TCP socket and unconnected UDP socket of
    the process), not from the configuration, so a listener nobody meant to open shows too.
    A socket on the port of a ``configured`` TLS, WebSocket or QUIC endpoint is named with
    that protocol (``NetworkConfig.listen_endpoints()``).
    """
    configured = tuple(configured)
    process = psutil.Process()
    connections = getattr(process, "net_connections", process.connections)
    found: set[str] = set()
    try:
        sockets = connections(kind="inet")
    except psutil.Error:
        return []
    for conn in sockets:
        if not conn.laddr:
            continue
        if conn.type == socket.SOCK_STREAM and conn.status == psutil.CONN_LISTEN:
            protocol = "tcp"
        elif conn.type == socket.SOCK_DGRAM and not conn.raddr:
            protocol = "udp"
        else:
            continue
        host = f"[{conn.laddr.ip}]" if ":" in conn.laddr.ip else conn.laddr.ip
        found.add(_relabelled(f"{protocol}/{host}:{conn.laddr.port}", configured))
    return sorted(found)


def _check_endpoints(endpoints: list[str], verb: str) -> None:
    """ConfigError naming the first endpoint Zenoh cannot parse, and the form it takes."""
    for endpoint in endpoints:
        try:
            zenoh.Config().insert_json5("connect/endpoints", json.dumps([endpoint]))
        except zenoh.ZError as exc:
            raise ConfigError(
                f"bad endpoint {endpoint!r} to {verb}: write {ENDPOINT_FORM}"
            ) from exc


# How long a send that cannot progress (``CongestionControl.BLOCK``) waits before Zenoh
# closes the link, in microseconds.
_BLOCK_CLOSE_KEY = "transport/link/tx/queue/congestion_control/block/wait_before_close"


def _insert(conf: zenoh.Config, key: str, value: Any) -> None:
    _insert_raw(conf, key, json.dumps(value))


def _insert_raw(conf: zenoh.Config, key: str, raw: str) -> None:
    try:
        conf.insert_json5(key, raw)
    except zenoh.ZError as exc:
        raise ConfigError(f"bad Zenoh setting {key} = {raw}: {zenoh_message(exc)}") from exc


def _split(value: str) -> tuple[str, ...]:
    return tuple(part.strip() for part in value.split(",") if part.strip())


def _int(value: str, what: str) -> int:
    try:
        return int(value)
    except ValueError as exc:
        raise ConfigError(f"{what} must be an integer, got {value!r}") from exc


def endpoint_parts(endpoint: str) -> tuple[str, str, str]:
    """(protocol, host, port) of a Zenoh endpoint such as ``tcp/10.0.0.2:7447#iface=eth0``
    (its ``?``/``#`` options dropped); a part it lacks is ""."""
    proto, _, address = endpoint.partition("/")
    host, _, port = address.split("#", 1)[0].split("?", 1)[0].rpartition(":")
    return proto, host, port


def checked_endpoints(endpoints: Iterable[str], what: str, lowest: int = 1) -> tuple[str, ...]:
    """``endpoints`` as given, or ConfigError naming ``what`` (the flag, variable or deploy
    file line) for one Zenoh cannot parse or whose port is not a number in
    ``lowest``..65535 (Zenoh would only say the endpoint is bad); 0 is a port to listen on
    (any free one), not one to connect to."""
    out = tuple(endpoints)
    for endpoint in out:
        try:
            _check_endpoints([endpoint], "use")
        except ConfigError as exc:
            raise ConfigError(f"{what}: bad endpoint {endpoint!r}: write {ENDPOINT_FORM}") from exc
        proto, host, port = endpoint_parts(endpoint)
        inet = proto in ("tcp", "tls", "udp", "quic")
        # No ":" at all (``tcp/abc``) is no port: ``_check_endpoints`` names the form.
        number = port.isascii() and port.isdigit() and lowest <= int(port) < 65536
        if inet and host and not number:
            raise ConfigError(
                f"{what} {endpoint}: {port or 'no port'} is not a port number: use {lowest}..65535"
            )
    return out


def _port(value: str, what: str) -> int:
    """A TCP port number (1..65535), or ConfigError naming ``what``."""
    port = _int(value, what)
    if not 0 < port < 65536:
        raise ConfigError(f"{what}={value} is not a port number: use 1..65535")
    return port


def add_network_arguments(parser: argparse.ArgumentParser) -> None:
    """The connection flags every framegate command accepts."""
    group = parser.add_argument_group("network")
    group.add_argument(
        "--connect",
        "-e",
        action="append",
        metavar="ENDPOINT",
        help="Zenoh endpoint to connect to, e.g. tcp/10.0.0.2:7447 (repeatable)",
    )
    group.add_argument(
        "--listen",
        "-l",
        action="append",
        metavar="ENDPOINT",
        help="Zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)",
    )
    group.add_argument("--config", "-c", metavar="FILE", help="Zenoh JSON5 configuration file")
    group.add_argument(
        "--namespace",
        metavar="NAME",
        help=f"key prefix of all buffers (default {DEFAULT_NAMESPACE})",
    )
    group.add_argument(
        "--no-shm", action="store_true", help="disable Zenoh's shared-memory transport"
    )


def network_from_args(args: argparse.Namespace, base: NetworkConfig | None = None) -> NetworkConfig:
    """defaults (or ``base`` from a deploy file) → environment → flags."""
    return (base or NetworkConfig()).with_env().with_args(args)
