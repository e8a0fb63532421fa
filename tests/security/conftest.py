"""Certificates from deploy/tls/make-certs.sh and a mutual-TLS router with access control."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import zenoh

from middleware import FramegateError, NetworkConfig, Node
from tests.conftest import REPO, child_env, free_port, wait_until
from tests.helpers.timing import scaled

MAKE_CERTS = REPO / "deploy" / "tls" / "make-certs.sh"
# The roles of deploy/secure-router.json5 plus one certificate the router knows nothing about.
NAMES = ("camera", "gyro", "mediator", "detector", "cli", "intruder")


@dataclass(frozen=True)
class Certs:
    """Output of make-certs.sh: DIR/NAME.pem, .key and .json5 per name, plus a rogue CA."""

    dir: Path
    rogue: Path

    def config(self, name: str) -> Path:
        return self.dir / f"{name}.json5"


def make_certs(out: Path, *names: str) -> None:
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed: cannot generate test certificates")
    done = subprocess.run(
        ["bash", str(MAKE_CERTS), str(out), *names],
        capture_output=True,
        text=True,
        timeout=scaled(60),
    )
    assert done.returncode == 0, done.stdout + done.stderr


@pytest.fixture(scope="session")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Certs:
    root = tmp_path_factory.mktemp("tls")
    make_certs(root / "certs", *NAMES)
    # Another CA entirely: its certificates carry the right names but nobody's trust.
    make_certs(root / "rogue", "camera", "cli")
    return Certs(root / "certs", root / "rogue")


def derived_config(base: Path, out: Path, settings: dict[str, Any]) -> Path:
    """``base`` with some keys changed (``None`` clears one), written as JSON for --config."""
    conf = zenoh.Config.from_file(str(base))
    for key, value in settings.items():
        conf.insert_json5(key, json.dumps(value))
    out.write_text(str(conf))
    return out


@dataclass
class SecureRouter:
    """``framegate router`` with the secure profile, on a free loopback port."""

    proc: subprocess.Popen[str]
    port: int
    certs: Certs

    @property
    def endpoint(self) -> str:
        return f"tls/localhost:{self.port}"

    def net(self, name: str, config: Path | None = None) -> NetworkConfig:
        """How the process with certificate ``name`` connects (its make-certs.sh config)."""
        return NetworkConfig(
            config_file=config or self.certs.config(name), connect=(self.endpoint,)
        )

    def args(self, name: str) -> list[str]:
        return ["--config", str(self.certs.config(name)), "--connect", self.endpoint]


def start_router(certs: Certs, config: Path | None = None) -> SecureRouter:
    port = free_port()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.cli",
            "router",
            "--config",
            str(config or certs.config("router")),
            "--listen",
            f"tls/127.0.0.1:{port}",
        ],
        cwd=REPO,
        env=child_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    router = SecureRouter(proc, port, certs)

    def reachable() -> bool:
        assert proc.poll() is None, f"router exited: {proc.communicate()[0]}"
        try:
            with Node(network=router.net("cli")):
                return True
        except FramegateError:
            return False

    wait_until(reachable, 30, "the secure router to accept a cli certificate")
    return router


def stop_router(router: SecureRouter) -> None:
    router.proc.terminate()
    try:
        router.proc.wait(timeout=scaled(10))
    except subprocess.TimeoutExpired:
        router.proc.kill()
        router.proc.wait()


@pytest.fixture(scope="module")
def secure_router(certs: Certs) -> Iterator[SecureRouter]:
    """One router per test module; each test's processes leave with the test."""
    router = start_router(certs)
    yield router
    stop_router(router)
