"""Deploy files and the supervisor."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import pytest

from middleware import ConfigError, NetworkConfig
from services.launch import (
    ProcessSpec,
    Supervisor,
    load_deployment,
    parse_deployment,
    process_specs,
    reaches_own_listener,
)
from services.nodes import service as service_type
from tests.conftest import REPO, wait_until
from tests.helpers.timing import scaled


def test_shipped_deploy_files_parse_and_plan() -> None:
    for path in (REPO / "deploy").glob("*.yaml"):
        deployment = load_deployment(path)
        for host in deployment.hosts:
            try:
                specs = process_specs(deployment, host, NetworkConfig(), text=path.read_text())
            except ConfigError as exc:
                # Its certificates are made by deploy/tls/make-certs.sh, not shipped.
                assert path.name == "secure.yaml" and "deploy/tls/certs/" in str(exc), exc
                continue
            assert all(spec.argv for spec in specs), path


def test_local_deploy_matches_the_paper_pipeline() -> None:
    deployment = load_deployment(REPO / "deploy" / "local.yaml")
    assert [s.type for s in deployment.services] == ["camera", "gyro", "mediator", "detector"]


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            "services:\n  camera:\n    tpye: camera\n",
            r"x\.yaml:3: unknown key 'tpye' in service 'camera' \(did you mean 'type'\?\)",
        ),
        ("sevices: {}\n", r"x\.yaml:1: unknown key 'sevices' in the top level"),
        (
            "services:\n  cam: {type: camra}\n",
            r"x\.yaml:2: .*unknown type 'camra' \(did you mean 'camera'\?\)",
        ),
        ("hosts: {a: {}, b: {}}\nservices:\n  camera: {}\n", r"x\.yaml:3: .*needs a 'host'"),
        ("services:\n  camera: {host: nowhere}\n", r"x\.yaml:2: .*host 'nowhere'"),
        ("version: 2\nservices: {}\n", r"x\.yaml:1: unsupported version 2; this framegate reads"),
        ("services: [1, 2]\n", r"x\.yaml:1: services must be a mapping"),
        ("services:\n  camera:\n    host:\n", r"^x\.yaml:3: host is empty; give it a value$"),
        (
            "services:\n  camera:\n    network: {config: }\n",
            r"^x\.yaml:3: config is empty; give it a value$",
        ),
        (
            "services:\n  camera:\n    args: {seed: {a: 1}}\n",
            r"^x\.yaml:3: expected a single value \(a word or a number\), got a mapping$",
        ),
        # One line, where the parser gave up (PyYAML's own message spans five).
        ("services:\n  camera: {args: {source: sim}\n", r"^x\.yaml:3:1: not valid YAML: [^\n]*$"),
        (
            "hosts: {robot: {}}\nservices:\n  camera: {host: robt}\n",
            r"x\.yaml:3: .*host 'robt'.*\(did you mean 'robot'\?\)",
        ),
        (
            "services:\n  camera: {network: {connect: [tcp/127.0.0.1:99999]}}\n",
            r"x\.yaml:2: connect tcp/127\.0\.0\.1:99999: 99999 is not a port number",
        ),
        (
            "services:\n  camera:\n    network:\n      connect:\n        - garbage\n",
            r"x\.yaml:5: connect: bad endpoint 'garbage'",
        ),
        (
            "network: {listen: tcp/127.0.0.1:0}\nservices:\n  camera: {}\n"
            "  gyro: {network: {listen: [tcp/127.0.0.1:x]}}\n",
            r"x\.yaml:4: listen tcp/127\.0\.0\.1:x: x is not a port number: use 0\.\.65535",
        ),
        ("", "empty"),
        ("services:\n  bad/name: {type: camera}\n", "bad service name"),
    ],
)
def test_deploy_mistakes_name_the_line_and_key(text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        parse_deployment(text, "x.yaml")


def test_unknown_service_option_names_its_line() -> None:
    text = "services:\n  camera:\n    args:\n      source: sim\n      sede: 3\n"
    deployment = parse_deployment(text, "x.yaml")
    with pytest.raises(ConfigError, match=r"x\.yaml:5: service 'camera' has no option 'sede'"):
        process_specs(deployment, None, NetworkConfig(), text=text)


def test_host_selection_and_network_layers() -> None:
    text = """
network: {connect: [tcp/10.0.0.1:7447]}
hosts:
  robot: {address: 10.0.0.2, network: {listen: [tcp/10.0.0.2:7447]}}
  base: {address: 10.0.0.1}
services:
  camera: {host: robot}
  detector: {host: base, network: {namespace: lab}}
"""
    deployment = parse_deployment(text, "x.yaml")
    with pytest.raises(ConfigError, match="names several hosts"):
        deployment.for_host(None)
    with pytest.raises(ConfigError, match="no host 'moon'"):
        deployment.for_host("moon")
    (camera,) = deployment.for_host("robot")
    net = deployment.network_for(camera)
    assert net.connect == ("tcp/10.0.0.1:7447",) and net.listen == ("tcp/10.0.0.2:7447",)
    (detector,) = deployment.for_host("base")
    assert deployment.network_for(detector).namespace == "lab"
    argv = process_specs(deployment, "base", NetworkConfig(), text=text)[0].argv
    assert "--namespace" in argv and "lab" in argv


@pytest.mark.parametrize(
    ("name", "hint"),
    [("local.yml", " (did you mean 'local.yaml'?)"), ("locl.yaml", " (did you mean 'local.yaml'?)"),
     ("nosuch.yaml", "")],
)  # fmt: skip
def test_a_missing_deploy_file_suggests_a_sibling_only_by_its_name(
    tmp_path: Path, name: str, hint: str
) -> None:
    # Compared with the suffix, every name was close: nosuch.yaml suggested ros2.yaml.
    for sibling in ("local.yaml", "ros2.yaml", "two-hosts.yaml"):
        (tmp_path / sibling).write_text("services: {}\n")
    with pytest.raises(ConfigError) as caught:
        load_deployment(tmp_path / name)
    assert str(caught.value).endswith("No such file or directory" + hint), caught.value


def test_the_readmes_deploy_file_starts_a_router_that_does_not_connect_to_itself() -> None:
    # The file-wide connect names the router every process reaches; the router got it
    # too, and connected to its own listen address.
    readme = (REPO / "README.md").read_text()
    text = readme.split("## Deploy files", 1)[1].split("```yaml\n", 1)[1].split("```", 1)[0]
    deployment = parse_deployment(text, "README.md")
    base = {p.name: p.argv for p in process_specs(deployment, "base", NetworkConfig(), text=text)}
    assert set(base) == {"router", "mediator", "detector"}
    router = base["router"]
    assert "--connect" not in router and "tcp/10.0.0.1:7447" in router
    assert "tcp/10.0.0.1:7447" in base["mediator"]
    robot = process_specs(deployment, "robot", NetworkConfig(), text=text)
    assert {p.name for p in robot} == {"camera", "gyro"}


def test_supervisor_restarts_a_crashing_process_and_stops_cleanly(tmp_path: Path) -> None:
    marker = tmp_path / "runs"
    script = (
        "import pathlib, sys, time\n"
        f"p = pathlib.Path({str(marker)!r})\n"
        "p.write_text(p.read_text() + 'x' if p.exists() else 'x')\n"
        "print('started', flush=True)\n"
        "sys.exit(3) if len(p.read_text()) < 3 else time.sleep(60)\n"
    )
    lines: list[str] = []
    supervisor = Supervisor(
        [ProcessSpec("crashy", (sys.executable, "-c", script))], colour=False, out=lines.append
    )
    supervisor.start()
    try:
        deadline = time.monotonic() + scaled(20)
        while time.monotonic() < deadline and supervisor.restarts()["crashy"] < 2:
            supervisor.poll()
            time.sleep(0.05)
        assert supervisor.restarts()["crashy"] == 2
        wait_until(lambda: any("exited with 3" in line for line in lines), 30, "the exit log")
        assert all(line.startswith("[crashy]") for line in lines)
        pid = wait_until(lambda: supervisor.pids()["crashy"], 30, "the third run")
    finally:
        started = time.monotonic()
        supervisor.stop()
    # Stopping within 2 s is the contract; the scaled bound only catches a stop that hangs.
    assert time.monotonic() - started < scaled(20)
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


@pytest.mark.integration
def test_a_service_whose_name_is_taken_exits_4_and_is_not_restarted_at_once(listen_net) -> None:
    """A copy of a running deploy file (or any second instance) must not storm the host
    with restarts that cannot succeed while the first instance lives."""
    from middleware import EXIT_NAME_TAKEN, Node

    with Node("gyro", listen_net) as first:
        first.offer("rates")
        lines: list[str] = []
        supervisor = Supervisor([_sim_gyro(listen_net)], colour=False, out=lines.append)
        supervisor.start()
        try:
            wait_until(
                lambda: (supervisor.poll(), supervisor.name_taken())[1] == ["gyro"],
                60,
                "the second gyro to give up",
            )
            # Polled on for a while: it is not started again.
            deadline = time.monotonic() + 1.0
            while time.monotonic() < deadline:
                supervisor.poll()
                time.sleep(0.05)
            assert supervisor.restarts()["gyro"] == 0 and supervisor.pids()["gyro"] is None
        finally:
            supervisor.stop()
    assert EXIT_NAME_TAKEN == 4
    assert any("already offered by pid" in line for line in lines), lines
    assert any("trying again every 10 s" in line for line in lines), lines


@pytest.mark.integration
def test_a_service_whose_name_was_taken_starts_once_the_other_instance_is_gone(
    listen_net,
) -> None:
    """Issue 30: a service given up when its name was taken (another instance run by hand,
    a peer answering in its name at the instant of a restart) stayed down for the rest of
    the launch after that instance had gone; it is tried again, slowly, and starts."""
    from middleware import Node

    lines: list[str] = []
    supervisor = Supervisor([_sim_gyro(listen_net)], colour=False, out=lines.append)
    try:
        with Node("gyro", listen_net) as first:
            first.offer("rates")
            supervisor.start()
            wait_until(
                lambda: (supervisor.poll(), supervisor.name_taken())[1] == ["gyro"],
                60,
                "the second gyro to find its name taken",
            )
        # The first instance is gone: the launcher's own gyro starts and stays up.
        with Node("watcher", listen_net) as watcher:

            def launched_gyro_offers() -> bool:
                supervisor.poll()
                pid = supervisor.pids()["gyro"]
                return any(
                    info.service == "gyro" and info.pid == pid
                    for info in watcher.services(timeout_s=1.0)
                )

            wait_until(launched_gyro_offers, scaled(60), "the launcher's gyro to start once free")
        assert supervisor.name_taken() == [] and supervisor.pids()["gyro"] is not None
        said = [line for line in lines if "trying again every 10 s" in line]
        assert len(said) == 1, lines  # said once, not at every retry
    finally:
        supervisor.stop()


def test_flags_outrank_the_deploy_file() -> None:
    from dataclasses import replace

    text = "network: {connect: [tcp/10.0.0.1:7447]}\nservices:\n  camera: {}\n"
    deployment = parse_deployment(text, "x.yaml")
    specs = process_specs(
        deployment, None, NetworkConfig(),
        override=lambda net: replace(net, connect=("tcp/127.0.0.1:9000",)),
    )  # fmt: skip
    argv = specs[0].argv
    assert "tcp/127.0.0.1:9000" in argv and "tcp/10.0.0.1:7447" not in argv


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            'services:\n  camera:\n    restart: "false"\n',
            r"x\.yaml:3: restart must be true or false",
        ),
        ("services:\n  camera:\n    restart: 0\n", r"x\.yaml:3: restart must be"),
        ('services:\n  "camera\\n": {type: camera}\n', r"x\.yaml:2: .*control character"),
        ('hosts:\n  "robot\\t": {}\nservices: {}\n', r"x\.yaml:2: .*control character"),
    ],
)
def test_deploy_booleans_and_names_are_strict(text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        parse_deployment(text, "x.yaml")


def test_yaml_booleans_set_restart() -> None:
    deployment = parse_deployment("services:\n  camera: {restart: false}\n", "x.yaml")
    assert deployment.services[0].restart is False


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ("{source: [sim, -e, tcp/10.0.0.1:7447]}", "has no option 'e'"),
        ("{source: [sim, tcp/10.0.0.1:7447]}", "does not take the value 'tcp/10.0.0.1:7447'"),
        ("{se: 3}", "has no option 'se'"),  # no abbreviations of --seed
        ("{connect: tcp/10.0.0.1:7447}", "network settings go under 'network'"),
        (
            "{source: prerendered, loop: yes please}",
            r"x\.yaml:3: service 'camera' takes true or false for 'loop', got 'yes please'",
        ),
    ],
)
def test_deploy_args_are_checked_short_long_and_exact(args: str, message: str) -> None:
    text = f"services:\n  camera:\n    args: {args}\n"
    deployment = parse_deployment(text, "x.yaml")
    with pytest.raises(ConfigError, match=message):
        process_specs(deployment, None, NetworkConfig(), text=text)


def test_deploy_args_are_checked_as_the_service_checks_its_flags() -> None:
    # --check said "ok" to a port that `framegate run ros2 --ros-connect` refuses.
    text = (
        "services:\n  ros2:\n    args:\n      image_in: /cam\n"
        "      ros_connect: tcp/localhost:99999\n"
    )
    deployment = parse_deployment(text, "x.yaml")
    with pytest.raises(
        ConfigError,
        match=r"x\.yaml:5: service 'ros2': --ros-connect tcp/localhost:99999: "
        r"99999 is not a port number",
    ):
        process_specs(deployment, None, NetworkConfig(), text=text)


def test_two_host_deploy_opens_no_wide_listener() -> None:
    path = REPO / "deploy" / "two-hosts.yaml"
    deployment = load_deployment(path)
    for host in deployment.hosts:
        for spec in process_specs(deployment, host, NetworkConfig(), text=path.read_text()):
            argv = list(spec.argv)
            listen = [argv[i + 1] for i, a in enumerate(argv) if a == "--listen"]
            # Each process says where it listens (else Zenoh's peer default is every
            # interface), and none says "everywhere".
            assert listen, spec.name
            assert not any("0.0.0.0" in e or "[::]" in e for e in listen), (spec.name, listen)


def test_a_router_without_listen_stays_on_loopback() -> None:
    deployment = parse_deployment("services:\n  router: {type: router}\n", "x.yaml")
    argv = process_specs(deployment, None, NetworkConfig())[0].argv
    assert argv[argv.index("--listen") + 1] == "tcp/127.0.0.1:7447"


@pytest.mark.parametrize(
    "path",
    [*sorted((REPO / "deploy").glob("*.yaml")), *sorted((REPO / "examples").glob("*.yaml"))],
    ids=lambda p: f"{p.parent.name}/{p.name}",
)
def test_no_shipped_deploy_file_renders_its_camera_live(path: Path) -> None:
    # Live rendering runs the camera at 4-5 of 15 frames/s on 2 cores: prerendered keeps it.
    for service in load_deployment(path).services:
        if service.type in ("camera", "gyro"):
            parser = argparse.ArgumentParser(add_help=False)
            service_type(service.type).add_arguments(parser)
            source = parser.parse_known_args(list(service.args))[0].source
            assert source != "sim", f"{path.name}: {service.name} renders live"


def test_an_empty_arg_value_is_left_unset_not_a_traceback() -> None:
    # `seed:` with nothing after it is YAML null: as if the key were not there.
    text = "services:\n  camera:\n    args: {source: prerendered, seed: }\n"
    (camera,) = parse_deployment(text, "x.yaml").services
    assert camera.args == ("--source", "prerendered")


@pytest.mark.parametrize(
    ("connect", "listen"),
    [
        ("tls/localhost:18067", "tls/[::]:18067"),
        ("tcp/localhost:18067", "tcp/127.0.0.1:18067"),
        ("tcp/127.0.0.1:18067", "tcp/0.0.0.0:18067"),
        ("tcp/[::1]:18067", "tcp/[::]:18067"),
        ("tcp/127.0.0.1:18067#iface=lo", "tcp/127.0.0.1:18067"),
    ],
)
def test_a_router_does_not_connect_to_its_own_listener_written_differently(
    connect: str, listen: str
) -> None:
    assert reaches_own_listener(connect, listen)
    text = (
        "version: 1\n"
        f"network: {{connect: ['{connect}']}}\n"
        f"services:\n  router: {{type: router, network: {{listen: ['{listen}']}}}}\n"
    )
    (router,) = process_specs(parse_deployment(text, "t.yaml"), None, NetworkConfig(), text=text)
    assert "--connect" not in router.argv, router.argv


@pytest.mark.parametrize(
    ("connect", "listen"),
    [
        ("tcp/localhost:18068", "tcp/127.0.0.1:18067"),  # another port
        ("tls/localhost:18067", "tcp/127.0.0.1:18067"),  # another protocol
        ("tcp/192.0.2.7:18067", "tcp/0.0.0.0:18067"),  # an address this machine lacks
        ("tcp/127.0.0.2:18067", "tcp/127.0.0.1:18067"),  # another loopback address
    ],
)
def test_a_router_keeps_a_connect_that_reaches_another_listener(connect: str, listen: str) -> None:
    assert not reaches_own_listener(connect, listen)


def _sim_gyro(net: NetworkConfig) -> ProcessSpec:
    """A simulated gyro named ``gyro`` that connects to ``net``'s listen endpoint."""
    argv = (
        sys.executable, "-m", "services.cli", "run", "gyro", "--source", "sim",
        "--connect", net.listen[0],
    )  # fmt: skip
    return ProcessSpec("gyro", argv)
