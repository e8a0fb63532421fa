"""The bridge's Zenoh session on the ROS 2 side: the one place in services/nodes that
imports zenoh (framegate's own buffers go through ``middleware`` as everywhere else).

A :class:`RosLink` is one ROS 2 node as rmw_zenoh makes it: a Zenoh session to the ROS 2
system (``rmw_zenohd``), the node's liveliness token, and per topic a publisher or a
subscriber with its own token. Publishers attach rmw_zenoh's per-sample attachment
(sequence number, source timestamp, gid) to every sample.

Threads: Zenoh's callback thread only hands each received sample's payload and attachment
bytes to the subscription's ``on_sample`` (which must only enqueue); everything else runs
on the caller's threads, and the end of a look at the graph (``ask_graph``) is only handed on.
A publisher's sequence counter is guarded by its own lock.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable
from types import TracebackType

import zenoh
import zenoh.ext

from middleware import ConfigError, NetworkConfig, TransportError

from ._rmw import (
    ADMIN_SPACE,
    Attachment,
    Durability,
    EntityKind,
    NodeIdentity,
    Qos,
    Reliability,
    data_key,
    gid,
)

OnSample = Callable[[bytes, bytes | None], None]
_Subscriber = zenoh.Subscriber[None] | zenoh.ext.AdvancedSubscriber[None]
# The most liveliness tokens one snapshot of the ROS graph keeps.
GRAPH_MAX = 65_536


def _callback(on_sample: OnSample) -> zenoh.handlers.Callback[zenoh.Sample]:
    """``on_sample(payload, attachment)`` per sample, run by zenoh-python's thread
    (``indirect``: Zenoh's own thread only queues)."""

    def deliver(sample: zenoh.Sample) -> None:
        attachment = sample.attachment
        on_sample(
            sample.payload.to_bytes(),
            attachment.to_bytes() if attachment is not None else None,
        )

    return zenoh.handlers.Callback(deliver, indirect=True)


class RosPublisher:
    """A ROS 2 publisher: a Zenoh publisher on the topic's data key plus its MP token."""

    def __init__(self, publisher: zenoh.Publisher, token: zenoh.LivelinessToken, gid_: bytes):
        self._publisher = publisher
        self._token = token
        self._gid = gid_
        self._sequence = 0
        self._lock = threading.Lock()

    def publish(self, cdr: bytes | bytearray) -> None:
        """Put one CDR message (Zenoh copies it into its own buffer, as any put);
        TransportError when Zenoh cannot."""
        with self._lock:
            self._sequence += 1
            attachment = Attachment(self._sequence, time.time_ns(), self._gid).encode()
        try:
            self._publisher.put(cdr, attachment=attachment)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot publish on {self._publisher.key_expr}: {exc}") from exc

    def close(self) -> None:
        self._token.undeclare()
        self._publisher.undeclare()


class RosLink:
    """One ROS 2 node on the ROS 2 system's Zenoh network (use as a context manager)."""

    def __init__(
        self,
        network: NetworkConfig,
        *,
        domain_id: int,
        node_name: str,
        namespace: str = "/",
    ) -> None:
        try:
            self._session = zenoh.open(network.zenoh_configs()[0])
        except zenoh.ZError as exc:
            where = ", ".join(network.connect) or "the configured endpoints"
            raise TransportError(f"cannot open the ROS 2 Zenoh session to {where}: {exc}") from exc
        self.identity = NodeIdentity(
            domain_id, str(self._session.info.zid()), node_name, namespace=namespace
        )
        # Publishers, and subscriptions as their data subscriber and token (either may be
        # declared alone: ``listen_any_type``, ``subscription_token``).
        self._entities: list[
            RosPublisher | tuple[_Subscriber | None, zenoh.LivelinessToken | None]
        ] = []
        self._watchers: list[zenoh.Subscriber[None]] = []
        self._next_id = self.identity.node_id + 1
        self._node_token = self._session.liveliness().declare_token(self.identity.node_token())

    def watch_graph(self, on_token: Callable[[str], None]) -> None:
        """Call ``on_token(key)`` with the liveliness token of every ROS 2 entity of the
        domain, present and arriving (as every rmw_zenoh node watches the graph); it runs on
        zenoh-python's thread for this watch, one token at a time."""

        def seen(sample: zenoh.Sample) -> None:
            if sample.kind == zenoh.SampleKind.PUT:  # a new object each time: not `is`
                on_token(str(sample.key_expr))

        try:
            watcher = self._session.liveliness().declare_subscriber(
                f"{ADMIN_SPACE}/{self.identity.domain_id}/**",
                zenoh.handlers.Callback(seen, indirect=True),
                history=True,
            )
        except zenoh.ZError as exc:
            raise TransportError(f"cannot watch the ROS 2 graph: {exc}") from exc
        self._watchers.append(watcher)

    def ask_graph(self, answer: Callable[[list[str]], object], timeout_s: float = 2.0) -> None:
        """Ask for the liveliness tokens of the domain's ROS graph without waiting for them:
        ``answer(tokens)`` runs once when the query ends (replied, or ``timeout_s`` passed), on
        Zenoh's thread, so it must only hand them on; ``[]`` when no one answers, and then at
        once on the caller's thread when Zenoh refuses the query."""
        tokens: list[str] = []

        def on_reply(reply: zenoh.Reply) -> None:
            # Bounded: a peer may declare any number of tokens.
            if reply.ok is not None and len(tokens) < GRAPH_MAX:
                tokens.append(str(reply.ok.key_expr))

        def finished() -> None:
            answer(tokens)

        try:
            self._session.liveliness().get(
                f"{ADMIN_SPACE}/{self.identity.domain_id}/**",
                zenoh.handlers.Callback(on_reply, finished, indirect=False),
                timeout=timeout_s,
            )
        except zenoh.ZError:
            answer([])

    def routers(self) -> int:
        """How many Zenoh routers (``rmw_zenohd``) the session is connected to now."""
        try:
            return len(list(self._session.info.routers_zid()))
        except zenoh.ZError:
            return 0

    def _entity_id(self) -> int:
        entity_id, self._next_id = self._next_id, self._next_id + 1
        return entity_id

    def publisher(self, topic_fqn: str, ros_type: str, hash_chunk: str, qos: Qos) -> RosPublisher:
        """Declare a publisher (data key + MP liveliness token)."""
        token_key = self.identity.endpoint_token(
            self._entity_id(), EntityKind.PUBLISHER, topic_fqn, ros_type, hash_chunk, qos
        )
        key = data_key(self.identity.domain_id, topic_fqn, ros_type, hash_chunk)
        try:
            # Like rmw_zenoh: samples are dropped rather than block the publisher, except for a
            # reliable keep-all publisher, which may lose nothing.
            lossless = qos.reliability is Reliability.RELIABLE and qos.depth == 0
            publisher = self._session.declare_publisher(
                key,
                congestion_control=(
                    zenoh.CongestionControl.BLOCK if lossless else zenoh.CongestionControl.DROP
                ),
                reliability=(
                    zenoh.Reliability.RELIABLE
                    if qos.reliability is Reliability.RELIABLE
                    else zenoh.Reliability.BEST_EFFORT
                ),
            )
            token = self._session.liveliness().declare_token(token_key)
        except zenoh.ZError as exc:
            raise ConfigError(f"cannot publish ROS 2 topic {topic_fqn}: {exc}") from exc
        entity = RosPublisher(publisher, token, gid(token_key))
        self._entities.append(entity)
        return entity

    def subscribe(
        self,
        topic_fqn: str,
        ros_type: str,
        hash_chunk: str,
        qos: Qos,
        on_sample: OnSample,
    ) -> None:
        """Declare a subscription (data key + MS liveliness token); ``on_sample(payload,
        attachment)`` runs on Zenoh's callback thread and must only enqueue."""
        token_key = self.identity.endpoint_token(
            self._entity_id(), EntityKind.SUBSCRIPTION, topic_fqn, ros_type, hash_chunk, qos
        )
        key = data_key(self.identity.domain_id, topic_fqn, ros_type, hash_chunk)
        try:
            callback = _callback(on_sample)
            subscriber: _Subscriber
            if qos.durability is Durability.TRANSIENT_LOCAL:
                # As rmw_zenoh's transient-local subscriptions: an advanced subscriber asks
                # each publisher's cache for its history (a plain one would get nothing
                # published before it), now and whenever a publisher appears later.
                subscriber = zenoh.ext.declare_advanced_subscriber(
                    self._session,
                    key,
                    callback,
                    history=zenoh.ext.HistoryConfig(
                        detect_late_publishers=True, max_samples=qos.depth or None
                    ),
                    subscriber_detection=True,
                )
            else:
                subscriber = self._session.declare_subscriber(key, callback)
            token = self._session.liveliness().declare_token(token_key)
        except zenoh.ZError as exc:
            raise ConfigError(f"cannot subscribe to ROS 2 topic {topic_fqn}: {exc}") from exc
        self._entities.append((subscriber, token))

    def listen_any_type(self, topic_fqn: str, on_sample: OnSample) -> None:
        """A data subscriber taking samples of every type and hash on the topic, with no
        liveliness token yet (``subscription_token`` declares it once the type is known):
        Zenoh routes a publisher's samples by data subscribers, so one declared before the
        type is learnt hears the first. ``on_sample`` as for ``subscribe``."""
        key = f"{self.identity.domain_id}/{topic_fqn.strip('/')}/*/*"
        try:
            subscriber = self._session.declare_subscriber(key, _callback(on_sample))
        except zenoh.ZError as exc:
            raise ConfigError(f"cannot subscribe to ROS 2 topic {topic_fqn}: {exc}") from exc
        self._entities.append((subscriber, None))

    def subscription_token(self, topic_fqn: str, ros_type: str, hash_chunk: str, qos: Qos) -> None:
        """The MS liveliness token of a subscription of ``ros_type`` (the ROS graph's view of
        a ``listen_any_type`` subscriber)."""
        token_key = self.identity.endpoint_token(
            self._entity_id(), EntityKind.SUBSCRIPTION, topic_fqn, ros_type, hash_chunk, qos
        )
        try:
            token = self._session.liveliness().declare_token(token_key)
        except zenoh.ZError as exc:
            raise ConfigError(f"cannot subscribe to ROS 2 topic {topic_fqn}: {exc}") from exc
        self._entities.append((None, token))

    def close(self) -> None:
        """Withdraw every token and close the session (a process with it open may hang)."""
        for entity in reversed(self._entities):
            try:
                if isinstance(entity, RosPublisher):
                    entity.close()
                else:
                    for declared in (entity[1], entity[0]):
                        if declared is not None:
                            declared.undeclare()
            except zenoh.ZError:
                pass  # the session is going anyway
        self._entities.clear()
        for watcher in self._watchers:
            with contextlib.suppress(zenoh.ZError):
                watcher.undeclare()
        self._watchers.clear()
        with contextlib.suppress(zenoh.ZError):
            self._node_token.undeclare()
        self._session.close()

    def __enter__(self) -> RosLink:
        return self

    def __exit__(
        self,
        _type: type[BaseException] | None,
        _value: BaseException | None,
        _tb: TracebackType | None,
    ) -> None:
        self.close()
