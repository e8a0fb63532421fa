"""``hostile``: a camera-like producer under peers that ask for everything and take nothing.

A framegate producer puts 1280×1024 mono8 frames (1.3 MB, a fresh ``bytes`` each) at
``CAMERA_HZ`` without waiting, into a buffer retaining ``RETAIN_FRAMES`` frames. In each
case it first runs alone for a short control window, then a hostile peer speaking the wire
with plain Zenoh (``_raw.raw_hostile``) joins and the camera runs for the measured window
(``--duration``; 2 minutes by default; one run per case):

- ``tokens``: ``HOSTILE_TOKENS`` flow-control subscription tokens asking for a queue of
  2^20 each, whose notifications are received and never acknowledged;
- ``subscriber``: one flow-control subscriber asking for a queue of 10^6 that never takes
  (its notifications are received, never acknowledged).

The cases with a consumer (``ATTACKS``, ``consumer=True``) add a flow-controlled consumer
that takes every frame (``fg-sub``) and measure what reaches it, alone and then while
``flood`` workers (``_floods``) attack the producer's control keys: 16-byte garbage acks
from 4 processes, 1 MiB garbage acks from 2, forged but valid-looking acks (a subscriber's
own last ack, repeated) from 2, churn of observe tokens and of flow tokens from 2 each, and a
greedy subscriber (one token asking for the largest queue a holder may get, never taking).
The flooders run at ``FLOOD_NICE`` (see there). Reported: the consumer's delivered rate
under attack as a share of its delivered rate alone (goal >= ``RATE_GOAL``; none for
flow-token churn: ``CHURN_FLOW_NOTE``), the flood's rate, the camera's CPU alone and
attacked, and the camera's RSS growth against the same allowance.

Reported per case without one: the camera's achieved rate as a share of nominal (goal >=
``RATE_GOAL``) and its RSS growth from just after ``offer`` to the maximum seen while
attacked, against an allowance of the retention's bytes plus the headers the producer states
it may keep for un-acked notifications (its queue budget, where the middleware exports it).
The control window's rate and growth are reported alongside, without a goal.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import middleware
from middleware import NetworkConfig

from ._options import BenchOptions
from ._procs import WorkerGroup, free_endpoint
from ._records import Goal, Row, ScenarioResult

FRAME_BYTES = 1280 * 1024
CAMERA_HZ = 15.0
RETAIN_FRAMES = 32
RATE_GOAL = 0.9
HOSTILE_TOKENS = 300
# Longest control window (camera alone) before the hostile peer joins.
CONTROL_MAX_S = 10.0
# A kept header beyond its metadata: the Python objects that hold it (generous).
KEPT_HEADER_OVERHEAD_BYTES = 512
# Frames a camera holds beyond retention at a moment: the one being made and the one that
# retention evicts as the new one is stored.
FRAMES_IN_FLIGHT = 2
MB = 1e6
# Runs per case: the window is long (minutes), so one run each, not --pairs.
HOSTILE_RUNS = 1


# The flooders' niceness. On this one machine the flooders' busy loops would otherwise take
# the camera's CPU (4 of them on 2 cores: the camera fell to ~0.3 of its rate alone with the
# same flood aimed at a key nobody subscribes to, i.e. with nothing reaching it); a remote
# attacker's CPU is not the producer's. At 19 they take the CPU the camera leaves, and what
# is measured is what receiving and dropping the flood costs the producer. The flood's rate
# is reported beside each row (``flood_msgs_s``) so that a flood starved of CPU shows.
FLOOD_NICE = 19


# The greedy subscriber's queue: what its holder may get beside the consumer (it takes
# nothing, so the producer keeps a header per frame for it, within the window).
GREEDY_QUEUE = middleware.FLOW_QUEUE_MAX // 2


@dataclass(frozen=True, slots=True)
class Attack:
    """One case of the table: the workers that attack the camera, and what is measured."""

    name: str
    label: str
    worker: str  # "raw-hostile" (tokens, ``_raw``) or "flood" (``_floods``)
    params: dict[str, Any]  # the worker's parameters beside where it connects
    processes: int = 1
    # With a consumer that takes every frame, what reaches it under attack is measured as a
    # share of what reached it alone; without one, the camera's rate as a share of nominal.
    consumer: bool = False
    # Whether the rate row has a goal (``CHURN_FLOW_NOTE``: one that measures the attacker).
    goal: bool = True

    def as_json(self) -> dict[str, Any]:
        return {
            "label": self.label,
            "worker": self.worker,
            "processes": self.processes,
            "consumer": self.consumer,
            "goal": self.goal,
            **self.params,
        }


def _tokens(
    name: str, label: str, tokens: int, queue_size: int, *, consumer: bool = False
) -> Attack:
    """Flow-control registrations that never take; beside no consumer, their notifications
    are received too (and counted), never acknowledged."""
    params = {"tokens": tokens, "queue_size": queue_size, "listen_notify": not consumer}
    return Attack(name, label, "raw-hostile", params, consumer=consumer)


def _flood(name: str, label: str, processes: int, *, goal: bool = True, **flood: Any) -> Attack:
    """Workers flooding the camera's control keys, beside a consumer; at ``FLOOD_NICE``."""
    params = {"nice": FLOOD_NICE, **flood}
    return Attack(name, label, "flood", params, processes, consumer=True, goal=goal)


# Why the flow-token churn row has no rate goal. A flow-controlled registration that never
# takes stops the source once its queue is full, for as long as its token lives: that is the
# paper's buffering rule, not a cost of the producer, so the rate under flow-token churn
# measures how long the attacker keeps its tokens alive (a churner descheduled between
# declaring and withdrawing 8 tokens holds the camera for that long), not the producer.
# What the producer owes there is checked elsewhere: no element lost uncounted (the
# sequence-checking subscriber of the hostile-peer tests) and bounded work (the camera's CPU,
# reported here). The rate goal is on the observe-token churn row, whose tokens may never
# hold the producer: its share is the cost of the churn itself (liveliness events,
# registrations made and retired, their greetings).
CHURN_FLOW_NOTE = (
    "no goal: a live flow registration that never takes stops the source by the buffering "
    "rule once its queue is full, so this share measures the churned tokens' lifetime; the "
    "goal is on the observe-token churn row (tokens that can never hold the producer)"
)


ATTACKS = (
    _tokens("tokens", f"{HOSTILE_TOKENS} tokens q=2^20", HOSTILE_TOKENS, 1 << 20),
    _tokens("subscriber", "never-taking sub q=10^6", 1, 10**6),
    _flood("acks-16", "16 B acks x 4 processes", 4, kind="acks", size=16),
    _flood("acks-1m", "1 MiB acks x 2 processes", 2, kind="acks", size=1 << 20),
    _flood("forged-acks", "forged valid acks x 2", 2, kind="forged-acks"),
    _flood("churn", "observe-token churn x 2", 2, kind="churn", batch=8, mode="observe"),
    _flood("churn-flow", "flow-token churn x 2", 2, goal=False, kind="churn", batch=8),
    _tokens("greedy", "greedy never-taking sub q=2^14", 1, GREEDY_QUEUE, consumer=True),
)
# Zenoh's shared-memory pool on one host (its default size).
SHM_POOL_BYTES = 16 * 1024 * 1024
# The consumer's queue (frames) and how long the flood runs before the window opens.
CONSUMER_QUEUE = 4
FLOOD_WARMUP_S = 1.0
# Floods that a plain Zenoh process can receive in the producer's place (the others need a
# producer's notifications or registrations to act on).
SINK_KINDS = ("acks", "churn")
# Floods whose every message the camera drops as it comes (counted in ``dropped_messages``):
# their rows report the camera's CPU per dropped message. Under churn that count is only an
# overflowing token inbox's, or an honest consumer's repeated ack: no per-message cost.
DROPPED_KINDS = ("acks", "forged-acks")


def control_s(window_s: float) -> float:
    """The camera's control window before the hostile peer joins: enough to fill retention
    (``RETAIN_FRAMES`` at ``CAMERA_HZ``) but at most CONTROL_MAX_S."""
    fill_s = RETAIN_FRAMES / CAMERA_HZ + 0.5
    return max(fill_s, min(CONTROL_MAX_S, window_s / 4))


def kept_headers_cap(metadata_bytes: int) -> int | None:
    """Bytes the producer may keep for un-acked notifications: its queue budget (headers
    without payload) times a header's size; None when the middleware does not export it."""
    budget = getattr(middleware, "QUEUE_BUDGET", None)
    if budget is None:
        return None
    return int(budget) * (metadata_bytes + KEPT_HEADER_OVERHEAD_BYTES)


def allowance_bytes(metadata_bytes: int) -> int:
    """Retention (plus the frames in flight) and the stated caps: what the camera's RSS may
    grow by."""
    frames = (RETAIN_FRAMES + FRAMES_IN_FLIGHT) * FRAME_BYTES
    return frames + (kept_headers_cap(metadata_bytes) or 0)


def camera_sample(answer: dict[str, Any], pair: int) -> dict[str, Any]:
    """A camera ``run`` answer as a sample: value = achieved rate / nominal."""
    return {
        "pair": pair,
        "value": float(answer["rate_hz"]) / CAMERA_HZ,
        "rss_growth_mb": (int(answer["rss_max"]) - int(answer["rss_offered"])) / MB,
        "private_growth_mb": int(answer.get("private_growth", 0)) / MB,
        "shared_growth_mb": int(answer.get("shared_growth", 0)) / MB,
        **{
            key: answer[key]
            for key in (
                "ticks",
                "stored",
                "refused",
                "late",
                "failed",
                "errors",
                "elapsed_s",
                "rate_hz",
                "subscriptions",
                "refused_subscriptions",
                "buffer_bytes",
            )
        },
        **{key: answer[key] for key in ("dropped_messages",) if key in answer},
    }


def run_hostile(options: BenchOptions) -> ScenarioResult:
    window_s = options.hostile_s
    control = control_s(window_s)
    metadata_bytes = len(middleware.make_metadata("generic", 0))
    allowance = allowance_bytes(metadata_bytes)
    cap = kept_headers_cap(metadata_bytes)
    result = ScenarioResult(
        "hostile",
        params={
            "window_s": window_s,
            "control_s": control,
            "camera": {
                "frame_bytes": FRAME_BYTES,
                "rate_hz": CAMERA_HZ,
                "retain_frames": RETAIN_FRAMES,
                "put": "wait_s=0; a frame more than a period late is skipped",
            },
            "cases": {attack.name: attack.as_json() for attack in ATTACKS},
            "allowance_bytes": allowance,
            "kept_headers_cap_bytes": cap,
            "allowance": f"(retention + {FRAMES_IN_FLIGHT} frames in flight) x frame bytes "
            f"+ queue budget x (metadata + {KEPT_HEADER_OVERHEAD_BYTES} B)"
            + ("" if cap is not None else "; the middleware exports no QUEUE_BUDGET: 0"),
        },
    )
    alone = Row(f"camera {CAMERA_HZ:g} Hz alone", "rate / nominal", "share", True, raw=None)
    alone_rss = Row(f"camera {CAMERA_HZ:g} Hz alone: RSS", "RSS growth", "MB", False, raw=None)
    windows = _Windows(options, window_s, control, NetworkConfig().namespace)
    rows: list[Row] = []
    for attack in ATTACKS:
        if attack.consumer:
            rows += _delivered_rows(windows, attack, allowance)
        else:
            rows += _camera_rows(windows, attack, allowance, alone, alone_rss)
    result.rows = [alone, alone_rss, *rows]
    return result


@dataclass(frozen=True, slots=True)
class _Windows:
    """What every attack's run shares: the windows, the namespace, where progress goes."""

    options: BenchOptions
    window_s: float
    control_s: float
    namespace: str


def _start_camera(group: WorkerGroup, consumer: bool) -> tuple[str, Any, Any]:
    """The camera and, if asked, a consumer that takes every frame, ready: (endpoint,
    camera, consumer or None)."""
    at = free_endpoint()
    camera = group.start(
        "fg-camera",
        {
            "listen": at,
            "size": FRAME_BYTES,
            "rate_hz": CAMERA_HZ,
            "retain": RETAIN_FRAMES,
            "buffer": "images",
        },
    )
    group.wait_ready()
    if not consumer:
        return at, camera, None
    taker = group.start(
        "fg-sub", {"connect": at, "buffer": "images", "queue_size": CONSUMER_QUEUE, "push": True}
    )
    group.wait_ready()
    return at, camera, taker


def _start_attack(group: WorkerGroup, attack: Attack, at: str, namespace: str) -> list[Any]:
    """The attack's workers, ready."""
    params = {"connect": at, "namespace": namespace, "service": "bench", "buffer": "images"}
    workers = [
        group.start(attack.worker, {**params, **attack.params}) for _ in range(attack.processes)
    ]
    group.wait_ready()
    return workers


def _camera_rows(
    run: _Windows, attack: Attack, allowance: int, alone: Row, alone_rss: Row
) -> list[Row]:
    """An attack without a consumer: the camera's rate and RSS growth under it."""
    label = attack.label
    rate = Row(f"camera + {label}", "rate / nominal", "share", True, raw=None)
    rss = Row(f"camera + {label}: RSS", "RSS growth", "MB", False, raw=None)
    rss.note = (
        f"camera: {FRAME_BYTES / MB:.2f} MB frames at {CAMERA_HZ:g} Hz, retention "
        f"{RETAIN_FRAMES} frames; RSS growth from offer to the maximum while attacked, "
        f"allowance {allowance / MB:.0f} MB = retention + {FRAMES_IN_FLIGHT} frames in flight + "
        "the producer's stated caps (its queue budget of kept headers, where exported)"
    )
    for pair in range(HOSTILE_RUNS):
        with WorkerGroup() as group:
            at, camera, _ = _start_camera(group, consumer=False)
            before = _camera_run(camera, run.control_s, pair)
            alone.framegate.append(before)
            alone_rss.framegate.append({"pair": pair, "value": before["rss_growth_mb"]})
            workers = _start_attack(group, attack, at, run.namespace)
            during = _camera_run(camera, run.window_s, pair)
            if attack.params.get("listen_notify"):
                during["hostile_notifications"] = sum(int(w.call("mark")["count"]) for w in workers)
            during["rss_growth_beyond_alone_mb"] = during["rss_growth_mb"] - before["rss_growth_mb"]
            rate.framegate.append(during)
            rss.framegate.append({"pair": pair, "value": during["rss_growth_mb"]})
        run.options.progress(
            f"hostile {attack.name}: alone "
            f"{before['rate_hz']:.1f} Hz; attacked {during['rate_hz']:.1f} Hz "
            f"({during['value']:.2f} of nominal), RSS +{during['rss_growth_mb']:.0f} MB, "
            f"{during['refused_subscriptions']} refused registrations, "
            f"{during.get('hostile_notifications', 0)} notifications to the hostile peer"
        )
    rate.goal = Goal(f"rate >= {RATE_GOAL:g} of nominal", RATE_GOAL, True, rate.median("framegate"))
    rss.goal = _rss_goal(rss, allowance)
    return [rate, rss]


def _delivered_rows(run: _Windows, attack: Attack, allowance: int) -> list[Row]:
    """An attack beside a consumer: what reaches the consumer, and the camera's RSS."""
    label = attack.label
    rate = Row(f"camera + {label}: delivered", "delivered / alone", "share", True, raw=None)
    sinkable = attack.worker == "flood" and attack.params["kind"] in SINK_KINDS
    rss = Row(f"camera + {label}: RSS", "RSS growth", "MB", False, raw=[] if sinkable else None)
    # A consumer that takes pushed frames on this host receives them through Zenoh's shared
    # memory pool, which the camera's process maps: part of its RSS while it has a consumer.
    allowance += SHM_POOL_BYTES
    rss.note = (
        f"allowance {allowance / MB:.0f} MB: as for the cases above, plus Zenoh's "
        f"{SHM_POOL_BYTES / MB:.0f} MB shared-memory pool (a consumer takes pushed frames), "
        "plus Zenoh's own share under the same flood: raw = the RSS growth of a plain Zenoh "
        "process that receives the flood on the same keys and drops it at once (its receive "
        "buffers and each flooding peer's shared-memory pool, mapped)"
    )
    for pair in range(HOSTILE_RUNS):
        with WorkerGroup() as group:
            at, camera, consumer = _start_camera(group, consumer=True)
            alone = _delivered(camera, consumer, run.control_s, pair)
            workers = _start_attack(group, attack, at, run.namespace)
            time.sleep(FLOOD_WARMUP_S)
            sent = _sent(attack, workers)
            during = _delivered(camera, consumer, run.window_s, pair)
            if sent is not None:
                flood_sent = (_sent(attack, workers) or 0) - sent
                during["flood_msgs_s"] = flood_sent / during["elapsed_s"]
            _cost_per_drop(during, alone, attack.params.get("kind") in DROPPED_KINDS)
            share = during["delivered_hz"] / alone["delivered_hz"] if alone["delivered_hz"] else 0
            during.update(value=share, alone_delivered_hz=alone["delivered_hz"])
            rate.framegate.append(during)
            rss.framegate.append(
                {
                    "pair": pair,
                    "value": during["rss_growth_mb"],
                    "alone_mb": alone["rss_growth_mb"],
                    "beyond_alone_mb": during["rss_growth_mb"] - alone["rss_growth_mb"],
                }
            )
        cost = during.get("cpu_us_per_dropped")
        run.options.progress(
            f"hostile {attack.name}: delivered {alone['delivered_hz']:.1f} Hz alone, "
            f"{during['delivered_hz']:.1f} Hz attacked ({share:.2f}) by "
            f"{during.get('flood_msgs_s', 0):.0f} msg/s; camera CPU {alone['cpu_pct']:.0f} % "
            f"alone, {during['cpu_pct']:.0f} % attacked, {during['dropped_in_window']} dropped"
            + (f" ({cost:.1f} us each); " if cost is not None else "; ")
            + f"RSS +{during['rss_growth_mb']:.0f} MB (private +{during['private_growth_mb']:.0f}, "
            f"shared +{during['shared_growth_mb']:.0f}; alone: +{alone['private_growth_mb']:.0f}, "
            f"+{alone['shared_growth_mb']:.0f})"
        )
        if sinkable:
            rss.raw = [_transport_share(attack, run.window_s, run.namespace, pair)]
    if attack.goal:
        rate.goal = Goal(
            f"delivered >= {RATE_GOAL:g} of alone", RATE_GOAL, True, rate.median("framegate")
        )
    else:
        rate.note = CHURN_FLOW_NOTE
    transport = rss.median("raw") or 0.0
    rss.goal = _rss_goal(rss, allowance, transport=transport if sinkable else None)
    return [rate, rss]


def _transport_share(attack: Attack, window_s: float, namespace: str, pair: int) -> dict[str, Any]:
    """The same flood against a plain Zenoh process that drops it (``flood-sink``): what
    Zenoh itself holds for it, which no application on top can bound."""
    with WorkerGroup() as group:
        at = free_endpoint()
        where = {"namespace": namespace, "service": "bench", "buffer": "images"}
        sink = group.start("flood-sink", {"listen": at, **where})
        group.wait_ready()
        for _ in range(attack.processes):
            group.start("flood", {"connect": at, **where, **attack.params})
        group.wait_ready()
        time.sleep(FLOOD_WARMUP_S)
        # Growth from before the flood (the sink's ``ready``), as the camera's is from its offer.
        answer = sink.call("run", window_s + 60.0, seconds=window_s)
    return {
        "pair": pair,
        "value": int(answer["growth"]) / MB,
        "private_growth_mb": int(answer["private_growth"]) / MB,
        "shared_growth_mb": int(answer["shared_growth"]) / MB,
    }


def _rss_goal(rss: Row, allowance: int, *, transport: float | None = None) -> Goal:
    """RSS growth within ``allowance``, plus Zenoh's own measured share (MB) where given."""
    limit = allowance / MB + (transport or 0.0)
    return Goal(
        f"RSS growth <= {limit:.1f} MB"
        + (f" ({allowance / MB:.1f} + Zenoh's {transport:.1f})" if transport is not None else ""),
        round(limit, 1),
        False,
        rss.median("framegate"),
    )


def _camera_run(camera: Any, seconds: float, pair: int) -> dict[str, Any]:
    return camera_sample(camera.call("run", seconds + 60.0, seconds=seconds), pair)


def _cost_per_drop(during: dict[str, Any], alone: dict[str, Any], per_message: bool) -> None:
    """The control messages the camera dropped in the window (garbage, repeats, oversize,
    overflow: counted as ``dropped_messages``) and, for a flood made of them
    (``per_message``), its CPU beyond its CPU alone per dropped message, in us."""
    dropped = int(during.get("dropped_messages", 0)) - int(alone.get("dropped_messages", 0))
    during["dropped_in_window"] = dropped
    if per_message and dropped > 0:
        extra_s = (during["cpu_pct"] - alone["cpu_pct"]) / 100.0 * during["elapsed_s"]
        during["cpu_us_per_dropped"] = 1e6 * extra_s / dropped


def _sent(attack: Attack, workers: list[Any]) -> int | None:
    """What the flood workers have sent so far (messages or tokens); None for other workers."""
    if attack.worker != "flood":
        return None
    return sum(int(worker.call("count")["count"]) for worker in workers)


def _delivered(camera: Any, consumer: Any, seconds: float, pair: int) -> dict[str, Any]:
    """Run the camera for ``seconds``: its sample (with its CPU use, % of one core), plus what
    reached the consumer."""
    before = consumer.call("mark")
    cpu_s = camera.cpu_s()
    sample = _camera_run(camera, seconds, pair)
    sample["cpu_pct"] = 100.0 * (camera.cpu_s() - cpu_s) / max(sample["elapsed_s"], 1e-9)
    after = consumer.call("mark")
    elapsed_s = (int(after["t_ns"]) - int(before["t_ns"])) / 1e9
    sample["delivered"] = int(after["count"]) - int(before["count"])
    sample["delivered_hz"] = sample["delivered"] / elapsed_s if elapsed_s > 0 else 0.0
    return sample
