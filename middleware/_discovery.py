"""Finding services on the network: what is live, what each offers (its ``@info``).

``Discovery`` is a part of ``Node`` (a base class): the methods here are the node's."""

from __future__ import annotations

import difflib
import json
import time
from contextlib import suppress
from typing import Any

import zenoh

from ._clock import ClockSample, now_ns
from ._config import NetworkConfig, check_name
from ._errors import ConfigError, NotFoundError, QueryError
from ._records import BufferInfo, Retention, ServiceInfo, SubscriptionInfo, SubscriptionMode
from ._session import zenoh_errors
from ._wire import Keys

# A fresh session needs a moment to learn the network's liveliness tokens and queryables;
# discovery asked earlier sees only part of it (measured: 2-3 of 4 services, through a router).
_SETTLE_S = 0.3
# Thread names an @info reply may list (a peer's list is cut here, not trusted to be short).
_MAX_THREADS = 256


def split_target(target: str) -> tuple[str, str]:
    """``service/buffer`` → (service, buffer), with a message that says what is wrong."""
    parts = target.strip("/").split("/")
    if len(parts) != 2:
        raise QueryError(f"bad buffer name {target!r}: write SERVICE/BUFFER, e.g. camera/images")
    try:
        return check_name(parts[0], "service"), check_name(parts[1], "buffer")
    except ConfigError as exc:
        raise QueryError(str(exc)) from exc


class Discovery:
    """What a node asks the network about services (see ``Node``)."""

    network: NetworkConfig
    keys: Keys
    _session: zenoh.Session
    _opened: float

    def _await_peers(self, expected: int, deadline: float) -> None:
        """Return once the session is connected to ``expected`` peers (every other live
        process of the rendezvous), or at ``deadline``: discovery asked earlier would miss
        the services of a peer still connecting."""
        while time.monotonic() < deadline:
            with suppress(zenoh.ZError):
                if len(list(self._session.info.peers_zid())) >= expected:
                    return
            time.sleep(0.005)

    def _settle(self) -> None:
        if self.network.uses_local_default:
            return  # the constructor waited for every peer (_await_peers)
        time.sleep(max(0.0, self._opened + _SETTLE_S - time.monotonic()))

    def live_services(self, *, timeout_s: float = 1.0) -> list[str]:
        """Names of services whose liveliness token is visible now."""
        self._settle()
        prefix = self.keys.service_token("")
        with zenoh_errors("listing live services"):
            replies = self._session.liveliness().get(
                self.keys.service_token("*"), timeout=timeout_s
            )
            names = [str(r.ok.key_expr)[len(prefix) :] for r in replies if r.ok is not None]
        return sorted(set(names))

    def connected(self) -> int:
        """How many other Zenoh sessions (peers and routers) this node is connected to now:
        0 means nothing answered at all, which a command tells from "nothing is live"."""
        with zenoh_errors("listing connected sessions"):
            info = self._session.info
            return len(list(info.peers_zid())) + len(list(info.routers_zid()))

    def _await_live(self, service: str, wait_s: float) -> None:
        """Return once ``service`` is live; NotFoundError (as ``_require_service``) if it is
        not within ``wait_s`` (a service being started is given that long)."""
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            if service in self.live_services(timeout_s=min(1.0, max(0.1, wait_s))):
                return
            time.sleep(0.05)
        self._require_service(
            service, " (to subscribe before it starts: subscribe(..., await_service=True))"
        )

    def _require_service(self, service: str, advice: str = "") -> None:
        live = self.live_services()
        if service not in live:
            hint = difflib.get_close_matches(service, live, n=1)
            did_you_mean = f" (did you mean {hint[0]!r}?)" if hint else ""
            listing = ", ".join(live) if live else "none"
            raise NotFoundError(
                f"no live service named {service!r}{did_you_mean}; live services: {listing}"
                + advice
            )

    def services(self, *, timeout_s: float = 2.0) -> list[ServiceInfo]:
        """Every live service with its buffers, clock offset and round trip."""
        self._settle()
        out: list[ServiceInfo] = []
        start = now_ns()
        with zenoh_errors("describing services"):
            replies = list(
                self._session.get(
                    self.keys.info("*"),
                    consolidation=zenoh.ConsolidationMode.NONE,
                    timeout=timeout_s,
                )
            )
        end = now_ns()
        for reply in replies:
            if reply.ok is None:
                continue
            try:
                out.append(_service_info(json.loads(reply.ok.payload.to_bytes()), start, end))
            except (ValueError, KeyError, TypeError):
                continue  # a peer that answers garbage is left out, not fatal
        return sorted(out, key=lambda s: s.service)

    def service_info(self, service: str, *, timeout_s: float = 2.0) -> ServiceInfo:
        """One live service's description; NotFoundError if it is not live."""
        start = now_ns()
        with zenoh_errors(f"describing {service}"):
            replies = list(self._session.get(self.keys.info(service), timeout=timeout_s))
        end = now_ns()
        for reply in replies:
            if reply.ok is not None:
                return _service_info(json.loads(reply.ok.payload.to_bytes()), start, end)
        self._require_service(service)
        raise NotFoundError(f"service {service!r} did not answer within {timeout_s} s")

    def buffer_info(self, target: str, *, timeout_s: float = 2.0) -> BufferInfo:
        """One buffer's description (retention, size, rate, subscriptions, counters)."""
        service, buffer = split_target(target)
        info = self.service_info(service, timeout_s=timeout_s)
        for candidate in info.buffers:
            if candidate.buffer == buffer:
                return candidate
        names = [b.buffer for b in info.buffers]
        hint = difflib.get_close_matches(buffer, names, n=1)
        did_you_mean = f" (did you mean {hint[0]!r}?)" if hint else ""
        offered = ", ".join(names) or "none"
        raise NotFoundError(
            f"service {service!r} has no buffer {buffer!r}{did_you_mean}; it offers: {offered}"
        )


def _service_info(body: dict[str, Any], start_ns: int, end_ns: int) -> ServiceInfo:
    buffers = []
    for b in body["buffers"]:
        subs = tuple(
            SubscriptionInfo(
                s["id"],
                SubscriptionMode(s["mode"]),
                int(s["queue_size"]),
                int(s["queued"]),
                node=s.get("node"),
                host=s.get("host"),
            )
            for s in b["subscriptions"]
        )
        buffers.append(
            BufferInfo(
                service=b["service"],
                buffer=b["buffer"],
                kind=b["kind"],
                retention=Retention(**b["retention"]),
                count=b["count"],
                payload_bytes=b["payload_bytes"],
                oldest_ns=b["oldest_ns"],
                newest_ns=b["newest_ns"],
                rate_hz=b["rate_hz"],
                puts=b["puts"],
                refused=b["refused"],
                rejected=b["rejected"],
                subscriptions=subs,
                skipped={str(k): int(v) for k, v in b.get("skipped", {}).items()},
                refused_subscriptions=int(b.get("refused_subscriptions", 0)),
                dropped_messages=int(b.get("dropped_messages", 0)),
            )
        )
    sample = ClockSample.from_times(start_ns, int(body["clock_ns"]), end_ns)
    clock = body.get("clock")
    return ServiceInfo(
        service=body["service"],
        host=body["host"],
        pid=int(body["pid"]),
        clock_ns=int(body["clock_ns"]),
        buffers=tuple(buffers),
        clock_offset_ns=sample.offset_ns,
        round_trip_ns=sample.round_trip_ns,
        clock_steps=int(clock["steps"]) if isinstance(clock, dict) else None,
        clock_lead_ns=int(clock["lead_ns"]) if isinstance(clock, dict) else None,
        threads=_names(body.get("threads")),
    )


def _names(value: Any) -> tuple[str, ...] | None:
    """A list of strings as a tuple; None for anything else (an old or odd peer)."""
    if isinstance(value, list) and all(isinstance(v, str) for v in value):
        return tuple(value[:_MAX_THREADS])
    return None
