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

Reported per case: the camera's achieved rate as a share of nominal (goal >= ``RATE_GOAL``)
and its RSS growth from just after ``offer`` to the maximum seen while attacked, against an
allowance of the retention's bytes plus the headers the producer states it may keep for
un-acked notifications (its queue budget, where the middleware exports it). The control
window's rate and growth are reported alongside, without a goal.
"""

from __future__ import annotations

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
    result.rows = [alone, alone_rss, *rows]
    return result
