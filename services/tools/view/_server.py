"""The Foxglove WebSocket server (``foxglove-sdk``) and the channels the viewer logs to.

The SDK speaks the Foxglove WebSocket protocol (subprotocol ``foxglove.sdk.v1``): it
advertises every channel to each client, sends a channel's messages only to clients that
subscribed to it, and never blocks the logger: each client has an outbox of ``backlog``
messages, and when a client reads too slowly the oldest ones are dropped. The SDK does not
say how many; it logs "outbox for client ADDR full" (at most once per 30 s), which we count
per client and show in the status line.

Threads: ``publish`` is called from the viewer's streaming threads (``Channel.log`` is
thread-safe and returns at once). The SDK calls ``_Listener`` and ``_SlowClients`` on its
own threads; they only update ``Counters`` (under its lock).
"""

from __future__ import annotations

import logging
import re
import socket
import sys
import threading
from typing import Any

import foxglove
from foxglove.websocket import ChannelView, Client, ServerListener

from middleware import ConfigError
from services.tools.bag import DerivedMessage, DerivedTopic

from ._config import VIEW_PORT_ENV, ViewConfig
from ._status import Counters

_SLOW = re.compile(r"outbox for client (\S+) full")
_GONE = re.compile(r"(?:Unregistered client|Connection closed by client) (\S+)")


class _Listener(ServerListener):
    """Which client subscribes to which channel (``foxglove.websocket.ServerListener``)."""

    def __init__(self, counters: Counters) -> None:
        self._counters = counters

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        self._counters.subscribed(client.id, channel.id)

    def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
        self._counters.unsubscribed(client.id, channel.id)


class _SlowClients(logging.Handler):
    """Counts the SDK's reports of a client whose outbox overflowed."""

    def __init__(self, counters: Counters) -> None:
        super().__init__(level=logging.INFO)
        self._counters = counters

    def emit(self, record: logging.LogRecord) -> None:
        text = record.getMessage()
        if slow := _SLOW.search(text):
            self._counters.slow_client(slow.group(1))
        elif gone := _GONE.search(text):
            self._counters.client_gone(gone.group(1))
        elif record.levelno >= logging.WARNING:
            # Anything else the SDK warns about (a client subscribing to a channel it does
            # not know, a client disconnected) is for the user to see, one line each.
            print(f"foxglove: {text}", file=sys.stderr, flush=True)


_logging_lock = threading.Lock()
_sdk_logging = {"enabled": False}


def _route_sdk_logs(counters: Counters) -> _SlowClients:
    """Send the SDK's log records to our counter instead of the terminal."""
    handler = _SlowClients(counters)
    with _logging_lock:
        sdk = logging.getLogger("foxglove")
        sdk.propagate = False  # its INFO chatter (client connected, ...) stays off stderr
        sdk.setLevel(logging.INFO)
        sdk.addHandler(handler)
        if not _sdk_logging["enabled"]:
            foxglove.set_log_level("INFO")  # only the first call in a process counts
            _sdk_logging["enabled"] = True
    return handler


class FoxgloveServer:
    """A running server plus one channel per derived topic (created on first use)."""

    def __init__(self, config: ViewConfig, counters: Counters) -> None:
        self._counters = counters
        self._handler = _route_sdk_logs(counters)
        self._context = foxglove.Context()
        self._channels: dict[str, foxglove.Channel] = {}
        self._lock = threading.Lock()
        try:
            self._server = foxglove.start_server(
                name="framegate",
                host=config.host,
                port=config.port,
                server_listener=_Listener(counters),
                context=self._context,
                message_backlog_size=config.backlog,
            )
        except RuntimeError as exc:  # the SDK reports a bind failure as a bare RuntimeError
            where = f"{config.host}:{config.port}"
            if "in use" in str(exc).lower():
                raise ConfigError(
                    f"cannot serve Foxglove on {where}: the port is taken (another "
                    f"`framegate view`?); choose another with --port N ({VIEW_PORT_ENV}), "
                    "0 for any free port"
                ) from exc
            if "assign requested address" in str(exc).lower():  # EADDRNOTAVAIL
                raise ConfigError(
                    f"cannot serve Foxglove on {where}: that address is not one of this "
                    "machine's; give --host an address of this one (127.0.0.1, the default, "
                    "or 0.0.0.0 for every interface)"
                ) from exc
            raise ConfigError(f"cannot serve Foxglove on {where}: {exc}") from exc
        self.host = config.host

    @property
    def port(self) -> int:
        return int(self._server.port)

    @property
    def url(self) -> str:
        # Every interface (0.0.0.0, ::) is no address a client can open: name this machine.
        host = socket.gethostname() if self.host in ("0.0.0.0", "::", "") else self.host
        return f"ws://{host}:{self.port}"

    def declare(self, topics: tuple[DerivedTopic, ...]) -> None:
        """Advertise channels now, so a client sees them before any data arrives."""
        for topic in topics:
            self._channel(topic)

    def _channel(self, topic: DerivedTopic) -> foxglove.Channel:
        with self._lock:
            channel = self._channels.get(topic.topic)
            if channel is None:
                schema: Any = None
                if topic.schema_name is not None:
                    schema = foxglove.Schema(
                        name=topic.schema_name,
                        encoding=topic.schema_encoding,
                        data=topic.schema_data,
                    )
                channel = foxglove.Channel(
                    topic.topic,
                    schema=schema,
                    message_encoding=topic.message_encoding,
                    context=self._context,
                    metadata={"framegate.role": topic.role},
                )
                self._channels[topic.topic] = channel
            return channel

    def wanted(self, topics: tuple[DerivedTopic, ...]) -> set[str]:
        """The topics some client subscribes to right now (the others need no work)."""
        return {t.topic for t in topics if self._channel(t).has_sinks()}

    def publish(self, topics: dict[str, DerivedTopic], messages: list[DerivedMessage]) -> None:
        """Hand messages to the server; returns at once (slow clients drop, see above)."""
        for message in messages:
            self._channel(topics[message.topic]).log(message.data, log_time=message.log_time_ns)
            self._counters.count(message.topic)

    def stop(self) -> None:
        self._server.stop()
        with _logging_lock:
            logging.getLogger("foxglove").removeHandler(self._handler)
