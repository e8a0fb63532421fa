"""Fuzz a live service with hostile input and check it answers and loses nothing.

    python -m tests.fuzz.run --cases 10000       # the benchmark-style run
    (tests/fuzz/test_fuzz.py runs a smaller number in CI)

Categories: malformed selectors and time ranges (raw Zenoh queries), hostile metadata,
wrong-typed fields and oversized payloads (put by the service process itself), garbage on
the notification, ack and subscription-token keys. Every so often the service must still
answer, with every accepted element byte-identical, and a legitimate subscriber still works.
"""

from __future__ import annotations

import argparse
import base64
import random
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import msgpack
import zenoh

from tests.conftest import NodeProcess, free_port
from tests.helpers.raw_zenoh import open_session
from tests.helpers.timing import scaled

SERVICE, BUFFER = "fz", "buf"
MAX_PAYLOAD = 1 << 20
# Deadlines, not speed goals: generous for a machine ten times slower than the development
# VM, and scaled by FRAMEGATE_TEST_TIMEOUT_SCALE (the node driver scales what it is sent).
TAKE_TIMEOUT_S = 30.0
QUERY_TIMEOUT_S = 30.0


@dataclass
class Tally:
    """What happened, per category."""

    counts: Counter[str] = field(default_factory=Counter)
    failures: list[str] = field(default_factory=list)

    def fail(self, what: str) -> None:
        self.counts["FAILURE"] += 1
        if len(self.failures) < 20:
            self.failures.append(what)


def _query(session: zenoh.Session, selector: Any, tally: Tally, what: str) -> None:
    replies = list(
        session.get(
            selector, consolidation=zenoh.ConsolidationMode.NONE, timeout=scaled(QUERY_TIMEOUT_S)
        )
    )
    if not replies:
        tally.counts["query-empty"] += 1  # e.g. a key no queryable matches
        return
    elements = 0
    for reply in replies:
        if reply.ok is not None:
            head = msgpack.unpackb(reply.ok.attachment.to_bytes())
            if "end" in head:  # an answer's last reply counts the elements before it
                if head != {"end": elements}:
                    tally.fail(f"{what}: end mark {head} after {elements} elements")
                continue
            elements += 1
            if not isinstance(head.get("t"), int):
                tally.fail(f"{what}: ok reply without a timestamp")
            tally.counts["query-answered"] += 1
        else:
            text = reply.err.payload.to_string()
            if text == "Timeout":
                tally.fail(f"{what}: timed out")
            elif not (text.startswith("bad-query: ") or text.startswith("not-found: ")):
                tally.fail(f"{what}: error without a named problem: {text!r}")
            else:
                tally.counts["query-rejected"] += 1


def run(cases: int, seed: int, endpoint: str | None = None) -> Tally:
    """Fuzz ``cases`` inputs; returns the tally (FAILURE count must be 0)."""
    from tests.fuzz import hostile

    rng = random.Random(seed)
    endpoint = endpoint or f"tcp/127.0.0.1:{free_port()}"
    service = NodeProcess(SERVICE, ["--listen", endpoint])
    tally = Tally()
    accepted: dict[int, bytes] = {}
    next_t = 1_000
    try:
        service.call(
            "offer",
            buffer=BUFFER,
            retention={"max_count": 100_000, "max_payload_bytes": MAX_PAYLOAD},
        )
        session = open_session(endpoint)
        legit = NodeProcess(None, ["--connect", endpoint])
        legit.call("subscribe", target=f"{SERVICE}/{BUFFER}", queue=100_000, mode="observe")
        # A flow subscriber that takes everything: forgeries must neither block the service
        # nor make it miss anything.
        flow = NodeProcess(None, ["--connect", endpoint])
        legit_id = flow.call("subscribe", target=f"{SERVICE}/{BUFFER}", queue=4)["id"]
        spied: list[str] = []  # the flow subscriber's epoch, as any peer can read it
        spy = session.declare_subscriber(
            f"framegate/@notify/{SERVICE}/{BUFFER}/{legit_id}",
            lambda sample: (
                spied.append(msgpack.unpackb(sample.attachment.to_bytes())[0])
                if sample.attachment is not None and len(spied) < 1000
                else None
            ),
        )
        base = f"framegate/{SERVICE}/{BUFFER}"
        for case in range(cases):
            kind = rng.random()
            if kind < 0.4:
                params = hostile.query_parameters(rng)
                key = (
                    base
                    if rng.random() < 0.8
                    else rng.choice(
                        [f"framegate/{SERVICE}/*", f"framegate/{SERVICE}/nope", "framegate/**"]
                    )
                )
                _query(session, zenoh.Selector(key, params), tally, f"query {key} {params}")
            elif kind < 0.75:
                doc, valid = hostile.metadata(rng, next_t)
                extra: dict[str, Any] = {}
                if rng.random() < 0.1:
                    extra = {"payload_size": rng.choice([MAX_PAYLOAD + 1, 3 * MAX_PAYLOAD])}
                    valid = False
                t: Any = next_t
                if rng.random() < 0.08:
                    t = rng.choice(["12", 1.5, None, -5, 2**64, True])
                    valid = False
                elif rng.random() < 0.05 and accepted:
                    t = max(accepted)  # duplicate
                    valid = False
                if rng.random() < 0.03:
                    extra = {"payload_raw": rng.choice([5, "text", [1, 2]])}
                    valid = False
                metadata_b64 = base64.b64encode(doc).decode()
                reply = service.call(
                    "put", buffer=BUFFER, t=t, metadata_b64=metadata_b64, wait_s=30, **extra
                )
                if reply["ok"]:
                    _flow_takes(flow, next_t, tally)
                    if not valid:
                        tally.fail(f"accepted hostile put: {doc[:80]!r} {extra} t={t!r}")
                    accepted[next_t] = b"p%d" % next_t
                    next_t += 1_000
                    tally.counts["put-accepted"] += 1
                elif valid:
                    tally.fail(f"refused a valid put: {reply}")
                elif not reply.get("message"):
                    tally.fail(f"rejection without a message: {reply}")
                else:
                    tally.counts["put-rejected"] += 1
            elif kind < 0.85:
                target = rng.choice(["@ack", "@notify"])
                sub_id = rng.choice(
                    ["x", "0" * 12, legit_id, "".join(rng.choices("abcdef0123456789", k=12))]
                )
                session.put(
                    f"framegate/{target}/{SERVICE}/{BUFFER}/{sub_id}", hostile.control_message(rng)
                )
                if rng.random() < 0.2:
                    # Four segments after the id, as the token parser expects: it must see it.
                    suffix, _valid = hostile.token_suffix(rng)
                    token = session.liveliness().declare_token(
                        f"framegate/@sub/{SERVICE}/{BUFFER}/{sub_id}/{suffix}"
                    )
                    token.undeclare()
                    tally.counts["tokens-sent"] += 1
                tally.counts["garbage-sent"] += 1
            else:
                # Protocol-valid forgeries aimed at the legitimate flow subscriber.
                epoch = spied[-1] if spied else None
                if rng.random() < 0.6:
                    session.put(
                        f"framegate/@notify/{SERVICE}/{BUFFER}/{legit_id}",
                        b"forged",
                        attachment=hostile.forged_notification(rng, epoch, "flow/4/-1"),
                    )
                else:
                    session.put(
                        f"framegate/@ack/{SERVICE}/{BUFFER}/{legit_id}",
                        hostile.forged_ack(rng, epoch),
                    )
                tally.counts["forgeries-sent"] += 1
            if case % 250 == 249 or case == cases - 1:
                _health(service, accepted, tally)
        legit_stats = legit.call("take", target=f"{SERVICE}/{BUFFER}", timeout=TAKE_TIMEOUT_S)
        if not legit_stats["ok"]:
            tally.fail(f"the legitimate subscriber's take failed: {legit_stats}")
        elif accepted and legit_stats["notification"] is None:
            tally.fail("the legitimate subscriber received nothing")
        flow_stats = flow.call("stats", target=f"{SERVICE}/{BUFFER}")
        if flow_stats["missed_total"]:
            tally.fail(f"the flow subscriber missed {flow_stats['missed_total']}")
        spy.undeclare()
        flow.close()
        legit.close()
        session.close()
    finally:
        alive = service.proc.poll() is None
        if not alive:
            tally.counts["crashes"] += 1
            tally.fail(f"service process died with {service.proc.returncode}")
        service.close()
    return tally


def _flow_takes(flow: NodeProcess, t: int, tally: Tally) -> None:
    """The flow subscriber takes notifications until element ``t``'s; forged ones may come
    first (the trusted profile cannot tell them), real ones must come in order, unmissed."""
    while True:
        took = flow.call("take", target=f"{SERVICE}/{BUFFER}", timeout=TAKE_TIMEOUT_S)
        if not took["ok"]:
            if took["error"] == "NotFoundError":
                # Taken, then not found: a forged notification of an element the service
                # never stored (real ones are all retained); the trusted profile lets it in.
                tally.counts["forgery-taken"] += 1
                continue
            tally.fail(f"the flow subscriber's take failed waiting for element {t}: {took}")
            return
        note = took["notification"]
        if note is None:
            tally.fail(
                f"the flow subscriber got no notification within {scaled(TAKE_TIMEOUT_S):g} s"
                f" while waiting for element {t}"
            )
            return
        if note["missed"]:
            tally.fail(f"the flow subscriber reported {note['missed']} missed")
        if note["t"] == t:
            tally.counts["flow-taken"] += 1
            return
        if note["t"] % 2:
            tally.counts["forgery-taken"] += 1  # not one of ours: a forgery reached it
        else:
            tally.fail(f"the flow subscriber got element {note['t']} while waiting for {t}")


def _health(service: NodeProcess, accepted: dict[int, bytes], tally: Tally) -> None:
    """The service answers and every accepted element is intact."""
    if service.proc.poll() is not None:
        tally.fail("service died")
        return
    reply = service.call("query", target=f"{SERVICE}/{BUFFER}")
    got = {e["t"]: base64.b64decode(e["payload"]) for e in reply.get("elements", [])}
    if got != accepted:
        tally.fail(f"elements differ: {len(got)} stored vs {len(accepted)} accepted")
    tally.counts["health-checks"] += 1


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=10_000)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    started = time.monotonic()
    tally = run(args.cases, args.seed)
    elapsed = time.monotonic() - started
    print(f"{args.cases} cases in {elapsed:.1f} s (seed {args.seed})")
    for name, count in sorted(tally.counts.items()):
        print(f"  {name:<16} {count}")
    for failure in tally.failures:
        print("  !", failure)
    return 1 if tally.counts["FAILURE"] else 0


if __name__ == "__main__":
    sys.exit(main())
