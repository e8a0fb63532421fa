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

The flood cases (``FLOOD_CASES``) add a flow-controlled consumer that takes every frame
(``fg-sub``) and measure what reaches it, alone and then while ``flood`` workers
(``_floods``) attack the producer's control keys: 16-byte garbage acks from 4 processes,
1 MiB garbage acks from 2, forged but valid-looking acks (a subscriber's own last ack,
repeated) from 2, token churn from 2, and a greedy subscriber (one token asking for the
largest queue a holder may get, never taking). Reported: the consumer's delivered rate
under attack as a share of its delivered rate alone (goal >= ``RATE_GOAL``), and the
camera's RSS growth against the same allowance.

Reported per case: the camera's achieved rate as a share of nominal (goal >= ``RATE_GOAL``)
and its RSS growth from just after ``offer`` to the maximum seen while attacked, against an
allowance of the retention's bytes plus the headers the producer states it may keep for
un-acked notifications (its queue budget, where the middleware exports it). The control
window's rate and growth are reported alongside, without a goal.
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


@dataclass(frozen=True, slots=True)
class Case:
    name: str
    label: str
    tokens: int
    queue_size: int

    def as_json(self) -> dict[str, Any]:
        return {"tokens": self.tokens, "queue_size": self.queue_size, "label": self.label}


CASES = (
    Case("tokens", f"{HOSTILE_TOKENS} tokens q=2^20", HOSTILE_TOKENS, 1 << 20),
    Case("subscriber", "never-taking sub q=10^6", 1, 10**6),
)


@dataclass(frozen=True, slots=True)
class FloodCase:
    """A flood on the camera's control keys beside a consumer that takes every frame."""

    name: str
    label: str
    processes: int
    # The flood worker's parameters (``_floods``), or None for the greedy subscriber.
    flood: dict[str, Any] | None

    def as_json(self) -> dict[str, Any]:
        return {"label": self.label, "processes": self.processes, "flood": self.flood}


FLOOD_CASES = (
    FloodCase("acks-16", "16 B acks x 4 processes", 4, {"kind": "acks", "size": 16}),
    FloodCase("acks-1m", "1 MiB acks x 2 processes", 2, {"kind": "acks", "size": 1 << 20}),
    FloodCase("forged-acks", "forged valid acks x 2", 2, {"kind": "forged-acks"}),
    FloodCase("churn", "token churn x 2 processes", 2, {"kind": "churn", "batch": 8}),
    FloodCase("greedy", "greedy never-taking sub q=2^14", 1, None),
)
# The greedy subscriber's queue: what its holder may get beside the consumer (it takes
# nothing, so the producer keeps a header per frame for it, within the window).
GREEDY_QUEUE = middleware.FLOW_QUEUE_MAX // 2
# Zenoh's shared-memory pool on one host (its default size).
SHM_POOL_BYTES = 16 * 1024 * 1024
# The consumer's queue (frames) and how long the flood runs before the window opens.
CONSUMER_QUEUE = 4
FLOOD_WARMUP_S = 1.0


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
    }


def _rows(case: Case, allowance_mb: float) -> tuple[Row, Row]:
    rate = Row(f"camera + {case.label}", "rate / nominal", "share", True, raw=None)
    rss = Row(f"camera + {case.label}: RSS", "RSS growth", "MB", False, raw=None)
    rss.note = (
        f"camera: {FRAME_BYTES / MB:.2f} MB frames at {CAMERA_HZ:g} Hz, retention "
        f"{RETAIN_FRAMES} frames; RSS growth from offer to the maximum while attacked, "
        f"allowance {allowance_mb:.0f} MB = retention + {FRAMES_IN_FLIGHT} frames in flight + "
        "the producer's stated caps (its queue budget of kept headers, where exported)"
    )
    return rate, rss


def run_hostile(options: BenchOptions) -> ScenarioResult:
    window_s = options.hostile_s
    control = control_s(window_s)
    metadata_bytes = len(middleware.make_metadata("generic", 0))
    allowance = allowance_bytes(metadata_bytes)
    cap = kept_headers_cap(metadata_bytes)
    namespace = NetworkConfig().namespace
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
            "cases": {case.name: case.as_json() for case in CASES},
            "allowance_bytes": allowance,
            "kept_headers_cap_bytes": cap,
            "allowance": f"(retention + {FRAMES_IN_FLIGHT} frames in flight) x frame bytes "
            f"+ queue budget x (metadata + {KEPT_HEADER_OVERHEAD_BYTES} B)"
            + ("" if cap is not None else "; the middleware exports no QUEUE_BUDGET: 0"),
        },
    )
    alone = Row(f"camera {CAMERA_HZ:g} Hz alone", "rate / nominal", "share", True, raw=None)
    alone_rss = Row(f"camera {CAMERA_HZ:g} Hz alone: RSS", "RSS growth", "MB", False, raw=None)
    rows: list[Row] = []
    for case in CASES:
        rate, rss = _rows(case, allowance / MB)
        for pair in range(HOSTILE_RUNS):
            with WorkerGroup() as group:
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
                before = camera_sample(camera.call("run", control + 60.0, seconds=control), pair)
                alone.framegate.append(before)
                alone_rss.framegate.append({"pair": pair, "value": before["rss_growth_mb"]})
                hostile = group.start(
                    "raw-hostile",
                    {
                        "connect": at,
                        "namespace": namespace,
                        "service": "bench",
                        "buffer": "images",
                        "tokens": case.tokens,
                        "queue_size": case.queue_size,
                        "listen_notify": True,
                    },
                )
                group.wait_ready()
                during = camera_sample(camera.call("run", window_s + 60.0, seconds=window_s), pair)
                during["hostile_notifications"] = int(hostile.call("mark")["count"])
                during["rss_growth_beyond_alone_mb"] = (
                    during["rss_growth_mb"] - before["rss_growth_mb"]
                )
                rate.framegate.append(during)
                rss.framegate.append({"pair": pair, "value": during["rss_growth_mb"]})
            options.progress(
                f"hostile {case.name}: alone "
                f"{before['rate_hz']:.1f} Hz; attacked {during['rate_hz']:.1f} Hz "
                f"({during['value']:.2f} of nominal), RSS +{during['rss_growth_mb']:.0f} MB, "
                f"{during['refused_subscriptions']} refused registrations, "
                f"{during['hostile_notifications']} notifications to the hostile peer"
            )
        rate.goal = Goal(
            f"rate >= {RATE_GOAL:g} of nominal", RATE_GOAL, True, rate.median("framegate")
        )
        rss.goal = Goal(
            f"RSS growth <= {allowance / MB:.1f} MB",
            round(allowance / MB, 1),
            False,
            rss.median("framegate"),
        )
        rows += [rate, rss]
    for flood_case in FLOOD_CASES:
        rows += _flood_rows(options, flood_case, window_s, control, allowance, namespace)
    result.params["flood_cases"] = {c.name: c.as_json() for c in FLOOD_CASES}
    result.rows = [alone, alone_rss, *rows]
    return result


def _delivered(camera: Any, consumer: Any, seconds: float, pair: int) -> dict[str, Any]:
    """Run the camera for ``seconds``: its sample, plus what reached the consumer."""
    before = consumer.call("mark")
    sample = camera_sample(camera.call("run", seconds + 60.0, seconds=seconds), pair)
    after = consumer.call("mark")
    elapsed_s = (int(after["t_ns"]) - int(before["t_ns"])) / 1e9
    sample["delivered"] = int(after["count"]) - int(before["count"])
    sample["delivered_hz"] = sample["delivered"] / elapsed_s if elapsed_s > 0 else 0.0
    return sample


def _flood_rows(
    options: BenchOptions,
    case: FloodCase,
    window_s: float,
    control: float,
    allowance: int,
    namespace: str,
) -> list[Row]:
    rate = Row(f"camera + {case.label}: delivered", "delivered / alone", "share", True, raw=None)
    rss = Row(f"camera + {case.label}: RSS", "RSS growth", "MB", False, raw=None)
    # A consumer that takes pushed frames on this host receives them through Zenoh's shared
    # memory pool, which the camera's process maps: part of its RSS while it has a consumer.
    allowance += SHM_POOL_BYTES
    rss.note = (
        f"allowance {allowance / MB:.0f} MB: as for the cases above, plus Zenoh's "
        f"{SHM_POOL_BYTES / MB:.0f} MB shared-memory pool (a consumer takes pushed frames); "
        "the sample also has the growth in the same case's window alone"
    )
    for pair in range(HOSTILE_RUNS):
        with WorkerGroup() as group:
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
            consumer = group.start(
                "fg-sub",
                {"connect": at, "buffer": "images", "queue_size": CONSUMER_QUEUE, "push": True},
            )
            group.wait_ready()
            alone = _delivered(camera, consumer, control, pair)
            common = {"connect": at, "namespace": namespace, "service": "bench"}
            for _ in range(case.processes):
                if case.flood is None:
                    params = {**common, "buffer": "images", "tokens": 1}
                    group.start("raw-hostile", {**params, "queue_size": GREEDY_QUEUE})
                else:
                    group.start("flood", {**common, "buffer": "images", **case.flood})
            group.wait_ready()
            time.sleep(FLOOD_WARMUP_S)
            during = _delivered(camera, consumer, window_s, pair)
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
        options.progress(
            f"hostile {case.name}: delivered {alone['delivered_hz']:.1f} Hz alone, "
            f"{during['delivered_hz']:.1f} Hz attacked ({share:.2f}), "
            f"RSS +{during['rss_growth_mb']:.0f} MB"
        )
    rate.goal = Goal(
        f"delivered >= {RATE_GOAL:g} of alone", RATE_GOAL, True, rate.median("framegate")
    )
    rss.goal = Goal(
        f"RSS growth <= {allowance / MB:.1f} MB",
        round(allowance / MB, 1),
        False,
        rss.median("framegate"),
    )
    return [rate, rss]
