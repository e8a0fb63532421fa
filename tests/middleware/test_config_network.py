"""Network defaults: nothing listens beyond loopback unless asked; names are plain chunks."""

from __future__ import annotations

import argparse
import base64
import ipaddress
import json
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import psutil
import pytest
import zenoh

from middleware import ConfigError, NetworkConfig, Node, check_name
from middleware._config import listening_endpoints, zenoh_message
from tests.conftest import REPO, NodeProcess, child_env, free_port, wait_until
from tests.helpers.timing import scaled


@pytest.mark.parametrize("name", ["camera\n", "camera\r\n", "cam\x00", "cam\tera", "\ncamera"])
def test_check_name_refuses_control_characters(name: str) -> None:
    with pytest.raises(ConfigError, match="control characters"):
        check_name(name, "service")


def test_check_name_accepts_plain_names() -> None:
    assert check_name("camera-2.left_x", "service") == "camera-2.left_x"


def _listen(config: NetworkConfig) -> object:
    return json.loads(config.zenoh_configs()[0].get_json("listen/endpoints"))


def test_connect_alone_listens_on_loopback_not_every_interface() -> None:
    assert _listen(NetworkConfig(connect=("tcp/10.0.0.2:7447",))) == ["tcp/127.0.0.1:0"]


def test_an_explicit_listen_is_kept() -> None:
    wide = NetworkConfig(connect=("tcp/10.0.0.2:7447",), listen=("tcp/0.0.0.0:7447",))
    assert _listen(wide) == ["tcp/0.0.0.0:7447"]


def test_a_config_file_without_listen_endpoints_listens_on_loopback(tmp_path: Path) -> None:
    path = tmp_path / "peer.json5"
    path.write_text('{mode: "peer", connect: {endpoints: ["tcp/10.0.0.2:7447"]}}')
    assert _listen(NetworkConfig(config_file=path)) == ["tcp/127.0.0.1:0"]
    path.write_text('{mode: "router"}')
    assert _listen(NetworkConfig(config_file=path)) == ["tcp/127.0.0.1:7447"]


def _lease_ms(config: NetworkConfig) -> object:
    return json.loads(config.zenoh_configs()[0].get_json("transport/link/tx/lease"))


def test_a_config_file_without_a_lease_gets_ours_and_one_with_a_lease_decides(
    tmp_path: Path,
) -> None:
    # Peers believe a process alive for the lease it announces: Zenoh's default (10 s) let a
    # stopped flow-controlled subscriber hold its producer 10 s instead of 1 s.
    path = tmp_path / "peer.json5"
    path.write_text('{mode: "peer", connect: {endpoints: ["tcp/10.0.0.2:7447"]}}')
    assert _lease_ms(NetworkConfig(config_file=path)) == NetworkConfig().lease_ms == 1000
    path.write_text('{mode: "peer", transport: {link: {tx: {lease: 3000}}}}')
    assert _lease_ms(NetworkConfig(config_file=path)) == 3000


def test_a_config_file_that_names_listen_endpoints_decides(tmp_path: Path) -> None:
    path = tmp_path / "wide.json5"
    path.write_text('{mode: "peer", listen: {endpoints: ["tcp/0.0.0.0:0"]}}')
    assert _listen(NetworkConfig(config_file=path)) == ["tcp/0.0.0.0:0"]


def test_a_tls_only_config_file_gets_no_plain_tcp_listener(tmp_path: Path) -> None:
    path = tmp_path / "tls.json5"
    path.write_text('{mode: "peer", transport: {link: {protocols: ["tls"]}}}')
    assert _listen(NetworkConfig(config_file=path)) == []


def test_a_client_is_left_alone(tmp_path: Path) -> None:
    path = tmp_path / "client.json5"
    path.write_text('{mode: "client", connect: {endpoints: ["tcp/127.0.0.1:7447"]}}')
    default = json.loads(zenoh.Config().get_json("listen/endpoints"))
    assert _listen(NetworkConfig(config_file=path)) == default


def test_listening_endpoints_reports_the_actual_socket() -> None:
    port = free_port()
    with Node(network=NetworkConfig(listen=(f"tcp/127.0.0.1:{port}",))):
        assert f"tcp/127.0.0.1:{port}" in listening_endpoints()


# -- real processes ---------------------------------------------------------------------------


def _listeners(pid: int) -> list[str]:
    return [
        c.laddr.ip
        for c in psutil.Process(pid).net_connections(kind="inet")
        if c.status == psutil.CONN_LISTEN
    ]


@pytest.fixture
def spawn() -> Iterator[Callable[..., NodeProcess]]:
    started: list[NodeProcess] = []

    def start(name: str | None, *net_args: str) -> NodeProcess:
        process = NodeProcess(name, list(net_args))
        started.append(process)
        return process

    yield start
    for process in started:
        process.close()


@pytest.fixture
def router() -> Iterator[str]:
    """A ``framegate router`` on a loopback port; its endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    command = [sys.executable, "-m", "services.cli", "router", "--listen", endpoint]
    proc = subprocess.Popen(command, cwd=REPO, env=child_env(), stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and "router listening" in proc.stdout.readline()
        yield endpoint
    finally:
        proc.terminate()
        proc.wait(timeout=scaled(10))


def _offer_and_find(producer: NodeProcess, consumer: NodeProcess) -> None:
    assert producer.call("offer", buffer="data")["ok"]
    payload = base64.b64encode(b"x").decode()
    assert producer.call("put", buffer="data", t=1, payload=payload)["ok"]

    def found() -> bool:
        reply = consumer.call("query", target="src/data")
        return bool(reply["ok"] and reply["elements"])

    wait_until(found, 30, "the consumer to reach the producer")


@pytest.mark.integration
def test_a_service_given_only_connect_listens_on_loopback_only(
    spawn: Callable[..., NodeProcess], router: str
) -> None:
    producer = spawn("src", "--connect", router)
    consumer = spawn(None, "--connect", router)
    _offer_and_find(producer, consumer)  # peers still reach each other through a router
    listeners = _listeners(producer.proc.pid)
    assert listeners, "a peer listens on loopback so local peers can mesh"
    assert all(ipaddress.ip_address(ip).is_loopback for ip in listeners), listeners


@pytest.mark.integration
def test_peers_given_only_connect_mesh_through_a_loopback_hub(
    spawn: Callable[..., NodeProcess],
) -> None:
    # No router: a hub peer, and two spokes that must connect to each other directly
    # (peers do not forward), which they can because each listens on loopback.
    hub_endpoint = f"tcp/127.0.0.1:{free_port()}"
    spawn(None, "--listen", hub_endpoint)
    producer = spawn("src", "--connect", hub_endpoint)
    consumer = spawn(None, "--connect", hub_endpoint)
    _offer_and_find(producer, consumer)
    for process in (producer, consumer):
        ips = _listeners(process.proc.pid)
        assert ips and all(ipaddress.ip_address(ip).is_loopback for ip in ips), ips


def test_a_zenoh_error_reads_without_rust_source_paths(tmp_path: Path) -> None:
    path = tmp_path / "bad.json5"
    path.write_text('{ connect: { endpoints: ["bogus"] } }')
    with pytest.raises(zenoh.ZError) as info:
        zenoh.Config.from_file(str(path))
    assert zenoh_message(info.value) == (
        "Endpoints must be of the form <protocol>/<address>[?<metadata>][#<config>]: bogus "
        "(line 1, column 26)"
    )
    with pytest.raises(ConfigError, match=r"cannot read Zenoh config .*: Endpoints must") as bad:
        NetworkConfig(config_file=path).zenoh_configs()
    assert ".rs:" not in str(bad.value)


def test_a_config_file_set_by_the_environment_names_the_variable(tmp_path: Path) -> None:
    # FRAMEGATE_CONNECT=foo named its variable; FRAMEGATE_CONFIG=/nonexistent did not.
    missing = tmp_path / "nowhere.json5"
    net = NetworkConfig().with_env({"FRAMEGATE_CONFIG": str(missing)})
    with pytest.raises(
        ConfigError, match=rf"cannot read Zenoh config {missing} \(set by FRAMEGATE_CONFIG\): "
    ):
        net.check_files()
    # A --config flag outranks the variable, and its file is named as the flag's.
    flag = argparse.Namespace(config=str(missing))
    with pytest.raises(ConfigError, match=rf"cannot read Zenoh config {missing}: ") as bad:
        net.with_args(flag).check_files()
    assert "FRAMEGATE_CONFIG" not in str(bad.value)


def test_a_link_whose_peer_takes_nothing_closes_after_the_lease() -> None:
    """A send that cannot progress waits at most the lease before Zenoh closes the link, as
    a silent peer's is (Zenoh's own 5 s held a flow-controlled put that long)."""
    key = "transport/link/tx/queue/congestion_control/block/wait_before_close"
    for lease_ms in (1000, 3000):
        [conf] = NetworkConfig(connect=("tcp/10.0.0.2:7447",), lease_ms=lease_ms).zenoh_configs()
        assert json.loads(conf.get_json(key)) == lease_ms * 1000


def test_a_bad_namespace_names_the_variable_or_flag_that_set_it() -> None:
    # FRAMEGATE_NAMESPACE="bad ns" left in a shell said only "bad namespace name 'bad ns'".
    with pytest.raises(ConfigError, match=r"^FRAMEGATE_NAMESPACE: bad namespace name 'bad ns'"):
        NetworkConfig().with_env({"FRAMEGATE_NAMESPACE": "bad ns"})
    with pytest.raises(ConfigError, match=r"^--namespace: bad namespace name 'a/b'"):
        NetworkConfig().with_args(argparse.Namespace(namespace="a/b"))


def test_a_node_whose_config_names_a_missing_key_says_which_file_at_once(
    tmp_path: Path,
) -> None:
    # `ls --config cli.json5` with cli.key gone waited Zenoh's connect timeout (10 s) and
    # said "cannot open a Zenoh session (local port 7447): ... Timeout!", naming no file.
    config = tmp_path / "cli.json5"
    missing = tmp_path / "cli.key"
    config.write_text(
        '{mode: "client", connect: {endpoints: ["tls/localhost:1"], timeout_ms: 20000},'
        ' transport: {link: {protocols: ["tls"], tls: {'
        f' connect_private_key: "{missing}", enable_mtls: true}}}}}}}}\n'
    )
    with pytest.raises(ConfigError, match=rf"cannot read {missing}, the connect_private_key of "):
        Node(network=NetworkConfig(config_file=config))
