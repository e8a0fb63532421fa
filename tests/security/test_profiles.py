"""The secure profile's files: certificates, rendered configs and the access-control table."""

from __future__ import annotations

import json
import shutil
import stat
import subprocess
from pathlib import Path

import pytest
import yaml
import zenoh

from tests.conftest import REPO
from tests.security.conftest import MAKE_CERTS, NAMES, Certs


def _subject(cert: Path) -> str:
    done = subprocess.run(
        ["openssl", "x509", "-in", str(cert), "-noout", "-subject", "-nameopt", "sep_multiline"],
        capture_output=True,
        text=True,
        check=True,
    )
    return done.stdout


def test_each_certificate_names_its_service_and_keys_are_private(certs: Certs) -> None:
    for name in NAMES:
        assert f"CN={name}" in _subject(certs.dir / f"{name}.pem")
        mode = stat.S_IMODE((certs.dir / f"{name}.key").stat().st_mode)
        assert mode == 0o600, f"{name}.key is {oct(mode)}"
    verify = subprocess.run(
        ["openssl", "verify", "-CAfile", str(certs.dir / "ca.pem"), str(certs.dir / "cli.pem")],
        capture_output=True,
        text=True,
    )
    assert verify.returncode == 0, verify.stderr


def test_rendered_configs_load_and_point_at_their_own_certificate(certs: Certs) -> None:
    for name in (*NAMES, "router"):
        conf = json.loads(str(zenoh.Config.from_file(str(certs.config(name)))))
        tls = conf["transport"]["link"]["tls"]
        assert tls["enable_mtls"] is True
        assert Path(tls["root_ca_certificate"]) == certs.dir / "ca.pem"
        side = "listen" if name == "router" else "connect"
        assert Path(tls[f"{side}_certificate"]) == certs.dir / f"{name}.pem"
        assert Path(tls[f"{side}_private_key"]) == certs.dir / f"{name}.key"
        assert conf["mode"] == ("router" if name == "router" else "client")


def test_make_certs_refuses_a_name_that_is_not_a_plain_service_name(tmp_path: Path) -> None:
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed")
    done = subprocess.run(
        ["bash", str(MAKE_CERTS), str(tmp_path), "cam/era"], capture_output=True, text=True
    )
    assert done.returncode == 2
    assert "bad name 'cam/era'" in done.stderr


def test_access_control_table_is_consistent() -> None:
    acl = json.loads(str(zenoh.Config.from_file(str(REPO / "deploy" / "secure-router.json5"))))[
        "access_control"
    ]
    assert acl["enabled"] is True
    assert acl["default_permission"] == "deny"
    rules = {r["id"] for r in acl["rules"]}
    subjects = {s["id"] for s in acl["subjects"]}
    for policy in acl["policies"]:
        assert set(policy["rules"]) <= rules, policy["id"]
        assert set(policy["subjects"]) <= subjects, policy["id"]
    # Only the camera's certificate may offer camera/*.
    owners = {
        subject
        for policy in acl["policies"]
        if "camera-serve" in policy["rules"] or "camera-notify" in policy["rules"]
        for subject in policy["subjects"]
    }
    assert owners == {"camera"}
    # Every service of the secure deploy file has a subject of its own name.
    deploy = yaml.safe_load((REPO / "deploy" / "secure.yaml").read_text())
    for name, spec in deploy["services"].items():
        if spec.get("type") != "router":
            assert name in subjects
            assert spec["network"]["config"] == f"deploy/tls/certs/{name}.json5"


def test_generated_keys_are_ignored_by_git() -> None:
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    for path in ("deploy/tls/certs/camera.key", "deploy/tls/anything.key"):
        done = subprocess.run(["git", "check-ignore", "-q", path], cwd=REPO)
        assert done.returncode == 0, f"{path} is not git-ignored"
