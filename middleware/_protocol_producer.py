"""The producer's side of the protocol as one sans-IO object, in the manner of h11's
``Connection``: Zenoh samples' bytes and the time go in, wire-ready messages come out.

``ProducerProtocol`` owns every decision the producer makes: which registration a token
makes (or refuses, and why), what an ack means, whether a notification pushes the payload,
inlines the metadata or batches, when an outstanding notification is resent and how many
at once, which publisher a message leaves by and when that publisher is retired. The
Zenoh layer (``Producer``) only feeds it (``token``, ``ack``, ``put_many``, ``tick``) and
carries out what ``events()`` returns; ``next_deadline_ns()`` tells the node's executor when
to call ``tick``. The credit rules themselves are the pure ``ProducerLedger``.

Limits (every resource a peer can make a producer hold is bounded here; docs/limits.md
states them for users and ``info`` reports them as ``BufferLimits``):

- Registration slots: ``MAX_FLOW_REGISTRATIONS`` flow-controlled and, separately,
  ``MAX_OBSERVE_REGISTRATIONS`` observers, so a crowd of observers can never take the slot
  of a flow-controlled subscriber.
- Queue budget: a flow registration may leave up to its queue size of notifications
  un-acked, and the producer keeps each un-acked one (its seq, timestamp and metadata, never
  its payload) to resend it. The queue sizes of all flow registrations together may not
  exceed ``QUEUE_BUDGET``; a token that would exceed it is refused. So the headers kept for
  resending are at most ``QUEUE_BUDGET`` (each holding at most ``INLINE_METADATA_MAX`` bytes
  of metadata), whatever the peers ask for.
- Fair shares: one *holder* (the ``<node>~<host>`` a token names: the peer as the protocol
  sees it) may hold at most half of what the other holders leave free, of the queue budget
  and of each pool of slots. Why half of the free part and not a fixed quota: a fixed
  quota either starves a lone big consumer (a recorder with a deep queue) or lets a few
  holders take everything; with half of what is free, the first greedy holder gets half,
  and whoever asks next still finds the other half, whatever order they come in. A single
  flow queue can therefore be at most ``FLOW_QUEUE_MAX`` (half the budget). Holder names
  are what tokens say: a peer that forges many holder names gets ever smaller halves
  (after k names, 2^-k of the budget is left to the next), which needs the secure profile
  to close (only a consumer's certificate may declare flow tokens).
- Large pushes: a subscriber may ask for payloads above the producer's ``inline_max_bytes``
  to travel with its notifications; at most ``LARGE_PUSH_PER_HOLDER`` registrations of one
  holder and ``LARGE_PUSH_TOTAL`` in all get that (first come), the others get the
  producer's default (they fetch the larger ones). So no peer can make a put copy its
  payload to hundreds of registrations.
- Resends are paced: at most ``RESEND_BURST`` notifications of one registration per tick,
  the rest ``RESEND_PACE_NS`` later, never a whole window at once.
- Tokens cost O(1) amortised work each (one table look-up, the shares kept as running
  sums per holder), so token churn at any rate costs the producer bounded work per token.
  Token events the Zenoh layer had to drop (its inbox is bounded) are repaired by a
  ``resync`` against the live tokens, at most every ``RESYNC_NS``: a withdrawn token whose
  event was lost cannot hold the producer for ever, nor a live one stay unregistered. Only
  a whole answer (one that ended, with fewer than ``RESYNC_TOKENS`` keys) retires anyone,
  and a token event fed while the query was out is newer than the answer and wins: a live
  subscriber retired on a partial or stale answer is never told (its token still lives,
  so nothing would register it again) and waits for good.

Every refusal reaches the subscriber as a control message on its notification key
(``["refused", descriptor, reason]``; see ``_wire``) and is counted; an accepted
registration is greeted (``["hello", descriptor, epoch]``), so ``subscribe`` learns at once,
and greeted again with each resend round while it has acked nothing (a lost greeting heals).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from ._ledger_producer import (
    REPEAT_RESEND_NS,
    ProducerLedger,
    Registration,
    RegistrationKey,
    Send,
)
from ._protocol_events import Event, Publish, Refusal, Retire

# The limits live with the shares; importable from here too (the producer's side).
from ._protocol_shares import FLOW_QUEUE_MAX as FLOW_QUEUE_MAX
from ._protocol_shares import LARGE_PUSH_PER_HOLDER, LARGE_PUSH_TOTAL, Shares, fair_share, holder_of
from ._protocol_shares import MAX_FLOW_REGISTRATIONS as MAX_FLOW_REGISTRATIONS
from ._protocol_shares import MAX_OBSERVE_REGISTRATIONS as MAX_OBSERVE_REGISTRATIONS
from ._protocol_shares import QUEUE_BUDGET as QUEUE_BUDGET
from ._records import BufferLimits, DataObject, SubscriptionInfo, SubscriptionMode
from ._wire import (
    AckFilter,
    Keys,
    decode_ack,
    encode_batch_header,
    encode_control,
    encode_notification_header,
    parse_subscription_token,
)

log = logging.getLogger("framegate.middleware")

# Metadata rides along with notifications (and is kept for resends) up to this size.
INLINE_METADATA_MAX = 8 * 1024
RESEND_BURST = 16
# After lost token events, the table is checked against the live tokens at most this often,
# reading at most this many of them.
RESYNC_NS = 2_000_000_000
RESYNC_TOKENS = 4 * (MAX_FLOW_REGISTRATIONS + MAX_OBSERVE_REGISTRATIONS)
RESEND_PACE_NS = 5_000_000


@dataclass(slots=True)
class ProtocolCounters:
    """What the producer's protocol refused or ignored, reported by ``info``. A refusal's
    reason goes to the refused subscriber (its ``RegistrationRefused``), not here: each names
    its holder and counts, so counting by text would only keep the first few."""

    bad_messages: int = 0
    refused_registrations: int = 0


# What the ledger keeps per outstanding notification: never the payload.
_Kept = tuple[int, bytes | None]  # (timestamp_ns, metadata or None when too large)


class ProducerProtocol:
    """One buffer's producer protocol. Not thread-safe: the caller serialises every call."""

    def __init__(
        self,
        keys: Keys,
        service: str,
        buffer: str,
        epoch: str,
        *,
        inline_max_bytes: int,
        queue_budget: int = QUEUE_BUDGET,
        max_flow: int = MAX_FLOW_REGISTRATIONS,
        max_observe: int = MAX_OBSERVE_REGISTRATIONS,
    ) -> None:
        self.name = f"{service}/{buffer}"
        self.epoch = epoch
        self.inline_max_bytes = inline_max_bytes
        self._keys = keys
        self._service = service
        self._buffer = buffer
        self._max = {SubscriptionMode.FLOW: max_flow, SubscriptionMode.OBSERVE: max_observe}
        self._ledger: ProducerLedger[_Kept] = ProducerLedger(
            epoch, max_registrations=max_flow + max_observe
        )
        self._events: list[Event] = []
        # Registrations whose resend was cut at RESEND_BURST: when to go on.
        self._paced: dict[RegistrationKey, tuple[int, int]] = {}  # key -> (when, next seq)
        self._holders: dict[RegistrationKey, tuple[str | None, str | None]] = {}
        # Fair shares (module doc): per holder and in total; the push limit each registration
        # actually gets (its own, or the producer's inline limit beyond the large-push caps).
        self._shares = Shares(self.name, queue_budget, max_flow, max_observe)
        self._push_limit: dict[RegistrationKey, int] = {}
        self._notify_keys: dict[RegistrationKey, str] = {}  # see ``_notify_key``
        # Lost token events: when a resync is due (None: none), when the last one was; while
        # its query is out, the keys of the token events fed since (None: too many to keep).
        self._resync_at_ns: int | None = None
        self._resynced_ns = -RESYNC_NS
        self._changed: set[RegistrationKey] | None = None
        self._querying = False
        # The last ack decoded per ack key and when (see ``ack``).
        self._acks_seen = AckFilter(REPEAT_RESEND_NS)
        self.counters = ProtocolCounters()

    # -- input -----------------------------------------------------------------------------
    def token(self, keyexpr: str, alive: bool, now_ns: int) -> None:
        """A subscription token appeared (``alive``) or was withdrawn."""
        try:
            parsed = parse_subscription_token(keyexpr)
        except ValueError as exc:
            self.counters.bad_messages += 1
            log.debug("%s: ignored token %s: %s", self.name, keyexpr, exc)
            return
        key = RegistrationKey(*parsed[:4])
        if self._querying and self._changed is not None:
            self._changed.add(key)
            if len(self._changed) > RESYNC_TOKENS:
                self._changed = None
        if not alive:
            gone = self._ledger.token_delete(key)
            if gone is not None:
                self._forget(key)
                self._events.append(Retire(key))
                log.debug("%s: subscription %s withdrawn", self.name, key.sub_id)
            return
        if self._ledger.get(key) is not None:
            return  # a repeat (history and live both deliver it)
        node, host = parsed[4:]
        holder = holder_of(node, host)
        reason = self._shares.refusal(key, holder)
        if reason is not None:
            self.counters.refused_registrations += 1
            log.debug("%s: refused subscription %s: %s", self.name, key.sub_id, reason)
            self._control(key, encode_control("refused", key.descriptor, reason))
            return
        reg = self._ledger.token_put(key, now_ns)
        if reg is None:  # the ledger's own table bound; unreachable under the limits above
            self.counters.refused_registrations += 1
            return
        self._holders[key] = (node, host)
        large = key.push_max_bytes > self.inline_max_bytes and self._shares.large_push_free(holder)
        self._shares.add(key, holder, large, 1)
        if key.push_max_bytes >= 0:
            self._push_limit[key] = (
                key.push_max_bytes if large else min(key.push_max_bytes, self.inline_max_bytes)
            )
        log.debug("%s: subscription %s registered as %s", self.name, key.sub_id, reg.epoch)
        self._control(key, encode_control("hello", key.descriptor, reg.epoch, reg.base, reg.since))

    # -- lost token events ----------------------------------------------------------------
    def tokens_lost(self, now_ns: int) -> None:
        """Token events may be lost: the Zenoh layer's bounded inbox overflowed under churn,
        or someone acked a registration we retired (``retired_epoch``; mostly a leaver's last
        ack, but Zenoh can lose a token event unseen, "Unknown token id" under churn, and a
        subscriber whose token came back unheard repeats its ack while idle: nothing else
        would tell us it lives). The table may hold a registration whose token is gone (it
        would hold us for ever) or lack a live one: a resync is due, every ``RESYNC_NS`` at most."""
        if self._resync_at_ns is None:
            self._resync_at_ns = max(now_ns, self._resynced_ns + RESYNC_NS)

    def resync_due(self, now_ns: int) -> bool:
        """Whether to ask for the live tokens now (not while an answer is awaited)."""
        at = self._resync_at_ns
        return at is not None and at <= now_ns and not self._querying

    def resync_begin(self) -> None:
        """The liveliness query of a due ``resync`` goes out now (its caller times it): token
        events fed until its answer is given are newer, and are remembered to win over it."""
        self._querying = True
        self._changed = set()

    def resync(self, live_tokens: list[str], now_ns: int, *, ended: bool = True) -> None:
        """The tokens live now (a liveliness query's answer, at most ``RESYNC_TOKENS`` of
        them read): registrations without a live token go, live tokens not registered are
        judged as if they had just appeared. An answer that may have left a live token out
        retires nobody: one of ``RESYNC_TOKENS`` or more (a peer can declare any number), or
        one that did not end (``ended`` False: the query failed or timed out; it is asked
        again after ``RESYNC_NS``, so that a lost withdrawal still cannot hold the producer
        for ever). A key with a token event fed since ``resync_begin`` keeps what that event
        said; more such keys than can be kept make the whole answer stale (asked again)."""
        changed = self._changed if self._querying else set()
        self._querying, self._changed = False, None
        self._resync_at_ns = None
        self._resynced_ns = now_ns
        if not ended or changed is None:
            self._resync_at_ns = now_ns + RESYNC_NS
            if changed is None:
                return
        complete = ended and len(live_tokens) < RESYNC_TOKENS
        live: dict[RegistrationKey, str] = {}
        for keyexpr in live_tokens[:RESYNC_TOKENS]:
            try:
                parsed = parse_subscription_token(keyexpr)
            except ValueError:
                continue
            live[RegistrationKey(*parsed[:4])] = keyexpr
        for reg in self._ledger.registrations():
            if complete and reg.key not in live and reg.key not in changed:
                self._ledger.token_delete(reg.key)
                self._forget(reg.key)
                self._events.append(Retire(reg.key))
                log.debug("%s: subscription %s gone at a resync", self.name, reg.key.sub_id)
        for key, keyexpr in live.items():
            if key not in changed:
                self.token(keyexpr, True, now_ns)

    def _forget(self, key: RegistrationKey) -> None:
        """Drop what the protocol keeps beside the ledger for a registration that is gone."""
        self._paced.pop(key, None)
        self._notify_keys.pop(key, None)
        node, host = self._holders.pop(key, (None, None))
        limit = self._push_limit.pop(key, None)
        large = limit is not None and limit > self.inline_max_bytes
        self._shares.add(key, holder_of(node, host), large, -1)

    def ack(
        self,
        keyexpr: str,
        payload: bytes,
        now_ns: int,
        decoded: tuple[str, int] | None = None,
    ) -> bool:
        """An ack arrived on ``keyexpr``; True if it freed credit. ``decoded``: its (epoch,
        seq) when the ack inbox has decoded it already (from ``payload``).

        Two cheap checks come first, because a flood is made of exactly these: anything
        that is not a msgpack map of two (an ack's first byte) is garbage without decoding
        it, and an ack repeating the last one of its key within ``REPEAT_RESEND_NS`` can
        change nothing (acks are cumulative; a repeat makes resends due at most that often).
        """
        if self._acks_seen.malformed(payload):
            self.counters.bad_messages += 1
            return False
        if self._acks_seen.repeat(keyexpr, payload, now_ns):
            return False
        sub_id = keyexpr.rsplit("/", 1)[-1]
        try:
            epoch, seq = decoded if decoded is not None else decode_ack(payload)
        except Exception:  # garbage on our ack key is counted, never raised
            self.counters.bad_messages += 1
            return False
        self._acks_seen.remember(keyexpr, payload, now_ns)
        if not self._ledger.plausible(sub_id, epoch, seq) and self._ledger.retired(epoch):
            self.tokens_lost(now_ns)
        freed = self._ledger.ack(sub_id, epoch, seq, now_ns)
        if freed:
            reg = self._ledger.by_epoch(epoch)
            if reg is not None and not reg.outstanding:
                self._paced.pop(reg.key, None)
        return freed

    def plausible_ack(self, sub_id: str, epoch: str, seq: int) -> bool:
        """Whether an ack could count (``ProducerLedger.plausible``; safe from another
        thread): what an ack inbox keeps, so that forged acks never fill it."""
        return self._ledger.plausible(sub_id, epoch, seq)

    def retired_epoch(self, epoch: str) -> bool:
        """``ProducerLedger.retired`` (safe from another thread; see ``tokens_lost``)."""
        return self._ledger.retired(epoch)

    def admit(self, count: int, *, may_wait: bool) -> Refusal | None:
        """Whether ``count`` elements may be stored now (None), else why not and whether to
        wait for credit: never for a batch larger than the full subscriber's queue, which
        can never fit, nor when the caller has no time left (``may_wait``)."""
        full = self._ledger.full(count)
        if full is None:
            return None
        k, wait = full.key, may_wait and count <= full.key.queue_size
        return Refusal(self.name, k.sub_id, full.queued, k.queue_size, count, wait=wait)

    def put_many(self, elements: tuple[DataObject, ...], now_ns: int) -> int:
        """Count stored elements (the caller checked ``admit``) and queue their notifications:
        one per registration, a batch if there are several. How many flow-controlled
        registrations were notified."""
        kept = tuple(
            [
                (e.timestamp_ns, e.metadata if len(e.metadata) <= INLINE_METADATA_MAX else None)
                for e in elements
            ]
        )
        flow = 0
        for send in self._ledger.put_many(kept, now_ns):
            flow += send.key.mode is SubscriptionMode.FLOW
            self._events.append(self._publish(send, elements))
        return flow

    def send_failed(self, key: RegistrationKey, epoch: str) -> None:
        """A notification did not leave: it stays outstanding and is resent at the next tick."""
        self._ledger.send_failed(key, epoch)

    def tick(self, now_ns: int) -> None:
        """Queue the resends that are due, at most ``RESEND_BURST`` per registration."""
        # The ledger hands over each due registration's whole window, oldest first: pace it.
        started: set[RegistrationKey] = set()
        for send in self._ledger.tick(now_ns):
            if send.key not in started:
                started.add(send.key)
                reg = self._ledger.get(send.key)
                if reg is not None:
                    if reg.acked == 0:
                        # Nothing acked yet: the greeting may be what was lost, and a flow
                        # subscription adopts a new epoch only after it (under a flood of
                        # made-up ones: ``SubscriberLedger``, rule 3).
                        self._control(
                            reg.key,
                            encode_control(
                                "hello", reg.key.descriptor, reg.epoch, reg.base, reg.since
                            ),
                        )
                    self._resend_from(reg, send.seq, now_ns)
        for key, (at, seq) in list(self._paced.items()):
            if at <= now_ns:
                del self._paced[key]
                reg = self._ledger.get(key)
                if reg is not None and reg.outstanding:
                    self._resend_from(reg, max(seq, reg.outstanding[0][0]), now_ns)

    def _resend_from(self, reg: Registration[_Kept], first: int, now_ns: int) -> None:
        sent = 0
        for seq, kept in reg.outstanding:
            if seq < first:
                continue
            if sent == RESEND_BURST:
                self._paced[reg.key] = (now_ns + RESEND_PACE_NS, seq)
                return
            again = Send(reg.key, reg.epoch, seq, reg.acked, (kept,), again=True, base=reg.base)
            self._events.append(self._publish(again, ()))
            sent += 1

    def next_deadline_ns(self) -> int | None:
        """When ``tick`` has work next (None: nothing outstanding)."""
        deadlines = [at for at, _ in self._paced.values()]
        if self._resync_at_ns is not None and not self._querying:
            deadlines.append(self._resync_at_ns)
        retransmit = self._ledger.next_retransmit_ns()
        if retransmit is not None:
            deadlines.append(retransmit)
        return min(deadlines, default=None)

    # -- output ----------------------------------------------------------------------------
    def events(self) -> list[Event]:
        """What to carry out, in order (each call hands over what accumulated since)."""
        events, self._events = self._events, []
        return events

    def _control(self, key: RegistrationKey, attachment: bytes) -> None:
        self._events.append(
            Publish(
                key,
                self._keys.notify(self._service, self._buffer, key.sub_id),  # no registration
                b"",
                attachment,
                block=False,
                epoch=None,
            )
        )

    def _notify_key(self, key: RegistrationKey) -> str:
        """A registration's notification key, formatted once (``_forget`` drops it)."""
        keyexpr = self._notify_keys.get(key)
        if keyexpr is None:
            keyexpr = self._keys.notify(self._service, self._buffer, key.sub_id)
            self._notify_keys[key] = keyexpr
        return keyexpr

    def _publish(self, send: Send[_Kept], elements: tuple[DataObject, ...]) -> Publish:
        """The wire form of ``send``: ``elements`` are the stored elements (with payloads)
        when it is a first send; a resend carries no payload (the subscriber fetches)."""
        key = send.key
        limit = self._push_limit.get(key, self.inline_max_bytes)
        block = key.mode is SubscriptionMode.FLOW
        if len(send.headers) > 1:
            payloads = [e.payload for e in elements]
            sizes = [len(p) for p in payloads]
            pushed = bool(sizes) and max(sizes) <= limit
            stamps, metas = zip(*send.headers, strict=True)
            header = encode_batch_header(
                send.epoch,
                send.seq,
                stamps,
                metas,
                sizes if pushed else None,
                acked=send.acked,
                descriptor=key.descriptor,
                base=send.base,
            )
            payload = b"".join(payloads) if pushed else b""
            return Publish(key, self._notify_key(key), payload, header, block, send.epoch)
        timestamp, metadata = send.headers[0]
        element = elements[0] if elements else None
        pushed = element is not None and not send.again and len(element.payload) <= limit
        header = encode_notification_header(
            send.epoch,
            send.seq,
            timestamp,
            metadata,
            pushed=pushed,
            acked=send.acked,
            descriptor=key.descriptor,
            base=send.base,
        )
        # The payload travels as the Zenoh payload itself: no copy into msgpack, and large
        # ones go through Zenoh's shared memory on one host.
        payload = element.payload if pushed and element is not None else b""
        return Publish(key, self._notify_key(key), payload, header, block, send.epoch)

    # -- reading ---------------------------------------------------------------------------
    def registrations(self) -> list[Registration[_Kept]]:
        return self._ledger.registrations()

    def get(self, key: RegistrationKey) -> Registration[_Kept] | None:
        return self._ledger.get(key)

    @property
    def foreign_acks(self) -> int:
        """Acks the ledger ignored: of no live registration (stale or forged), or beyond
        what was sent (``ProducerCounters``)."""
        return self._ledger.counters.foreign_acks

    def subscriptions(self) -> list[SubscriptionInfo]:
        out = []
        for reg in self._ledger.registrations():
            k, (node, host) = reg.key, self._holders.get(reg.key, (None, None))
            # An observer is never held back: sent - acked counts what it missed too, while
            # its queue holds at most N (flow control never exceeds N).
            queued = min(reg.queued, k.queue_size)
            out.append(
                SubscriptionInfo(k.sub_id, k.mode, k.queue_size, queued, reg.taken_ns, node, host)
            )
        return out

    def close(self) -> None:
        """Forget every registration; their publishers are retired."""
        for reg in self._ledger.clear():
            self._forget(reg.key)
            self._events.append(Retire(reg.key))

    def limits(self) -> BufferLimits:
        """The limits this producer applies to subscriptions, as ``info`` reports them."""
        return BufferLimits(
            flow_registrations=self._max[SubscriptionMode.FLOW],
            observe_registrations=self._max[SubscriptionMode.OBSERVE],
            queue_budget=self._shares.budget,
            flow_queue_max=fair_share(self._shares.budget, 0),
            large_push_per_holder=LARGE_PUSH_PER_HOLDER,
            large_push_total=LARGE_PUSH_TOTAL,
        )
