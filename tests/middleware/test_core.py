"""The redesigned core against real Zenoh sessions on loopback: limits refused at subscribe,
registration slots and the queue budget, the horizon, the one loop per node, names."""

from __future__ import annotations

import subprocess
import sys
import threading

import pytest

from middleware import (
    ConfigError,
    FlowControlRefused,
    NetworkConfig,
    Node,
    NotFoundError,
    RegistrationRefused,
    SchemaError,
    SubscriptionMode,
    make_metadata,
    now_ns,
)
from middleware._inbox import Control
from middleware._protocol_producer import FLOW_QUEUE_MAX
from middleware._wire import MAX_QUEUE_SIZE, Keys, encode_ack
from tests.conftest import child_env, wait_until
from tests.helpers.raw_zenoh import open_session
from tests.helpers.timing import scaled


def _meta(t: int) -> bytes:
    return make_metadata("generic", t)


def test_a_queue_beyond_the_limit_is_refused_at_subscribe(listen_net, connect_net) -> None:
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        service.offer("images")
        with pytest.raises(ConfigError, match=f"exceeds the flow limit of {FLOW_QUEUE_MAX}"):
            client.subscribe("cam/images", queue_size=FLOW_QUEUE_MAX + 1)
        with pytest.raises(ConfigError, match="exceeds the observe limit"):
            client.subscribe(
                "cam/images", queue_size=MAX_QUEUE_SIZE + 1, mode=SubscriptionMode.OBSERVE
            )


def test_a_registration_beyond_the_budget_is_refused_with_its_reason(
    listen_net, connect_net
) -> None:
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        service.offer("images")
        # Each waits for the producer's answer (greeting or refusal) as long as a loaded
        # machine needs: after subscribe's default 2 s an unanswered one is returned as is.
        wait_s = scaled(10.0)
        big = client.subscribe("cam/images", queue_size=FLOW_QUEUE_MAX - 10, wait_s=wait_s)
        with pytest.raises(RegistrationRefused, match="queue size 20 exceeds the fair share"):
            client.subscribe("cam/images", queue_size=20, wait_s=wait_s)
        small = client.subscribe("cam/images", queue_size=10, wait_s=wait_s)  # what is left fits
        info = client.buffer_info("cam/images", timeout_s=scaled(10.0))
        assert info.refused_subscriptions == 1
        assert {s.subscription_id for s in info.subscriptions} == {
            big.subscription_id,
            small.subscription_id,
        }


def test_hostile_huge_queue_tokens_never_hold_the_producer(listen_net, endpoint) -> None:
    """300 forged flow tokens asking for 2**20 each are refused: puts go on, no memory held."""
    with Node("cam", listen_net) as service:
        images = service.offer("images")
        keys = Keys("framegate")
        with open_session(endpoint) as rogue:
            tokens = [
                rogue.liveliness().declare_token(
                    keys.subscription_token(
                        "cam", "images", f"rogue{i}", SubscriptionMode.FLOW, 1 << 20, 0, "x~y"
                    )
                )
                for i in range(300)
            ]
            wait_until(lambda: images.info().refused_subscriptions == 300, 10.0, "300 refusals")
            for t in range(1, 50):
                images.put(t, b"x" * 1000, _meta(t))  # never refused
            assert images.subscriptions() == []
            for token in tokens:
                token.undeclare()


def test_observers_cannot_take_a_flow_subscribers_slot(listen_net, endpoint, connect_net) -> None:
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        images = service.offer("images")
        keys = Keys("framegate")
        with open_session(endpoint) as rogue:
            tokens = [
                rogue.liveliness().declare_token(
                    keys.subscription_token(
                        "cam", "images", f"obs{i}", SubscriptionMode.OBSERVE, 2, 0, "x~y"
                    )
                )
                for i in range(300)
            ]
            wait_until(lambda: images.info().refused_subscriptions >= 44, 10.0, "observers full")
            sub = client.subscribe("cam/images", queue_size=1)
            images.put(1, b"a", _meta(1))
            assert sub.take(timeout_s=scaled(30)) is not None
            images.put(2, b"b", _meta(2), wait_s=5.0)  # once the take's ack arrived
            with pytest.raises(FlowControlRefused):
                images.put(3, b"c", _meta(3))  # the flow subscriber holds the producer back
            for token in tokens:
                token.undeclare()


def test_an_element_stamped_beyond_the_horizon_is_refused(listen_net) -> None:
    with Node("cam", listen_net) as service:
        images = service.offer("images")
        ahead = now_ns() + 3600 * 10**9
        with pytest.raises(SchemaError, match="ahead of this process's clock"):
            images.put(ahead, b"x", _meta(ahead))
        t = now_ns()
        images.put(t, b"x", _meta(t))  # a sane stamp after it is stored
        assert images.info().rejected == 1 and images.info().count == 1


def test_the_horizon_is_chosen_at_offer(listen_net) -> None:
    with Node("cam", listen_net) as service:
        images = service.offer("images", horizon_s=1.0)
        ahead = now_ns() + 3 * 10**9  # inside the default 10 s, beyond this buffer's 1 s
        with pytest.raises(SchemaError, match="1 s ahead"):
            images.put(ahead, b"x", _meta(ahead))
        with pytest.raises(ConfigError, match="horizon_s"):
            service.offer("other", horizon_s=float("nan"))


def test_one_executor_thread_per_node_however_many_buffers_and_subscriptions(
    listen_net, connect_net
) -> None:
    def framegate_threads() -> list[str]:
        return [t.name for t in threading.enumerate() if t.name.startswith("fg-")]

    before = framegate_threads()
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        for i in range(4):
            service.offer(f"b{i}")
        subs = [client.subscribe(f"cam/b{i}", queue_size=8) for i in range(4)]
        names = [n for n in framegate_threads() if n not in before]
        assert sorted(n for n in names if n.startswith("fg-exec")) == [
            "fg-exec-cam",
            "fg-exec-client",
        ]
        assert not [n for n in names if n.startswith(("fg-resend", "fg-ack"))]
        del subs


def test_a_delayed_ack_leaves_without_the_caller_coming_back(listen_net, connect_net) -> None:
    """A queue of 8 coalesces acks: a take within the delay of the one before holds its
    ack, and the node's executor sends it once due although the caller never comes back."""
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        images = service.offer("images")
        sub = client.subscribe("cam/images", queue_size=8)
        t = 0
        held = False
        for _attempt in range(20):  # a take delayed past the ack delay is acked at once
            for _ in range(2):
                t += 1
                images.put(t, b"x", _meta(t))
            wait_until(lambda: sub.pending == 2, 10.0, "two notifications queued")
            assert len(sub.take_many(1, timeout_s=0)) == 1
            assert len(sub.take_many(1, timeout_s=0)) == 1
            held = sub.next_deadline_ns() is not None
            if held:
                break
            wait_until(lambda: images.subscriptions()[0].queued == 0, 30, "the acks at once")
        assert held, "no take came within the ack delay of the one before in 20 attempts"
        wait_until(lambda: images.subscriptions()[0].queued == 0, 30, "the executor's ack")


def test_a_misspelled_buffer_of_a_live_service_is_not_found(listen_net, connect_net) -> None:
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        service.offer("images")
        with pytest.raises(NotFoundError, match="images"):
            client.query("cam/imags", last=1)
        with pytest.raises(NotFoundError, match="images"):
            client.latest("cam/imags")
        # (Waits all of wait_s: a service may offer its buffers one after another.)
        with pytest.raises(NotFoundError, match="did you mean 'images'"):
            client.subscribe("cam/imags", wait_s=scaled(4.0))


def test_node_honours_framegate_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    from tests.conftest import free_port

    port = free_port()
    with Node("cam", _local(port)) as service:
        service.offer("images")
        monkeypatch.setenv("FRAMEGATE_LOCAL_PORT", str(port))
        with Node() as client:
            wait_until(lambda: "cam" in client.live_services(), 30, "cam seen")


def _local(port: int):  # type: ignore[no-untyped-def]
    from middleware import NetworkConfig

    return NetworkConfig(local_port=port)


def test_a_fetching_subscription_keeps_its_queue_of_fetches_in_flight(
    listen_net, connect_net
) -> None:
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        images = service.offer("images")
        sub = client.subscribe("cam/images", queue_size=8, push_max_bytes=0)

        def produce() -> None:
            for t in range(1, 41):
                images.put(t, t.to_bytes(4, "big") * 100, _meta(t), wait_s=10.0)

        producer = threading.Thread(target=produce)
        producer.start()
        got: list[tuple[int, bytes]] = []
        while len(got) < 40:
            notes = sub.take_many(8, timeout_s=scaled(5.0))
            assert notes, "no notification within 5 s"
            for note in notes:
                assert note.element is None  # nothing pushed: each element is fetched
                got.append((note.timestamp_ns, sub.fetch(note).payload))
        producer.join()
        assert got == [(t, t.to_bytes(4, "big") * 100) for t in range(1, 41)]
        assert sub.fetched_ahead > 0


def test_skips_a_service_counts_show_in_info(listen_net, connect_net) -> None:
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        images = service.offer("images")
        images.count_skip("late", 3)
        images.count_skip("late")
        assert client.buffer_info("cam/images", timeout_s=scaled(10.0)).skipped == {"late": 4}


# Floods the subscription's notification key and the producer's ack key with foreign-epoch
# forgeries and garbage (an in-window ack of the live epoch is the secure profile's to stop,
# see the trust profiles); says "flooding" once 5,000 of each are out.
_FLOOD = """
import sys
from middleware._wire import Keys, encode_ack, encode_notification_header
from tests.helpers.raw_zenoh import open_session

endpoint, subscription_id = sys.argv[1], sys.argv[2]
keys = Keys("framegate")
forged = encode_notification_header("X", 1, 5, b"m", pushed=True, descriptor=None)
with open_session(endpoint) as rogue:
    notify = rogue.declare_publisher(keys.notify("cam", "images", subscription_id))
    ack = rogue.declare_publisher(keys.ack("cam", "images", subscription_id))
    i = 0
    while True:
        i += 1
        notify.put(b"x" * 64, attachment=forged if i % 2 else b"\\xc1garbage")
        ack.put(encode_ack(f"X.{i}", 10**9) if i % 3 else b"\\x00")
        if i == 5_000:
            print("flooding", flush=True)
"""


@pytest.mark.integration
def test_a_flood_of_forged_messages_loses_nothing_accepted_and_blocks_nobody(
    listen_net, connect_net, endpoint
) -> None:
    """A rogue floods the subscription's notification key and the producer's ack key with
    foreign-epoch forgeries and garbage while the producer puts 60 elements through a queue
    of 2: every element arrives once, in order, and the producer is never held for good."""
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        images = service.offer("images")
        sub = client.subscribe("cam/images", queue_size=2)
        # The rogue is another process, as a peer is: a flooding thread in this process would
        # only compete with the node's threads for the interpreter lock, and under a loaded
        # machine that, not the flood's messages, would decide whether elements move.
        rogue = subprocess.Popen(
            [sys.executable, "-c", _FLOOD, endpoint, sub.subscription_id],
            env=child_env(),
            stdout=subprocess.PIPE,
            text=True,
        )

        def produce() -> None:
            for t in range(1, 61):
                images.put(t, t.to_bytes(2, "big"), _meta(t), wait_s=scaled(60.0))

        producer = threading.Thread(target=produce)
        try:
            assert rogue.stdout is not None
            assert rogue.stdout.readline().strip() == "flooding"
            producer.start()
            taken: list[int] = []
            while len(taken) < 60:
                note = sub.take(timeout_s=scaled(60.0))
                assert note is not None, f"stalled after {taken[-3:]}"
                if note.metadata == b"m":
                    continue  # a forgery of an epoch it had not met yet: indistinguishable
                taken.append(note.timestamp_ns)
                assert sub.fetch(note).payload == note.timestamp_ns.to_bytes(2, "big")
            producer.join(timeout=scaled(60.0))
            assert not producer.is_alive()
            assert rogue.poll() is None, "the flood ended before the elements went through"
        finally:
            rogue.kill()
            rogue.wait()
        assert taken == list(range(1, 61))
        assert sub.garbage > 0


def test_subscribe_to_a_service_that_is_not_live_is_refused_unless_awaited(
    listen_net, connect_net
) -> None:
    with Node("camera", listen_net) as service, Node(network=connect_net) as client:
        service.offer("images")
        with pytest.raises(NotFoundError, match=r"'camra' \(did you mean 'camera'\?\)"):
            client.subscribe("camra/images", wait_s=0.2)
        early = client.subscribe("later/data", wait_s=0, await_service=True)
        with Node("later", NetworkConfig(connect=connect_net.connect)) as later:
            data = later.offer("data")
            assert data.wait_for_subscribers(1, timeout_s=scaled(10))  # registered when it appeared
            data.put(1, b"x", _meta(1))
            note = early.take(timeout_s=scaled(30))
            assert note is not None and note.timestamp_ns == 1


def test_ignored_acks_and_churned_tokens_reach_the_buffers_description(
    listen_net, connect_net
) -> None:
    """What the producer ignored is counted in ``info`` and so in every peer's description
    (``framegate info --json``): an ack of an epoch it never gave, and a token withdrawn in
    the batch that declared it (both appended as Zenoh's thread appends them)."""
    keys = Keys("framegate")
    with Node("cam", listen_net) as service, Node(network=connect_net) as client:
        images = service.offer("images")
        token = keys.subscription_tokens("cam", "images").replace("**", "churn/flow/2/-1")
        images._tokens._items.extend([Control(token, b"", True), Control(token, b"", False)])
        forged = Control(keys.ack("cam", "images", "nobody"), encode_ack("forged.1", 1), True)
        images._acks._items.append(forged)
        local = images.info()
        assert (local.foreign_acks, local.collapsed_tokens) == (1, 1)
        assert local.subscriptions == ()
        told = client.buffer_info("cam/images", timeout_s=scaled(10))
        assert (told.foreign_acks, told.collapsed_tokens) == (1, 1)
