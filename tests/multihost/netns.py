"""Two Linux network namespaces joined by a veth pair: two "machines" on one kernel.

    with Lab.create() as lab:                 # pytest.skip(reason) if namespaces are impossible
        proc = lab.popen(lab.robot, [sys.executable, "-m", "services.cli", "router"])
        lab.link_down(); lab.link_up()

Names carry a random suffix so concurrent runs never collide; everything created is removed
on exit (also after a failure), and processes still inside the namespaces are killed by pid.
Only addresses inside the namespaces (10.213.<n>.0/24) and their loopback are ever used.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
import signal
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Any

import pytest

from tests.conftest import REPO, child_env
from tests.helpers.timing import scaled

SUBNET = "10.213.{n}.0/24"
NETEM_UNKNOWN = "Specified qdisc kind is unknown"


class LabError(RuntimeError):
    """A command that set up or changed the lab failed; the message has its stderr."""


@dataclass(frozen=True, slots=True)
class Host:
    """One namespace: its name, its end of the veth pair and its address on it."""

    role: str
    netns: str
    veth: str
    address: str


def _ip(*args: str, netns: str | None = None) -> subprocess.CompletedProcess[str]:
    cmd = ["ip", *args] if netns is None else ["ip", "netns", "exec", netns, "ip", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=scaled(10))


def _check(result: subprocess.CompletedProcess[str]) -> None:
    if result.returncode != 0:
        raise LabError(f"{' '.join(result.args)}: {result.stderr.strip() or result.returncode}")


def skip_reason() -> str | None:
    """Why namespaces cannot be used here, or None if they can."""
    if shutil.which("ip") is None:
        return "iproute2 ('ip') is not installed"
    if os.geteuid() != 0:
        return f"network namespaces need root (running as uid {os.geteuid()})"
    probe = f"fgprobe{secrets.token_hex(3)}"
    made = _ip("netns", "add", probe)
    if made.returncode != 0:
        return f"cannot create a network namespace: {made.stderr.strip()}"
    try:
        veth = _ip("link", "add", f"{probe}a", "type", "veth", "peer", "name", f"{probe}b")
        if veth.returncode != 0:
            return f"cannot create a veth pair: {veth.stderr.strip()}"
        _ip("link", "del", f"{probe}a")
    finally:
        _ip("netns", "del", probe)
    return None


class Lab:
    """The two namespaces ``robot`` and ``base`` and the veth link between them."""

    def __init__(self, subnet_index: int = 1) -> None:
        tag = secrets.token_hex(3)
        n = subnet_index
        self.robot = Host("robot", f"fg-robot-{tag}", f"fgr{tag}", f"10.213.{n}.1")
        self.base = Host("base", f"fg-base-{tag}", f"fgb{tag}", f"10.213.{n}.2")
        self.subnet = SUBNET.format(n=n)
        self._procs: list[subprocess.Popen[str]] = []
        self._made_netns: list[str] = []

    @classmethod
    def create(cls) -> Lab:
        """A lab that is up, or ``pytest.skip`` with the reason if this machine cannot."""
        reason = skip_reason()
        if reason is not None:
            print(f"\nSKIP multihost: {reason}")
            pytest.skip(reason)
        lab = cls()
        try:
            lab._setup()
        except (LabError, subprocess.TimeoutExpired):
            lab.close()
            raise
        return lab

    def _setup(self) -> None:
        for host in (self.robot, self.base):
            _check(_ip("netns", "add", host.netns))
            self._made_netns.append(host.netns)
        # Created in the root namespace, then each end moved: nothing stays behind if the
        # namespaces are deleted (a veth dies with the namespace holding either end).
        _check(_ip("link", "add", self.robot.veth, "type", "veth", "peer", "name", self.base.veth))
        for host in (self.robot, self.base):
            _check(_ip("link", "set", host.veth, "netns", host.netns))
            _check(_ip("link", "set", "lo", "up", netns=host.netns))
            _check(_ip("addr", "add", f"{host.address}/24", "dev", host.veth, netns=host.netns))
            _check(_ip("link", "set", host.veth, "up", netns=host.netns))

    # -- processes -----------------------------------------------------------------------------
    def popen(
        self, host: Host, argv: list[str], log: IO[str] | None = None
    ) -> subprocess.Popen[str]:
        """Start ``argv`` inside ``host``'s namespace (``ip netns exec`` execs, so the pid is
        the program's own)."""
        proc = subprocess.Popen(
            ["ip", "netns", "exec", host.netns, *argv],
            stdout=log if log is not None else subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            text=True,
            cwd=REPO,
            # Unbuffered: a log file gets each line as it is written, so a fixture that
            # gives up shows what the launchers had said by then (not an empty file).
            env={**child_env(), "PYTHONUNBUFFERED": "1"},
        )
        self._procs.append(proc)
        return proc

    def run(
        self, host: Host, argv: list[str], timeout_s: float = 30.0
    ) -> subprocess.CompletedProcess[str]:
        """Run ``argv`` in ``host``'s namespace to completion."""
        return subprocess.run(
            ["ip", "netns", "exec", host.netns, *argv],
            capture_output=True,
            text=True,
            cwd=REPO,
            env=child_env(),
            timeout=timeout_s,
        )

    def pids(self, host: Host) -> list[int]:
        """Every process inside ``host``'s namespace."""
        out = _ip("netns", "pids", host.netns)
        return [int(p) for p in out.stdout.split()] if out.returncode == 0 else []

    # -- the link --------------------------------------------------------------------------------
    def link_down(self) -> None:
        """Cut the link at the base station's end (as if its wireless dropped)."""
        _check(_ip("link", "set", self.base.veth, "down", netns=self.base.netns))

    def link_up(self) -> None:
        _check(_ip("link", "set", self.base.veth, "up", netns=self.base.netns))

    def ping(self, src: Host, dst: Host) -> bool:
        out = self.run(src, ["ping", "-c", "1", "-W", "1", dst.address], timeout_s=scaled(5))
        return out.returncode == 0

    def netem(self, spec: list[str]) -> str | None:
        """Add ``tc netem`` (e.g. ``["delay", "10ms"]``) on both veth ends; the reason if not."""
        if shutil.which("tc") is None:
            return "tc (iproute2) is not installed"
        for host in (self.robot, self.base):
            out = self.run(host, ["tc", "qdisc", "add", "dev", host.veth, "root", "netem", *spec])
            if out.returncode != 0:
                text = out.stderr.strip() or out.stdout.strip()
                if NETEM_UNKNOWN in text:
                    return f"the kernel has no netem qdisc (sch_netem): tc says {text!r}"
                return f"tc qdisc add ... netem failed: {text}"
        return None

    # -- teardown --------------------------------------------------------------------------------
    def stop(self, proc: subprocess.Popen[Any], timeout_s: float = 10.0) -> None:
        """SIGTERM, wait, then SIGKILL one process started here."""
        if proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()

    def close(self) -> None:
        """Stop every process, kill what is left inside the namespaces, delete them."""
        for proc in reversed(self._procs):
            self.stop(proc)
        for host in (self.robot, self.base):
            if host.netns not in self._made_netns:
                continue
            # Only processes of this run live in these uniquely named namespaces.
            for pid in self.pids(host):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            deadline = time.monotonic() + 5
            while self.pids(host) and time.monotonic() < deadline:
                time.sleep(0.05)
            _ip("netns", "del", host.netns)
        # A veth never moved into a namespace would still be in ours.
        for host in (self.robot, self.base):
            if Path(f"/sys/class/net/{host.veth}").exists():
                _ip("link", "del", host.veth)

    def __enter__(self) -> Lab:
        return self

    def __exit__(
        self,
        _type: type[BaseException] | None,
        _value: BaseException | None,
        _tb: TracebackType | None,
    ) -> None:
        self.close()
