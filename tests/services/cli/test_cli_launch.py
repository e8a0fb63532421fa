"""launch --check as data (the plan as JSON); a launch beside live services of its names."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from middleware import NetworkConfig, Node
from tests.conftest import REPO, child_env, free_port
from tests.helpers.raw_zenoh import open_session
from tests.helpers.timing import scaled


def _launch(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "services.cli", "launch", *args],
        cwd=REPO,
        env=env or child_env(),
        capture_output=True,
        text=True,
        timeout=scaled(120),
        check=False,
    )


def test_check_json_gives_each_process_with_its_command_and_starts_nothing() -> None:
    result = _launch("deploy/local.yaml", "--check", "--json")
    assert result.returncode == 0, result
    plan = json.loads(result.stdout)
    assert plan["started"] is False
    by_name = {p["name"]: p for p in plan["processes"]}
    assert sorted(by_name) == ["camera", "detector", "gyro", "mediator"]
    assert by_name["camera"]["command"][:5] == ["framegate", "run", "camera", "--name", "camera"]
    assert by_name["detector"]["type"] == "detector" and by_name["detector"]["restart"] is True


def test_check_of_a_file_of_several_hosts_checks_every_host_but_a_launch_picks_one() -> None:
    """`launch deploy/two-hosts.yaml --check` said "pick one with --host": the README's
    "--check validates the file" checked nothing of a two-host file without it."""
    text = _launch("deploy/two-hosts.yaml", "--check")
    assert text.returncode == 0, text
    assert "3 processes on host base" in text.stdout and "3 processes on host robot" in text.stdout
    assert text.stdout.endswith("ok: nothing started (--check of every host: base, robot)\n")
    plan = json.loads(_launch("deploy/two-hosts.yaml", "--check", "--json").stdout)
    assert {(p["name"], p["host"]) for p in plan["processes"]} == {
        ("base-router", "base"), ("mediator", "base"), ("detector", "base"),
        ("router", "robot"), ("camera", "robot"), ("gyro", "robot"),
    }  # fmt: skip
    started = _launch("deploy/two-hosts.yaml", "--duration", "1")  # a start must pick one
    assert started.returncode == 1 and "pick one with --host" in started.stderr, started


def test_json_without_check_is_one_line_and_exit_1() -> None:
    result = _launch("deploy/local.yaml", "--json")
    assert result.returncode == 1, result
    assert result.stderr.startswith("error: --json prints the plan of --check"), result
    assert len(result.stderr.splitlines()) == 1 and result.stdout == "", result


@pytest.mark.integration
def test_a_launch_beside_a_live_service_of_the_same_name_refuses_in_one_line() -> None:
    port = free_port()
    env = child_env()
    env["FRAMEGATE_LOCAL_PORT"] = str(port)
    with Node("camera", NetworkConfig(local_port=port)) as other:  # e.g. a demo's camera
        other.offer("images", kind="frame")
        result = _launch("deploy/local.yaml", "--duration", "5", env=env)
    assert result.returncode == 1, result
    assert result.stderr.startswith("error: service 'camera' is live already (pid "), result
    assert len(result.stderr.splitlines()) == 1 and "launching" not in result.stdout, result


@pytest.mark.integration
def test_a_bare_service_token_does_not_stop_a_launch(tmp_path: Path) -> None:
    """A peer holds the liveliness token ``framegate/@svc/camera`` and does not answer as
    ``camera``: the camera itself would start (with a warning), so the launch does too. It
    refused, "service 'camera' is live already (another process)", exit 1: any local
    process could keep every pipeline from launching."""
    port = free_port()
    env = child_env()
    env["FRAMEGATE_LOCAL_PORT"] = str(port)
    deploy = tmp_path / "gyro.yaml"
    deploy.write_text("version: 1\nservices:\n  camera:\n    type: gyro\n    args: {source: sim}\n")
    with open_session(f"tcp/127.0.0.1:{port}", listen=True) as rogue:
        token = rogue.liveliness().declare_token("framegate/@svc/camera")
        result = _launch(str(deploy), "--duration", "3", env=env)
        token.undeclare()
    assert result.returncode == 0, result
    assert "live already" not in result.stderr, result
    assert "does not answer as 'camera'" in result.stderr + result.stdout, result


def test_a_host_share_whose_router_cannot_listen_here_fails_check_and_starts_nothing(
    tmp_path: Path,
) -> None:
    # deploy/two-hosts.yaml's robot share on a machine that lacks the robot's address (the
    # base station, or a file whose hosts.robot.address was changed and the router's listen
    # was not): --check said "ok" and a launch restarted the router with backoff for ever.
    # 192.0.2.1 (TEST-NET-1) is no machine's address.
    deploy = tmp_path / "two.yaml"
    deploy.write_text(
        "version: 1\n"
        "hosts:\n"
        "  robot: {address: 192.0.2.1}\n"
        "  base: {address: 192.0.2.2}\n"
        "services:\n"
        "  router: {type: router, host: robot, network: {listen: [tcp/192.0.2.1:7447]}}\n"
        "  mediator: {host: base}\n"
    )
    message = (
        "cannot listen on tcp/192.0.2.1:7447: that address is not one of this machine's "
        "(is this machine host 'robot'?"
    )
    for extra in (("--check",), ("--duration", "5")):
        result = _launch(str(deploy), "--host", "robot", *extra)
        assert result.returncode == 1, result
        assert result.stderr.startswith(f"error: {deploy}: service 'router': {message}"), result
        assert len(result.stderr.splitlines()) == 1 and "launching" not in result.stdout, result
    # Each host's share checked in turn (no --host) is not this machine's: the file is valid.
    assert _launch(str(deploy), "--check").returncode == 0


def test_one_fixed_listen_port_for_several_processes_fails_check(tmp_path: Path) -> None:
    # `launch deploy/local.yaml --listen tcp/127.0.0.1:P` (or FRAMEGATE_LISTEN, or a
    # file-wide `network: {listen: ...}`) gave all four services the one port: --check said
    # "ok", and at the start three of them failed "Address already in use" and were
    # restarted for ever (a demo showed zeros).
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    message = f"would both listen on {endpoint}"
    flag = _launch("deploy/local.yaml", "--check", "--listen", endpoint)
    assert flag.returncode == 1, flag
    assert flag.stderr.startswith("error: deploy/local.yaml: services 'camera' and 'gyro' "), flag
    assert message in flag.stderr and "--listen or FRAMEGATE_LISTEN" in flag.stderr, flag
    assert len(flag.stderr.splitlines()) == 1, flag
    env = child_env()
    env["FRAMEGATE_LISTEN"] = endpoint
    assert message in _launch("deploy/local.yaml", "--check", env=env).stderr
    deploy = tmp_path / "wide.yaml"
    deploy.write_text(
        f"network: {{listen: [{endpoint}]}}\nservices:\n  camera: {{}}\n  gyro: {{}}\n"
    )
    in_file = _launch(str(deploy), "--check")
    assert in_file.returncode == 1 and message in in_file.stderr, in_file
    assert "--listen or FRAMEGATE_LISTEN" not in in_file.stderr, in_file
    # Port 0 is any free port, one per process: that is fine.
    assert _launch("deploy/local.yaml", "--check", "--listen", "tcp/127.0.0.1:0").returncode == 0


def test_a_zenoh_config_that_gives_every_process_one_port_fails_check(tmp_path: Path) -> None:
    # As --listen: FRAMEGATE_CONFIG (or --config) naming a fixed listen endpoint.
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = tmp_path / "peer.json5"
    config.write_text(f'{{mode: "peer", listen: {{endpoints: ["{endpoint}"]}}}}\n')
    result = _launch("deploy/local.yaml", "--check", "--config", str(config))
    assert result.returncode == 1, result
    assert f"would both listen on {endpoint} (the listen endpoints of" in result.stderr, result


def test_duration_counts_from_the_services_shared_start_not_the_launch() -> None:
    from services.cli.launch import run_seconds
    from services.launch import START_DELAY_S, load_deployment, process_specs

    now_ns = 1_000_000_000_000
    start_ns = now_ns + int(START_DELAY_S * 1e9)
    specs = process_specs(
        load_deployment(REPO / "deploy/local.yaml"), None, NetworkConfig(), start_at_ns=start_ns
    )
    assert run_seconds(2.0, specs, now_ns) == pytest.approx(START_DELAY_S + 2.0)
    assert run_seconds(2.0, specs, start_ns + 10**9) == pytest.approx(2.0)  # start has passed
    assert run_seconds(None, specs, now_ns) is None


def test_duration_help_says_it_counts_from_the_services_start() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "services.cli", "launch", "--help"],
        cwd=REPO,
        env=child_env(),
        capture_output=True,
        text=True,
        timeout=scaled(60),
        check=True,
    )
    assert "counted from their shared start" in " ".join(result.stdout.split())
