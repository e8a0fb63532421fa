"""The mediator as a real process under ``framegate launch``, with a hostile consumer."""

from __future__ import annotations

import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from middleware._wire import Keys
from services.launch import pipeline_yaml
from tests.conftest import REPO, child_env, wait_until
from tests.helpers.raw_zenoh import open_session
from tests.helpers.timing import scaled
from tests.services.nodes.pipeline import Pipeline

pytestmark = pytest.mark.integration

SEED_3 = {"camera": {"seed": 3}, "gyro": {"seed": 3}}
WATCH = ("watch", "mediator/decisions", "--flow-control", "--queue", "1", "--delay", "1")


@pytest.fixture
def pipe(tmp_path: Path) -> Iterator[Pipeline]:
    pipeline = Pipeline(
        tmp_path,
        pipeline_yaml(
            {"camera": {"seed": 3}, "gyro": {"seed": 3}, "detector": {"service_factor": 1.6}}
        ),
    )
    yield pipeline
    pipeline.close()


@pytest.mark.slow
def test_regression_slow_flow_controlled_decisions_watcher_leaves_the_mediator_forwarding(
    pipe: Pipeline,
) -> None:
    # Issue 15: the README's slow-consumer pattern on mediator/decisions killed the mediator
    # within a few frames, and the supervisor then restarted it in a loop.
    wait_until(
        lambda: pipe.counter("mediator/images") >= 5, 60, lambda: "forwarding\n" + pipe.log()
    )
    pid = pipe.pid("mediator")
    env = child_env()
    env["FRAMEGATE_LOCAL_PORT"] = str(pipe.port)
    watcher = subprocess.Popen(
        [sys.executable, "-m", "services.cli", *WATCH],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        cwd=REPO,
        env=env,
    )
    try:
        wait_until(
            lambda: pipe.subscriber_count("mediator/decisions") >= 1, 30, "the watcher to subscribe"
        )
        # The watcher's queue of one is full at once: from here on records are refused.
        wait_until(
            lambda: pipe.counter("mediator/decisions", "refused") >= 10,
            60,
            lambda: "refused decision records\n" + pipe.log(),
        )
        forwarded = pipe.count("mediator/images")
        wait_until(
            lambda: pipe.counter("mediator/images") >= forwarded + 10,
            60,
            lambda: "the mediator to keep forwarding\n" + pipe.log(),
        )
        assert watcher.poll() is None, "the watcher ended"
        assert pipe.pid("mediator") == pid, "the mediator restarted:\n" + pipe.log()
    finally:
        watcher.send_signal(signal.SIGINT)
        try:
            watcher.wait(timeout=scaled(10))
        except subprocess.TimeoutExpired:
            watcher.kill()
            watcher.wait()


def test_garbage_on_the_mediator_s_notification_keys_is_counted_and_it_goes_on(
    pipe: Pipeline,
) -> None:
    """A peer publishing garbage on the keys the mediator's camera and gyro notifications come
    on: counted ``bad-notification`` in ``framegate info mediator/images`` (the subscriptions
    counted it, but nothing showed it), and the mediator keeps forwarding."""
    wait_until(
        lambda: pipe.counter("mediator/images") >= 5, 60, lambda: "forwarding\n" + pipe.log()
    )
    keys = Keys("framegate")
    notify = [
        keys.notify(service, buffer, sub.subscription_id)
        for service, buffer in (("camera", "images"), ("gyro", "rates"))
        for sub in pipe.info(f"{service}/{buffer}").subscriptions
        if sub.node == "mediator"
    ]
    assert len(notify) == 2, notify
    with open_session(f"tcp/127.0.0.1:{pipe.port}") as rogue:

        def counted() -> bool:
            # Sent until counted: a new session's first puts may reach no one yet.
            for key in notify:
                for _ in range(10):
                    rogue.put(key, b"\xff" * 32, attachment=b"not a notification")
            return pipe.info("mediator/images").skipped.get("bad-notification", 0) >= 20

        wait_until(counted, 60, lambda: "the garbage counted\n" + pipe.log())
    forwarded = pipe.count("mediator/images")
    wait_until(
        lambda: pipe.counter("mediator/images") >= forwarded + 5,
        60,
        lambda: "the mediator to keep forwarding\n" + pipe.log(),
    )
    warned = "no notification of its inputs"
    wait_until(lambda: warned in pipe.log(), 30, lambda: "the one warning\n" + pipe.log())
    assert pipe.log().count(warned) == 1, pipe.log()
