"""A service's worker (``services.nodes._runtime.Worker``): a slow step (a camera's render)
runs off the node's executor, which goes on meanwhile, and its outcome comes back as a
handler on the executor. The camera used to make each frame on a new thread while the
executor waited for it, so acks and queries waited for every render."""

from __future__ import annotations

import threading

from middleware import NetworkConfig, Node
from services.nodes._runtime import Outcome, Worker
from tests.conftest import free_port
from tests.helpers.timing import scaled


def test_a_slow_step_runs_while_the_executor_serves_its_deadlines() -> None:
    release = threading.Event()
    ran: list[str] = []
    came: list[tuple[Outcome[int], str]] = []
    done = threading.Event()
    with Node("worker", NetworkConfig(local_port=free_port())) as node:
        worker = Worker("test-worker", node)

        def step() -> int:  # holds the worker until the executor has run a deadline
            assert release.wait(scaled(30)), "the executor ran nothing while the step ran"
            return 7

        def then(outcome: Outcome[int]) -> None:
            came.append((outcome, threading.current_thread().name))
            done.set()

        worker.submit(step, then)
        node.at(0, lambda _now: (ran.append(threading.current_thread().name), release.set()))
        assert done.wait(scaled(30))
        worker.close()
    ((outcome, thread),) = came
    assert outcome == Outcome(7) and ran == [thread] and thread.startswith("fg-exec-")


def test_what_a_step_raises_is_its_outcome_and_the_worker_goes_on() -> None:
    came: list[Outcome[int]] = []
    done = threading.Event()
    with Node("worker", NetworkConfig(local_port=free_port())) as node:
        worker = Worker("test-worker", node)

        def fails() -> int:
            raise ValueError("unreadable")

        worker.submit(fails, came.append)
        worker.submit(lambda: 3, lambda o: (came.append(o), done.set()))
        assert done.wait(scaled(30))
        worker.close()
    assert isinstance(came[0].error, ValueError) and came[1] == Outcome(3)
