"""Mutual TLS: only clients with a certificate from the framegate CA reach the router."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from middleware import NetworkConfig, Node, TransportError
from tests.conftest import REPO, child_env, free_port
from tests.helpers.timing import scaled
from tests.security.conftest import (
    Certs,
    SecureRouter,
    derived_config,
    start_router,
    stop_router,
)

pytestmark = pytest.mark.integration

# Refused clients retry until their connect timeout; keep it short here.
_FAIL_FAST = {"connect/timeout_ms": 2000}


def _refused(net: NetworkConfig) -> str:
    started = time.monotonic()
    with pytest.raises(TransportError, match="cannot open a Zenoh session") as info:
        with Node(network=net):
            pass
    # Refused within the short connect timeout above, not Zenoh's default; the scaled bound
    # only catches a client that waits for ever.
    assert time.monotonic() - started < scaled(30)
    return str(info.value)


def test_client_with_a_certificate_from_the_ca_connects(secure_router: SecureRouter) -> None:
    with Node(network=secure_router.net("cli")) as cli:
        assert cli.live_services() == []
        assert cli.services() == []


def test_client_without_a_certificate_is_refused(
    secure_router: SecureRouter, certs: Certs, tmp_path: Path
) -> None:
    config = derived_config(
        certs.config("cli"),
        tmp_path / "no-cert.json5",
        {
            **_FAIL_FAST,
            "transport/link/tls/connect_certificate": None,
            "transport/link/tls/connect_private_key": None,
        },
    )
    _refused(secure_router.net("cli", config))


def test_client_with_a_certificate_from_a_rogue_ca_is_refused(
    secure_router: SecureRouter, certs: Certs, tmp_path: Path
) -> None:
    # It trusts the real CA (so it accepts the router) but presents a certificate with the
    # right common name signed by another CA.
    config = derived_config(
        certs.config("camera"),
        tmp_path / "rogue.json5",
        {
            **_FAIL_FAST,
            "transport/link/tls/connect_certificate": str(certs.rogue / "camera.pem"),
            "transport/link/tls/connect_private_key": str(certs.rogue / "camera.key"),
        },
    )
    _refused(secure_router.net("camera", config))


def test_plain_tcp_to_the_tls_port_is_refused(
    secure_router: SecureRouter, certs: Certs, tmp_path: Path
) -> None:
    config = derived_config(
        certs.config("cli"),
        tmp_path / "tcp.json5",
        {**_FAIL_FAST, "transport/link/protocols": ["tcp", "tls"]},
    )
    net = NetworkConfig(config_file=config, connect=(f"tcp/127.0.0.1:{secure_router.port}",))
    _refused(net)


def test_client_refuses_a_router_its_ca_did_not_sign(
    secure_router: SecureRouter, certs: Certs, tmp_path: Path
) -> None:
    # A man in the middle would present a certificate from its own CA.
    config = derived_config(
        certs.config("cli"),
        tmp_path / "other-ca.json5",
        {**_FAIL_FAST, "transport/link/tls/root_ca_certificate": str(certs.rogue / "ca.pem")},
    )
    _refused(secure_router.net("cli", config))


def test_router_does_not_open_a_plain_tcp_listener(certs: Certs) -> None:
    # Even when one is asked for by mistake: the profile allows TLS links only.
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "services.cli",
            "router",
            "--config",
            str(certs.config("router")),
            "--listen",
            f"tcp/127.0.0.1:{free_port()}",
        ],
        cwd=REPO,
        env=child_env(),
        capture_output=True,
        text=True,
        timeout=scaled(30),
    )
    assert done.returncode == 1
    assert "Unsupported protocol: tcp" in done.stderr


@pytest.mark.integration
def test_a_tls_router_says_it_listens_on_tls_not_tcp(certs: Certs) -> None:
    # The OS sees a TCP socket; the user asked for TLS and must read TLS.
    router = start_router(certs)
    try:
        assert router.proc.stdout is not None
        first = router.proc.stdout.readline().strip()
    finally:
        stop_router(router)
    assert first == f"router listening on tls/127.0.0.1:{router.port}", first
