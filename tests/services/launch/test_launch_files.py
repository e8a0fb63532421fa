"""``launch`` (and ``launch --check``) read every file a deploy file names before anything
starts: Zenoh configs and the certificates in them, camera descriptions, replayed datasets."""

from __future__ import annotations

import signal
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from middleware import ConfigError, NetworkConfig
from services.launch import load_deployment, parse_deployment, process_specs
from tests.conftest import REPO, child_env, free_port, wait_until

_TLS_CONFIG = """{
  mode: "client",
  transport: { link: { tls: {
    root_ca_certificate: "%(dir)s/ca.pem",
    connect_certificate: "%(dir)s/camera.pem",
    connect_private_key: "%(dir)s/camera.key",
  } } },
}
"""


def _specs(text: str) -> None:
    process_specs(parse_deployment(text, "d.yaml"), None, NetworkConfig(), text=text)


def test_a_missing_zenoh_config_is_named(tmp_path: Path) -> None:
    missing = tmp_path / "nowhere.json5"
    text = f"services:\n  gyro:\n    network: {{config: {missing}}}\n"
    with pytest.raises(
        ConfigError, match=rf"d\.yaml:3: service 'gyro': cannot read Zenoh config {missing}"
    ):
        _specs(text)


@pytest.mark.parametrize(
    ("text", "line"),
    [
        ("services:\n  gyro:\n    network: {config: %s}\n", 3),
        ("network:\n  config: %s\nservices:\n  gyro: {}\n", 2),
        (
            "network: {config: /elsewhere.json5}\nhosts:\n  local:\n    address: 127.0.0.1\n"
            "    network: {config: %s}\nservices:\n  gyro: {}\n",
            5,
        ),
    ],
)
def test_a_missing_zenoh_config_names_the_line_that_gives_it(
    tmp_path: Path, text: str, line: int
) -> None:
    """As every other mistake in a deploy file: it said `d.yaml: service 'gyro': cannot read
    Zenoh config ...` with no line (deploy/secure.yaml before its certificates are made)."""
    missing = tmp_path / "nowhere.json5"
    with pytest.raises(ConfigError, match=rf"^d\.yaml:{line}: service 'gyro': cannot read Zenoh"):
        _specs(text % missing)


def test_a_missing_zenoh_config_named_by_a_variable_gets_no_line_of_the_file(
    tmp_path: Path,
) -> None:
    text = "services:\n  gyro:\n    network: {config: /in-the-file.json5}\n"
    missing = tmp_path / "nowhere.json5"
    with pytest.raises(ConfigError, match=rf"^d\.yaml: service 'gyro': cannot read .*{missing}"):
        process_specs(
            parse_deployment(text, "d.yaml"), None, NetworkConfig(), text=text,
            override=lambda net: replace(net, config_file=missing),
        )  # fmt: skip


def test_a_relative_path_missing_here_says_where_to_run_launch_from(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # As deploy/two-hosts.yaml launched from outside the repository: its router config
    # path is relative to the repository root.
    project = tmp_path / "project"
    (project / "deploy").mkdir(parents=True)
    (project / "deploy" / "router.json5").write_text("{}\n")
    deploy = project / "deploy" / "hosts.yaml"
    text = "services:\n  hub:\n    type: router\n    network: {config: deploy/router.json5}\n"
    deploy.write_text(text)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    with pytest.raises(ConfigError) as caught:
        process_specs(load_deployment(deploy), None, NetworkConfig(), text=text)
    assert str(caught.value).endswith(
        f"(relative paths are taken from the current directory, {elsewhere}; "
        f"it is in {project.resolve()}: run launch from there)"
    ), caught.value
    monkeypatch.chdir(project)
    process_specs(load_deployment(deploy), None, NetworkConfig(), text=text)


@pytest.mark.parametrize("absent", ["ca.pem", "camera.pem", "camera.key"])
def test_a_certificate_a_zenoh_config_names_must_exist(tmp_path: Path, absent: str) -> None:
    for name in ("ca.pem", "camera.pem", "camera.key"):
        if name != absent:
            (tmp_path / name).write_text("x")
    config = tmp_path / "camera.json5"
    config.write_text(_TLS_CONFIG % {"dir": tmp_path})
    text = f"services:\n  camera:\n    args: {{source: sim}}\n    network: {{config: {config}}}\n"
    with pytest.raises(
        ConfigError, match=rf"cannot read {tmp_path / absent}, the \w+ of Zenoh config"
    ):
        _specs(text)


def test_a_config_with_every_certificate_passes(tmp_path: Path) -> None:
    for name in ("ca.pem", "camera.pem", "camera.key"):
        (tmp_path / name).write_text("x")
    config = tmp_path / "camera.json5"
    config.write_text(_TLS_CONFIG % {"dir": tmp_path})
    _specs(f"services:\n  camera:\n    args: {{source: sim}}\n    network: {{config: {config}}}\n")


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            "{source: device, path: '0', camera_xml: /no/cam.xml}",
            r"cannot read camera description /no/cam\.xml",
        ),
        ("{source: replay, path: /no/dataset}", r"dataset /no/dataset"),
        ("{source: device, path: /dev/no-video9}", r"video device /dev/no-video9 does not exist"),
        # Only a device reads it: elsewhere it would be silently ignored.
        ("{source: prerendered, camera_xml: /no/cam.xml}", r"--camera-xml describes a device"),
    ],
)
def test_a_file_a_service_argument_names_must_be_readable(args: str, message: str) -> None:
    with pytest.raises(ConfigError, match=rf"d\.yaml:3: service 'camera': {message}"):
        _specs(f"services:\n  camera:\n    args: {args}\n")


def test_a_camera_description_that_is_no_camera_xml_is_refused(tmp_path: Path) -> None:
    bad = tmp_path / "cam.xml"
    bad.write_text("<not-metadata/>")
    text = f"services:\n  camera:\n    args: {{source: device, path: '0', camera_xml: {bad}}}\n"
    with pytest.raises(ConfigError, match=rf"camera description {bad}: "):
        _specs(text)


def test_a_ros2_side_config_must_exist() -> None:
    text = (
        "services:\n  ros2:\n    args: {ros_config: /no/ros.json5, image_in: /camera/image_raw}\n"
    )
    with pytest.raises(
        ConfigError, match=r"service 'ros2': cannot read Zenoh config /no/ros\.json5"
    ):
        _specs(text)


def _check_secure(deploy: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """``launch DEPLOY --check`` run in ``cwd``: it must fail (the certificates are made, not
    shipped)."""
    result = subprocess.run(
        [sys.executable, "-m", "services.cli", "launch", deploy, "--check"],
        cwd=cwd,
        env=child_env(),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 1, result
    return result


def test_check_of_the_secure_deploy_file_without_its_certificates_fails_in_one_line(
    tmp_path: Path,
) -> None:
    # The repository ships no certificates (make-certs.sh makes them): --check must say so.
    if (REPO / "deploy" / "tls" / "certs").exists():
        pytest.skip("certificates were generated in this checkout")
    result = _check_secure("deploy/secure.yaml", REPO)
    assert result.stdout == "", result
    assert result.stderr.startswith(
        "error: deploy/secure.yaml:16: service 'router': cannot read"
    ), result
    assert result.stderr.count("\n") == 1, result
    assert "make the certificates first: deploy/tls/make-certs.sh deploy/tls/certs" in (
        result.stderr
    ), result


@pytest.mark.integration
def test_launch_check_of_a_secure_file_elsewhere_says_where_to_make_certificates(
    tmp_path: Path,
) -> None:
    # From another directory the relative certificate paths name nothing there: the line
    # says where the script is and to launch from that directory.
    if (REPO / "deploy" / "tls" / "certs").exists():
        pytest.skip("certificates were generated in this checkout")
    result = _check_secure(str(REPO / "deploy" / "secure.yaml"), tmp_path)
    assert result.stderr.count("\n") == 1, result
    assert (
        f"make the certificates first: cd {REPO} && deploy/tls/make-certs.sh deploy/tls/certs, "
        "and run launch from there" in result.stderr
    ), result


@pytest.mark.integration
def test_launch_renders_a_prerendered_approach_first_and_a_stop_there_starts_nothing(
    tmp_path: Path,
) -> None:
    cache = tmp_path / "cache"
    deploy = tmp_path / "d.yaml"
    deploy.write_text(
        f"services:\n  camera:\n    args: {{source: prerendered, seed: 5, path: {cache}}}\n"
    )
    env = child_env()
    env["FRAMEGATE_LOCAL_PORT"] = str(free_port())
    env["FRAMEGATE_RUNTIME_DIR"] = str(tmp_path / "run")
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "launch", str(deploy)],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()  # before any service starts: the one-time render
        assert line.startswith(f"rendering the approach once (cached in {cache})"), line
        wait_until(lambda: any(cache.glob("*.partial-*")), 300, "the render to begin")
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, (out, err)
    assert "launching" not in out, out
    assert not list(cache.glob("*.partial-*")), "a stopped render leaves no partial directory"


def test_a_deploy_file_that_is_no_text_is_one_error(tmp_path: Path) -> None:
    """A recording or an image given where a deploy file goes (not UTF-8)."""
    binary = tmp_path / "run.mcap"
    binary.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)))
    with pytest.raises(ConfigError, match=r"run\.mcap is no deploy file: not text"):
        load_deployment(binary)


def test_a_deploy_file_with_no_services_is_refused_in_one_line(tmp_path: Path) -> None:
    """`services: {}` passed `--check` ("0 processes ... ok"), and `launch` printed
    `launching  (Ctrl-C stops everything)` and then waited, running nothing."""
    with pytest.raises(ConfigError, match=r"^d\.yaml:2: services is empty; list the services"):
        parse_deployment("version: 1\nservices: {}\n", "d.yaml")


def test_launching_a_host_with_no_services_is_refused_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`launch FILE --host b` where every service is on host a printed `launching  (Ctrl-C
    stops everything)` and waited, running nothing."""
    from services.cli import main

    deploy = tmp_path / "d.yaml"
    deploy.write_text(
        "version: 1\nhosts:\n  a: {address: 10.0.0.1}\n  b: {address: 10.0.0.2}\n"
        "services:\n  camera: {host: a}\n"
    )
    assert main(["launch", str(deploy), "--host", "b", "--duration", "1"]) == 1
    out, err = capsys.readouterr()
    assert out == ""
    assert err == f"error: {deploy}: no service runs on host 'b'; nothing to launch here\n"
