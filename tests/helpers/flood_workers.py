"""``flood`` workers of ``framegate bench`` (services/evidence/bench/_floods.py), one
process each, for the tests that flood a producer's control keys."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from tests.conftest import REPO, child_env
from tests.helpers.timing import scaled


class FloodWorker:
    """A ``flood`` worker of ``framegate bench`` (services/evidence/bench/_floods.py)."""

    def __init__(self, endpoint: str, **params: Any) -> None:
        params = {"connect": endpoint, "namespace": "framegate", **params}
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "services.evidence.bench._worker", "flood", json.dumps(params)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            cwd=REPO,
            env=child_env(),
        )
        assert self.proc.stdout is not None
        assert json.loads(self.proc.stdout.readline()).get("ready")

    def stop(self) -> int:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(json.dumps({"op": "stop"}) + "\n")
        self.proc.stdin.flush()
        count = int(json.loads(self.proc.stdout.readline())["count"])
        self.proc.stdin.close()
        self.proc.wait(timeout=scaled(10))
        return count

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


@contextmanager
def flood_workers(endpoint: str, count: int, **params: Any) -> Iterator[list[FloodWorker]]:
    floods: list[FloodWorker] = []
    try:
        for _ in range(count):
            floods.append(FloodWorker(endpoint, service="cam", buffer="images", **params))
        yield floods
    finally:
        for flood in floods:
            flood.kill()
