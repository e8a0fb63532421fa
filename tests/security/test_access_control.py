"""Access control by certificate common name: only the camera can put into camera/images.

In framegate, putting into camera/images means *being* the process that offers it: declaring
the queryable on framegate/camera/*, the token framegate/@svc/camera, and sending the
camera's notifications; acks on framegate/@ack/camera/** drive its flow control. An
intruder (an unknown certificate, or another service's) tries each of these; readers must
see exactly what the camera stored, while their own reads keep working.
"""

from __future__ import annotations

import base64
import json
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import msgpack
import pytest
import yaml
import zenoh

from middleware import FramegateError, NetworkConfig, Node, SubscriptionMode, make_metadata
from tests.conftest import REPO, NodeProcess, child_env, free_port, wait_until
from tests.helpers.timing import answered, scaled
from tests.security.conftest import Certs, SecureRouter

pytestmark = pytest.mark.integration

MS = 1_000_000
REAL = {t * MS: b"camera frame %d" % t for t in range(1, 6)}


def _session(router: SecureRouter, name: str) -> zenoh.Session:
    """A raw Zenoh session with ``name``'s certificate: an attacker needs no framegate."""
    conf = zenoh.Config.from_file(str(router.certs.config(name)))
    conf.insert_json5("connect/endpoints", json.dumps([router.endpoint]))
    return zenoh.open(conf)


@pytest.fixture
def raw_session(secure_router: SecureRouter) -> Iterator[Callable[[str], zenoh.Session]]:
    opened: list[zenoh.Session] = []

    def open_as(name: str) -> zenoh.Session:
        session = _session(secure_router, name)
        opened.append(session)
        return session

    yield open_as
    for session in opened:
        session.close()


@pytest.fixture
def camera(node_process: Callable[..., NodeProcess], secure_router: SecureRouter) -> NodeProcess:
    """The real camera (CN=camera) with five elements in camera/images."""
    proc = node_process("camera", *secure_router.args("camera"))
    assert proc.call("offer", buffer="images")["ok"]
    for t, payload in REAL.items():
        encoded = base64.b64encode(payload).decode()
        assert proc.call("put", buffer="images", t=t, payload=encoded)["ok"]
    return proc


def _elements(reader: NodeProcess) -> dict[int, bytes]:
    reply = reader.call("query", target="camera/images")
    assert reply["ok"], reply
    return {e["t"]: base64.b64decode(e["payload"]) for e in reply["elements"]}


def _ls(router: SecureRouter) -> list[dict[str, Any]]:
    done = subprocess.run(
        [sys.executable, "-m", "services.cli", "ls", "--json", *router.args("cli")],
        cwd=REPO,
        env=child_env(),
        capture_output=True,
        text=True,
        timeout=scaled(60),
    )
    assert done.returncode == 0, done.stderr
    services: list[dict[str, Any]] = json.loads(done.stdout)["services"]
    return services


@pytest.mark.parametrize("who", ["intruder", "detector"])
def test_intruder_offering_camera_does_not_change_what_readers_see(
    who: str,
    camera: NodeProcess,
    node_process: Callable[..., NodeProcess],
    secure_router: SecureRouter,
) -> None:
    # ``detector`` is a legitimate service with rights of its own, but not the camera's.
    reader = node_process(None, *secure_router.args("cli"))
    assert _elements(reader) == REAL

    fake = node_process("camera", *secure_router.args(who))
    # `unchecked`: skip the one-producer-per-name check, which would refuse the intruder
    # before the router could be shown dropping what it puts.
    assert fake.call("offer", buffer="images", unchecked=True)["ok"]
    forged = {3 * MS: b"forged", 100 * MS: b"injected", 101 * MS: b"injected"}
    for t, payload in forged.items():
        encoded = base64.b64encode(payload).decode()
        assert fake.call("put", buffer="images", t=t, payload=encoded)["ok"]
    # Its own session answers its own queries: the declarations were made, and dropped
    # by the router. Asked until it does (a query of the default timeout came back empty
    # once with two CPU hogs beside the suite: one look at a process is never enough).
    wait_until(lambda: set(_elements(fake)) >= {100 * MS, 101 * MS}, 60, "the fake's own elements")

    assert _elements(reader) == REAL
    cameras = [s for s in _ls(secure_router) if s["service"] == "camera"]
    assert len(cameras) == 1, cameras
    images = {b["buffer"]: b for b in cameras[0]["buffers"]}["images"]
    assert images["count"] == len(REAL)


def test_reads_allowed_to_cli_still_work(camera: NodeProcess, secure_router: SecureRouter) -> None:
    with Node(network=secure_router.net("cli")) as cli:
        wait_until(lambda: cli.live_services() == ["camera"], 30, "the camera, alone")
        last = answered(lambda: cli.query("camera/images", last=2), "camera/images")
        assert [e.timestamp_ns for e in last] == [4 * MS, 5 * MS]
        assert answered(lambda: cli.get("camera/images", 2 * MS), "2 ms").payload == REAL[2 * MS]
        info = answered(lambda: cli.buffer_info("camera/images", timeout_s=scaled(10.0)), "info")
        assert (info.count, info.puts) == (len(REAL), len(REAL))


def test_cli_may_observe_but_not_hold_the_camera_back(
    camera: NodeProcess, secure_router: SecureRouter
) -> None:
    with Node(network=secure_router.net("cli")) as cli:
        observer = cli.subscribe("camera/images", queue_size=4, mode=SubscriptionMode.OBSERVE)
        # A flow-controlled subscription would let an operator stall the camera: its token
        # is dropped at the router, so the camera never counts it.
        cli.subscribe("camera/images", queue_size=1, wait_s=1.0)
        assert camera.call("wait_subscribers", buffer="images", count=1, timeout=30)["registered"]
        for t in (6 * MS, 7 * MS, 8 * MS):
            assert camera.call("put", buffer="images", t=t)["ok"]
        modes = [s["mode"] for s in camera.call("fill", buffer="images")["subscriptions"]]
        assert modes == ["observe"]
        note = observer.take(timeout_s=scaled(30))
        assert note is not None and note.timestamp_ns == 6 * MS


def _forged_notification(t: int) -> bytes:
    """The header of a notification (README "Notifications"): it rides as the attachment,
    and with pushed true the Zenoh payload is taken for the element's payload."""
    # epoch, seq, timestamp_ns, metadata, pushed, acked, descriptor
    header = ["forged", 1, t, make_metadata("generic", t), True, None, None]
    return bytes(msgpack.packb(header, use_bin_type=True))


def test_intruder_cannot_send_the_camera_s_notifications(
    camera: NodeProcess,
    node_process: Callable[..., NodeProcess],
    secure_router: SecureRouter,
    raw_session: Callable[[str], zenoh.Session],
) -> None:
    mediator = node_process(None, *secure_router.args("mediator"))
    sub_id = mediator.call("subscribe", target="camera/images", queue=4)["id"]
    notify_key = f"framegate/@notify/camera/images/{sub_id}"
    forged = _forged_notification(999 * MS)

    for who in ("intruder", "detector", "cli", "mediator"):
        raw_session(who).put(notify_key, b"forged element", attachment=forged)
    taken = mediator.call("take", target="camera/images", timeout=1.5)
    assert taken["notification"] is None, taken

    assert camera.call("put", buffer="images", t=6 * MS)["ok"]
    taken = mediator.call("take", target="camera/images", timeout=30)
    assert taken["notification"]["t"] == 6 * MS
    assert base64.b64decode(taken["element"]["payload"]) == b"p%d" % (6 * MS)

    # Control: the same message from the camera's certificate does arrive, so it is the
    # access control, not a malformed message, that stopped the others.
    raw_session("camera").put(notify_key, b"forged element", attachment=forged)
    taken = mediator.call("take", target="camera/images", timeout=30)
    assert taken["notification"]["t"] == 999 * MS
    assert base64.b64decode(taken["element"]["payload"]) == b"forged element"


def test_intruder_cannot_ack_for_the_camera_s_subscriber(
    camera: NodeProcess,
    node_process: Callable[..., NodeProcess],
    secure_router: SecureRouter,
    raw_session: Callable[[str], zenoh.Session],
) -> None:
    # A forged ack would empty a subscriber's queue in the camera's books: flow control
    # would stop protecting the mediator. The attacker knows the epoch (it is on the wire).
    mediator = node_process(None, *secure_router.args("mediator"))
    sub_id = mediator.call("subscribe", target="camera/images", queue=2)["id"]
    epochs: list[str] = []
    notified: list[tuple[str, int]] = []  # (epoch, seq) of each notification seen
    seen = threading.Event()

    def on_notification(sample: zenoh.Sample) -> None:
        assert sample.attachment is not None
        header = msgpack.unpackb(sample.attachment.to_bytes())
        epochs.append(header[0])
        notified.append((header[0], header[1]))
        seen.set()

    spy = raw_session("mediator").declare_subscriber(
        f"framegate/@notify/camera/images/{sub_id}", on_notification
    )
    assert camera.call("wait_subscribers", buffer="images", count=1, timeout=30)["registered"]
    for t in (6 * MS, 7 * MS):
        assert camera.call("put", buffer="images", t=t)["ok"]
    assert seen.wait(scaled(30))
    refused = camera.call("put", buffer="images", t=8 * MS)
    assert refused["error"] == "FlowControlRefused"

    ack_key = f"framegate/@ack/camera/images/{sub_id}"
    ack = msgpack.packb({"e": epochs[0], "s": 2})
    for who in ("intruder", "detector", "cli", "gyro"):
        raw_session(who).put(ack_key, ack)
    queued = camera.call("fill", buffer="images")
    assert queued["fill"] == 1.0
    assert camera.call("put", buffer="images", t=8 * MS)["error"] == "FlowControlRefused"

    # Control: the subscriber's own principal may ack, and then the camera may put again.
    # Sent again until it counts, each time for the newest notification seen: a put right
    # after its session opened can go nowhere until the router's routes reach the session,
    # and a mediator process starved past its lease registers again, so that the queued
    # elements are notified again under a new epoch, which an ack of the old one does not
    # free (at load 30 the one ack of epochs[0] never freed the queue).
    as_mediator = raw_session("mediator")

    def acked() -> bool:
        epoch, seq = notified[-1]
        as_mediator.put(ack_key, msgpack.packb({"e": epoch, "s": seq}))
        return bool(camera.call("fill", buffer="images")["fill"] == 0.0)

    wait_until(
        acked,
        30,
        lambda: f"the mediator's ack (notified {notified}, {camera.call('fill', buffer='images')})",
    )
    assert camera.call("put", buffer="images", t=8 * MS)["ok"]
    spy.undeclare()


def _detections(cli: Node) -> int:
    """How many detections the detector stored, as ``cli`` sees it (0 while unreachable)."""
    try:
        return cli.buffer_info("detector/detections", timeout_s=scaled(10.0)).puts
    except FramegateError:
        return 0


def _launch(deploy: dict[str, Any], tmp_path: Path) -> subprocess.Popen[str]:
    """``framegate launch`` of ``deploy`` (a deploy file's mapping), written to tmp_path."""
    (tmp_path / "secure.yaml").write_text(yaml.safe_dump(deploy))
    return subprocess.Popen(
        [sys.executable, "-m", "services.cli", "launch", str(tmp_path / "secure.yaml")],
        cwd=REPO,
        env=child_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )


@pytest.mark.slow
def test_the_secure_profile_runs_the_whole_pipeline(
    secure_router: SecureRouter, tmp_path: Path
) -> None:
    """deploy/secure.yaml's services, each with its own certificate, through the router."""
    deploy = yaml.safe_load((REPO / "deploy" / "secure.yaml").read_text())
    del deploy["services"]["router"]  # the test's router is already up, on its own port
    for spec in deploy["services"].values():
        config = Path(spec["network"]["config"])
        assert config.parent == Path("deploy/tls/certs")
        spec["network"] = {
            "config": str(secure_router.certs.dir / config.name),
            "connect": [secure_router.endpoint],
        }
    launch = _launch(deploy, tmp_path)
    try:
        with Node(network=secure_router.net("cli")) as cli:
            wait_until(lambda: _detections(cli) >= 3, 90, "detections through the secure router")
            every = ["camera", "detector", "gyro", "mediator"]
            wait_until(lambda: cli.live_services() == every, 30, f"exactly {every}")
            accepted = answered(lambda: cli.query("mediator/images", last=1), "mediator")[0]
            frame = answered(lambda: cli.get("camera/images", accepted.timestamp_ns), "frame")
            assert frame.payload == accepted.payload
    finally:
        launch.terminate()
        launch.communicate(timeout=scaled(30))


@pytest.mark.slow
def test_the_secure_deploy_file_starts_with_its_own_router(certs: Certs, tmp_path: Path) -> None:
    """deploy/secure.yaml as written, router included (on a free port): the launcher must
    not wait, as a client of a router it has not started yet, before starting it (it did,
    for 12 s, then failed with "Timeout!")."""
    port = free_port()
    endpoint = f"tls/localhost:{port}"
    deploy = yaml.safe_load((REPO / "deploy" / "secure.yaml").read_text())
    for name, spec in deploy["services"].items():
        config = certs.dir / Path(spec["network"]["config"]).name
        if name == "router":
            spec["network"] = {"config": str(config), "listen": [f"tls/127.0.0.1:{port}"]}
        else:
            spec["network"] = {"config": str(config), "connect": [endpoint]}
    launch = _launch(deploy, tmp_path)
    try:
        cli_net = NetworkConfig(config_file=certs.config("cli"), connect=(endpoint,))

        def detections() -> int:
            assert launch.poll() is None, "the launcher ended"
            try:  # the launched router is not up at once: a client cannot open before it is
                with Node(network=cli_net) as cli:
                    return _detections(cli)
            except FramegateError:
                return 0

        wait_until(lambda: detections() >= 3, 180, "detections through the launched router")
    finally:
        launch.terminate()
        _, err = launch.communicate(timeout=scaled(30))
    assert launch.returncode == 0, err
