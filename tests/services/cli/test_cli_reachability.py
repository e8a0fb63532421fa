"""``ls`` tells "nothing answered" (exit 1) from "nothing is live" (exit 0), as ``info`` does,
and a port is checked as a port wherever one is given."""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from middleware import DataObject, Node, Retention, make_metadata
from services.tools.bag import BagWriter
from tests.conftest import REPO, child_env, free_port, run_framegate, start_framegate
from tests.services.cli.conftest import ABSENCE_TIMEOUT_S, Cli

pytestmark = pytest.mark.integration

TIMEOUT_S = 180.0


def _framegate(*argv: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return run_framegate(*argv, env=env, timeout_s=TIMEOUT_S)


@pytest.fixture
def mute_endpoint() -> Iterator[str]:
    """A TCP port that accepts connections and never speaks Zenoh (a host behind a proxy, a
    wrong service on the port): a TCP connect alone cannot tell it from a router."""
    server = socket.create_server(("127.0.0.1", 0))
    held: list[socket.socket] = []

    def accept() -> None:
        while True:
            try:
                conn, _ = server.accept()
            except OSError:
                return
            held.append(conn)

    threading.Thread(target=accept, daemon=True).start()
    yield f"tcp/127.0.0.1:{server.getsockname()[1]}"
    server.close()
    for conn in held:
        conn.close()


def test_ls_where_nothing_answers_is_an_error_like_info(mute_endpoint: str) -> None:
    # At once: each waits out its connection attempts to the mute endpoint (seconds each).
    with ThreadPoolExecutor() as pool:
        results = pool.map(
            lambda argv: _framegate(*argv, "--connect", mute_endpoint, "--timeout", "1"),
            (["ls"], ["info", "camera/images"]),
        )
    for result in results:
        assert result.returncode == 1, result
        assert result.stderr.startswith("error: nothing answered via " + mute_endpoint), result
        assert result.stderr.count("\n") == 1 and not result.stdout, result


def test_ls_of_a_refused_endpoint_names_it() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    result = _framegate("ls", "--connect", endpoint)
    assert result.returncode == 1, result
    assert f"error: cannot reach {endpoint}" in result.stderr, result


def test_ls_of_a_live_router_with_no_services_is_an_empty_answer() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = start_framegate(["router", "--listen", endpoint], local_port=free_port())
    try:
        assert router.stdout is not None
        assert "router listening" in router.stdout.readline()
        result = _framegate("ls", "--connect", endpoint)
        assert result.returncode == 0, result
        assert result.stdout.startswith(f"no live services via {endpoint}"), result
    finally:
        router.terminate()
        router.communicate(timeout=TIMEOUT_S)


def test_nothing_live_in_a_namespace_names_it_and_where_services_are(
    cli: Cli, service: Node
) -> None:
    # A FRAMEGATE_NAMESPACE left set hid every service behind "is the service running and
    # is --connect right?", though the rendezvous answered.
    service.offer("images", kind="frame")
    listed, info = cli.run_many(
        [
            ("ls", "--namespace", "other"),
            ("info", "cam/images", "--namespace", "other", "--timeout", str(ABSENCE_TIMEOUT_S)),
        ]
    )
    assert listed.returncode == 0, listed.describe()
    assert info.returncode == 1, info.describe()
    assert "in namespace 'other'" in listed.stdout, listed.describe()
    assert "in namespace 'other'" in info.stderr, info.describe()
    for said in (listed.stdout, info.stderr):
        assert (
            "services are live under namespace 'framegate' (cam): pass --namespace framegate"
            in said
        )


@pytest.mark.parametrize("value", ["99999", "0", "-1"])
def test_a_local_port_that_is_no_port_is_one_line_naming_the_variable(value: str) -> None:
    env = child_env()
    env["FRAMEGATE_LOCAL_PORT"] = value
    result = _framegate("ls", env=env)
    assert result.returncode == 1, result
    assert (
        result.stderr == f"error: FRAMEGATE_LOCAL_PORT={value} is not a port number: use 1..65535\n"
    )


def test_a_connect_port_that_is_no_port_is_one_line_naming_the_flag_or_variable() -> None:
    result = _framegate("ls", "--connect", "tcp/127.0.0.1:99999")
    assert result.returncode == 1, result
    assert result.stderr == (
        "error: --connect tcp/127.0.0.1:99999: 99999 is not a port number: use 1..65535\n"
    ), result
    env = child_env()
    env["FRAMEGATE_CONNECT"] = "tcp/127.0.0.1:0"  # 0 is a port to listen on, not to reach
    result = _framegate("ls", env=env)
    assert result.returncode == 1, result
    assert result.stderr.startswith("error: FRAMEGATE_CONNECT tcp/127.0.0.1:0: 0 is not"), result
    result = _framegate("ls", "--listen", "tcp/127.0.0.1:70000")
    assert "error: --listen tcp/127.0.0.1:70000: 70000 is not a port number: use 0..65535" in (
        result.stderr
    ), result


def test_router_listens_on_the_rendezvous_port_the_environment_names() -> None:
    port = free_port()
    router = start_framegate(["router"], local_port=port)  # FRAMEGATE_LOCAL_PORT=port
    try:
        assert router.stdout is not None
        line = router.stdout.readline()
        assert line == f"router listening on tcp/127.0.0.1:{port}\n", line
        socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT_S).close()
    finally:
        router.terminate()
        router.communicate(timeout=TIMEOUT_S)


def test_a_second_view_on_a_taken_port_is_one_line_naming_the_flag() -> None:
    env = child_env()
    env["FRAMEGATE_VIEW_PORT"] = str(free_port())
    env["FRAMEGATE_LOCAL_PORT"] = str(free_port())
    first = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "view"],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        assert first.stdout is not None
        line = first.stdout.readline()
        assert line.startswith(f"serving Foxglove on ws://127.0.0.1:{env['FRAMEGATE_VIEW_PORT']}")
        second = _framegate("view", env=env)
        assert second.returncode == 1, second
        assert second.stderr.count("\n") == 1, second
        assert "the port is taken" in second.stderr and "--port" in second.stderr, second
    finally:
        first.terminate()
        first.communicate(timeout=TIMEOUT_S)


def test_a_view_on_an_address_this_machine_lacks_is_one_line_naming_the_flag() -> None:
    # It was the Foxglove SDK's text: `FoxgloveError: Failed to bind port ... (os error 99)`.
    env = child_env()
    env["FRAMEGATE_LOCAL_PORT"] = str(free_port())
    result = _framegate("view", "--host", "192.0.2.1", "--port", str(free_port()), env=env)
    assert result.returncode == 1, result
    assert result.stderr.count("\n") == 1, result
    assert "not one of this machine's" in result.stderr and "--host" in result.stderr, result


def test_a_router_on_a_taken_port_is_one_line_naming_the_flag(mute_endpoint: str) -> None:
    result = _framegate("router", "--listen", mute_endpoint)
    assert result.returncode == 1, result
    assert result.stderr.count("\n") == 1, result
    assert f"cannot listen on {mute_endpoint}: the port is already in use" in result.stderr
    assert "--listen" in result.stderr and "FRAMEGATE_LOCAL_PORT" in result.stderr, result


def test_record_all_where_nothing_answers_is_an_error_naming_the_endpoint(
    mute_endpoint: str, tmp_path: Path
) -> None:
    out = tmp_path / "x.mcap"
    result = _framegate(
        "record", "--all", "-o", str(out), "--connect", mute_endpoint, "--timeout", "1"
    )
    assert result.returncode == 1, result
    assert result.stderr.startswith("error: nothing answered via " + mute_endpoint), result


def test_view_of_a_refused_endpoint_warns_and_keeps_waiting_for_it() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"  # nothing listens there
    env = child_env()
    env["FRAMEGATE_VIEW_PORT"] = str(free_port())
    result = _framegate("view", "--connect", endpoint, "--duration", "1", env=env)
    assert result.returncode == 0, result  # a viewer may start before the robot
    assert f"warning: cannot reach {endpoint} (" in result.stderr, result


def test_pub_to_a_refused_endpoint_warns_and_publishes_anyway() -> None:
    """As `ros2 topic pub`, it publishes with nobody listening; but "published" alone hid
    that the --connect endpoint refused every connection."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"  # nothing listens there
    result = _framegate(
        "pub", "t/x", "--kind", "generic", "--connect", endpoint, "--linger", "0",
        "--listen", f"tcp/127.0.0.1:{free_port()}",
    )  # fmt: skip
    assert result.returncode == 0, result
    assert f"warning: cannot reach {endpoint} (" in result.stderr, result
    assert "nobody there gets these" in result.stderr, result


def test_nothing_live_on_the_rendezvous_names_its_port_and_the_variable() -> None:
    """With no --connect given, "is --connect right?" pointed away from the usual cause: a
    FRAMEGATE_LOCAL_PORT set in one shell and not in the other."""
    env = child_env()
    port = free_port()
    env["FRAMEGATE_LOCAL_PORT"] = str(port)
    result = _framegate("info", "camera/images", "--timeout", "1", env=env)
    assert result.returncode == 1, result
    assert result.stderr.count("\n") == 1, result
    assert (
        f"on this host with the same rendezvous port ({port}; FRAMEGATE_LOCAL_PORT sets it), "
        "or on another host (then --connect to it)?"
    ) in result.stderr, result


def test_a_router_on_an_address_this_machine_lacks_is_one_line_naming_it() -> None:
    # 192.0.2.1 (TEST-NET-1) is no machine's address: as deploy/two-hosts.yaml's robot
    # router started with --host robot on the base station.
    endpoint = f"tcp/192.0.2.1:{free_port()}"
    result = _framegate("router", "--listen", endpoint, "--listen", "tcp/127.0.0.1:0")
    assert result.returncode == 1, result
    assert result.stderr.count("\n") == 1, result
    assert f"cannot listen on {endpoint}: that address is not one of this machine's" in (
        result.stderr
    ), result


def test_play_to_a_refused_endpoint_warns_and_plays_anyway(tmp_path: Path) -> None:
    """As `pub`: "offering ... from FILE" alone hid that the --connect endpoint refused every
    connection, so nobody there could get what was played."""
    bag = tmp_path / "one.mcap"
    with BagWriter(bag) as writer:
        writer.add_buffer("t", "x", kind="generic", retention=Retention())
        writer.write("t/x", DataObject(10**9, b"x", make_metadata("generic", 10**9)))
    endpoint = f"tcp/127.0.0.1:{free_port()}"  # nothing listens there
    result = _framegate(
        "play", str(bag), "--exit-when-done", "--connect", endpoint,
        "--listen", f"tcp/127.0.0.1:{free_port()}",
    )  # fmt: skip
    assert result.returncode == 0, result
    assert f"warning: cannot reach {endpoint} (" in result.stderr, result
    assert "nobody there gets what is played" in result.stderr, result
