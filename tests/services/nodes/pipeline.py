"""Run a deploy file with ``framegate launch`` in a subprocess, isolated on its own port."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from middleware import FramegateError, NetworkConfig, Node
from tests.conftest import REPO, child_env, free_port
from tests.helpers.timing import LEASE_LAPSE_S, scaled


class Pipeline:
    """``framegate launch FILE`` plus a client Node on the same private rendezvous port."""

    def __init__(self, tmp_path: Path, deploy_yaml: str) -> None:
        self.port = free_port()
        self.deploy = tmp_path / "deploy.yaml"
        self.deploy.write_text(deploy_yaml)
        env = child_env()
        env["FRAMEGATE_LOCAL_PORT"] = str(self.port)
        self.lines: list[str] = []
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "launch", str(self.deploy), "--no-colour"],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            cwd=REPO,
            env=env,
        )
        threading.Thread(target=self._pump, daemon=True).start()
        self.network = NetworkConfig(local_port=self.port)
        self.node = Node(network=self.network)

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line.rstrip())

    def info(self, target: str, *, wait_s: float = LEASE_LAPSE_S) -> Any:
        """A buffer's info; a service that does not answer is asked again for
        ``scaled(wait_s)`` (a live one may have lost its lease, see ``pid``), then its
        error is raised."""
        deadline = time.monotonic() + scaled(wait_s)
        while True:
            try:
                return self.node.buffer_info(target, timeout_s=scaled(10.0))
            except FramegateError:
                if time.monotonic() >= deadline:
                    raise
            time.sleep(0.2)

    def counter(self, target: str, name: str = "puts") -> int:
        """A producer counter (puts, refused, ...) of a buffer; 0 while it is not live (for
        polling: one look)."""
        try:
            return int(getattr(self.info(target, wait_s=0), name))
        except FramegateError:
            return 0

    def count(self, target: str, name: str = "puts") -> int:
        """A producer counter of a buffer, asked again while it does not answer (see
        ``info``): for a baseline or a difference, where ``counter``'s 0 would be wrong."""
        return int(getattr(self.info(target), name))

    def subscriber_count(self, target: str) -> int:
        """Subscriptions a buffer's producer counts; -1 while it is not live."""
        try:
            return len(self.info(target, wait_s=0).subscriptions)
        except FramegateError:
            return -1

    def subscription_ids(self, target: str) -> set[str] | None:
        """Ids of the subscriptions a buffer's producer counts; None while it is not live."""
        try:
            return {s.subscription_id for s in self.info(target, wait_s=0).subscriptions}
        except FramegateError:
            return None

    def pid(self, service: str, *, wait_s: float = LEASE_LAPSE_S) -> int | None:
        """The service's pid, or None when it has not answered for ``scaled(wait_s)``
        (crashed and not restarted yet, or restarting).

        A live service answers at once, but on a loaded machine a process can go without
        CPU for longer than its session's lease (measured: a camera's Zenoh transmit thread
        runnable but not run for 2.3 s at load 22 on 2 cores); its peers then drop it until
        it reconnects, seconds later, and meanwhile nobody answers for it. So a silent
        service is asked again until the deadline instead of being read as dead; a crash
        still shows, as a new pid (the launcher restarts it) or as silence past the deadline.
        """
        deadline = time.monotonic() + scaled(wait_s)
        while True:
            try:
                return self.node.service_info(service, timeout_s=scaled(10.0)).pid
            except FramegateError:
                if time.monotonic() >= deadline:
                    return None
            time.sleep(0.2)

    def kill(self, service: str) -> int:
        pid = self.pid(service)
        assert pid is not None, f"{service} is not live"
        os.kill(pid, signal.SIGKILL)
        return pid

    def log(self) -> str:
        return "\n".join(self.lines[-80:])

    def close(self) -> None:
        self.node.close()
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=scaled(15))
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
