"""Asking a service for its description without waiting (``Node.ask_service_info``): what a
handler on the executor uses, so a round trip never holds up the node's other handlers."""

from __future__ import annotations

import threading
import time

from middleware import NetworkConfig, Node, ServiceInfo


def _ask_from_a_handler(client: Node, service: str) -> tuple[ServiceInfo | None, str, bool]:
    """Ask from inside a deadline handler; (answer, thread it ran on, whether the handler
    had returned before the answer ran)."""
    answers: list[tuple[ServiceInfo | None, str, bool]] = []
    returned = threading.Event()
    done = threading.Event()

    def answer(info: ServiceInfo | None) -> None:
        answers.append((info, threading.current_thread().name, returned.is_set()))
        done.set()

    def ask(_now_ns: int) -> None:
        client.ask_service_info(service, answer, timeout_s=5.0)
        returned.set()

    client.at(time.monotonic_ns(), ask)
    assert done.wait(30.0), "no answer, not even None"
    assert len(answers) == 1
    return answers[0]


def test_the_description_comes_later_on_the_executor_with_a_clock_sample(
    listen_net: NetworkConfig, connect_net: NetworkConfig
) -> None:
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        service.offer("images")
        info, thread, after_return = _ask_from_a_handler(client, "cam")
        assert after_return  # the asking handler did not wait for the round trip
        assert thread == "fg-exec-client"  # not on Zenoh's thread
        assert info is not None and info.service == "cam"
        assert info.clock_offset_ns is not None and info.round_trip_ns is not None


def test_a_service_that_is_not_there_is_answered_with_none(listen_net: NetworkConfig) -> None:
    with Node("client", listen_net) as client:
        info, thread, after_return = _ask_from_a_handler(client, "nobody")
        assert info is None and after_return and thread == "fg-exec-client"
