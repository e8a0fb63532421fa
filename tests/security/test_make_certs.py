"""make-certs.sh never replaces an existing CA, and issues from a CA whose key lives elsewhere."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from middleware import Node
from tests.helpers.timing import scaled
from tests.security.conftest import MAKE_CERTS, Certs, make_certs, start_router, stop_router


def _run(out: Path, *names: str, **env: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["bash", str(MAKE_CERTS), str(out), *names],
        capture_output=True,
        text=True,
        timeout=scaled(60),
        env={**os.environ, **env},
    )


def _verify(ca: Path, cert: Path) -> bool:
    done = subprocess.run(
        ["openssl", "verify", "-CAfile", str(ca), str(cert)], capture_output=True, text=True
    )
    return done.returncode == 0


@pytest.fixture
def offline_ca(tmp_path: Path) -> tuple[Path, Path]:
    """(certificate dir without ca.key, the CA key moved elsewhere), as the README advises."""
    out = tmp_path / "certs"
    make_certs(out, "camera", "cli")
    offline = tmp_path / "offline"
    offline.mkdir()
    shutil.move(out / "ca.key", offline / "ca.key")
    return out, offline / "ca.key"


def test_a_ca_without_its_key_is_never_replaced(offline_ca: tuple[Path, Path]) -> None:
    out, _key = offline_ca
    before = (out / "ca.pem").read_bytes()
    done = _run(out, "lidar")
    assert done.returncode == 1, done.stdout + done.stderr
    [line] = done.stderr.strip().splitlines()
    assert "ca.pem exists without ca.key" in line and "CA_KEY=PATH" in line
    assert (out / "ca.pem").read_bytes() == before
    assert not (out / "ca.key").exists() and not (out / "lidar.pem").exists()


def test_a_key_without_its_ca_certificate_is_refused(tmp_path: Path) -> None:
    out = tmp_path / "certs"
    make_certs(out, "camera")
    (out / "ca.pem").unlink()
    done = _run(out, "lidar")
    assert done.returncode == 1 and "ca.key exists without ca.pem" in done.stderr
    assert not (out / "ca.pem").exists()


def test_the_wrong_ca_key_is_refused(offline_ca: tuple[Path, Path], tmp_path: Path) -> None:
    out, _key = offline_ca
    other = tmp_path / "other"
    make_certs(other, "camera")
    done = _run(out, "lidar", CA_KEY=str(other / "ca.key"))
    assert done.returncode == 1 and "is not the key of" in done.stderr
    assert not (out / "lidar.pem").exists()


@pytest.mark.integration
def test_a_service_added_later_with_the_ca_key_elsewhere_connects(
    offline_ca: tuple[Path, Path],
) -> None:
    out, key = offline_ca
    before = (out / "ca.pem").read_bytes()
    done = _run(out, "detector", CA_KEY=str(key))
    assert done.returncode == 0, done.stdout + done.stderr
    assert (out / "ca.pem").read_bytes() == before and not (out / "ca.key").exists()
    assert _verify(out / "ca.pem", out / "detector.pem")
    assert "kept" in done.stdout  # the router's certificate is not reissued
    router = start_router(Certs(out, out))
    try:
        with Node("detector", router.net("detector")):
            pass  # the router (signed before) accepts the certificate issued now
    finally:
        stop_router(router)
