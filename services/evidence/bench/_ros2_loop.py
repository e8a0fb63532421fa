"""``ros2-loop``: an unmodified ROS 2 vision node behind the mediator, through the bridge.

What ``framegate demo`` shows for framegate's own detector, for a ROS 2 node: the camera
and gyro play the simulated bumpy approach (the demo's prerendered one), the mediator
filters, and the ``ros2`` bridge carries two image streams to a ROS 2 system (a Zenoh
router standing in for ``rmw_zenohd``, opened by this process):

- ``mediator/images`` → ``/camera/image_sharp``, in the loop (``--consumer-done``): the
  bridge frees one of the node's ``QUEUE`` slots only when the node's result with the
  image's header arrives, so the mediator sees the node's real load;
- ``camera/images`` → ``/camera/image_raw``, observed (today's bridge): the uncontrolled
  baseline, as a ROS 2 node subscribed to a camera gets it.

Two identical ROS 2 vision nodes (``_ros2_node``: plain Zenoh speaking rmw_zenoh's format,
framegate's marker detector, ``SERVICE_FACTOR`` frame periods per image, results as
``vision_msgs/msg/Detection2DArray`` with the image's header) subscribe one to each. The
uncontrolled one keeps the newest ``QUEUE - 1`` images waiting (ROS 2 KEEP_LAST) besides
the one it works on, dropping blindly while busy. Rows: recognitions per board marker and
in total (raw = uncontrolled, framegate = in the loop: their ratio is 1 + the gain), images
each processed, and the loop's own cost per image: from the node publishing its result to
the bridge taking the gate's notification (which sends the ack that frees the slot at the
mediator), p50.

A pair is one run of ``window`` seconds with both nodes on the same camera at once: at
least ``WINDOW_S`` (``QUICK_WINDOW_S`` with --quick), or ``--duration`` if longer.
"""

from __future__ import annotations

import json
import queue
import subprocess
import sys
import threading
import time
from collections import Counter
from dataclasses import replace
from typing import Any

from ._options import BenchOptions
from ._procs import free_endpoint
from ._records import Goal, Row, ScenarioResult, ratio_goal
from ._stats import percentile

WINDOW_S = 45.0
QUICK_WINDOW_S = 15.0
SERVICE_FACTOR = 1.6
# The node may hold 3 images without a result: the one it works on and 2 waiting, what the
# demo's detector holds with its queue of 2 (it takes a frame out of its queue before working
# on it, the ROS 2 node's slot is freed only by its result).
QUEUE = 3
# The loop's cost per image should be a small share of a frame period (5 %).
RELEASE_SHARE_GOAL = 0.05
LOOP_TOPIC, RAW_TOPIC = "/camera/image_sharp", "/camera/image_raw"


class _VisionNode:
    """One ROS 2 vision node process (``_ros2_node``) and the markers of its results."""

    def __init__(self, params: dict[str, Any]) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "services.evidence.bench._ros2_node", json.dumps(params)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        self._events: queue.Queue[dict[str, Any]] = queue.Queue()
        threading.Thread(target=self._pump, daemon=True).start()
        self.seen: Counter[int] = Counter()
        self.processed = 0
        self.answered_ever = 0
        self.counting = False

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if line.startswith("{"):
                self._events.put(json.loads(line))

    def wait_ready(self, timeout_s: float) -> None:
        try:
            if self._events.get(timeout=timeout_s).get("ready"):
                return
        except queue.Empty:
            pass
        raise RuntimeError(f"the ROS 2 vision node did not start (exit {self.proc.poll()})")

    def poll(self) -> None:
        while True:
            try:
                event = self._events.get_nowait()
            except queue.Empty:
                return
            if "answered" not in event:
                continue
            self.answered_ever += 1
            if self.counting:
                self.processed += 1
                self.seen.update(int(m) for m in event["markers"])

    def close(self) -> None:
        if self.proc.poll() is None:
            assert self.proc.stdin is not None
            self.proc.stdin.close()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def _ros_router(at: str) -> Any:
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([at]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


def _bridge_argv(ros_at: str) -> tuple[str, ...]:
    return (
        *("--ros-connect", ros_at),
        *("--image-out", f"mediator/images={LOOP_TOPIC}", f"camera/images={RAW_TOPIC}"),
        *("--consumer-done", "/vision/sharp/detections", "--consumer-input", "mediator/images"),
        *("--consumer-queue", str(QUEUE), "--consumer-timeout-ms", "2000"),
    )


def _one_run(window_s: float, period_s: float, progress: Any) -> dict[str, Any]:
    """Run the pipeline and both nodes for ``window_s``; what each recognized, and the
    loop's figures read from the services' own buffers."""
    from middleware import NetworkConfig, Node, field_text, parse_untrusted
    from services.launch import (
        LOCAL_HOST,
        Deployment,
        ServiceSpec,
        Supervisor,
        process_specs,
    )
    from services.tools.demo import DemoConfig, demo_pipeline

    # The demo's pipeline; the ROS 2 nodes below take its detector's place.
    base = demo_pipeline(DemoConfig(), detector=None, name="ros2-loop")
    bridge = ServiceSpec("ros2", "ros2", LOCAL_HOST, _bridge_argv(ros_at := free_endpoint()))
    deployment = Deployment(base.path, base.network, base.hosts, (*base.services, bridge))
    network = NetworkConfig(local_port=int(free_endpoint().rsplit(":", 1)[1]))
    service_s = SERVICE_FACTOR * period_s
    common = {"connect": ros_at, "detect": True, "service_time_s": service_s}
    out: dict[str, Any] = {}
    with _ros_router(ros_at):
        nodes = {
            "loop": _VisionNode(
                {
                    **common,
                    "name": "vision_sharp",
                    "image_topic": LOOP_TOPIC,
                    "result_topic": "/vision/sharp/detections",
                    "depth": 10,
                }
            ),
            "raw": _VisionNode(
                {
                    **common,
                    "name": "vision_raw",
                    "image_topic": RAW_TOPIC,
                    "result_topic": "/vision/raw/detections",
                    "depth": QUEUE - 1,  # + the one it works on: as many as the loop's
                }
            ),
        }
        try:
            for vision in nodes.values():
                vision.wait_ready(60)
            # The children find the private rendezvous through the environment, as soak's.
            specs = [
                replace(spec, env=(*spec.env, ("FRAMEGATE_LOCAL_PORT", str(network.local_port))))
                for spec in process_specs(deployment, None, network)
            ]
            logs: list[str] = []
            supervisor = Supervisor(specs, colour=False, out=logs.append)
            out["logs"] = logs
            started = time.monotonic()
            with Node(network=network) as client:
                # Counting starts once both nodes have answered an image: they then see the
                # same camera for the same window.
                def tick() -> None:
                    for vision in nodes.values():
                        vision.poll()
                    if not nodes["loop"].counting and all(v.answered_ever for v in nodes.values()):
                        for vision in nodes.values():
                            vision.counting = True
                        out["counting_from_s"] = time.monotonic() - started

                def read_back() -> None:
                    # (FramegateError here ends the run: the scenario reports it.)
                    out["mediator"] = client.buffer_info("mediator/images", timeout_s=2.0)
                    out["camera"] = client.buffer_info("camera/images", timeout_s=2.0)
                    out["results_info"] = client.buffer_info("ros2/results", timeout_s=2.0)
                    out["results"] = client.query("ros2/results", timeout_s=5.0)

                stop = threading.Event()
                deadline: list[float] = []

                def watch() -> None:
                    tick()
                    if nodes["loop"].counting and not deadline:
                        deadline.append(time.monotonic() + window_s)
                    if deadline and time.monotonic() >= deadline[0]:
                        for vision in nodes.values():
                            vision.poll()
                            vision.counting = False
                        read_back()
                        stop.set()
                    elif time.monotonic() - started > window_s + 120:
                        raise RuntimeError("the mediator forwarded nothing within 120 s")

                supervisor.start()
                supervisor.run(None, on_tick=watch, stop=stop)
                out["restarts"] = {k: v for k, v in supervisor.restarts().items() if v}
        finally:
            for vision in nodes.values():
                vision.close()
    if "results" not in out:
        raise RuntimeError("the run ended before its window was read")
    release, answer = [], []
    for element in out["results"]:
        root = parse_untrusted(element.metadata)
        release.append(int(field_text(root, "release_ns") or 0) / 1e3)
        answer.append(int(field_text(root, "answer_ns") or 0) / 1e3)
    out["release_us"], out["answer_us"] = release, answer
    out["nodes"] = nodes
    progress(
        f"ros2-loop: {nodes['loop'].seen.total()} recognitions in the loop vs "
        f"{nodes['raw'].seen.total()} uncontrolled; {nodes['loop'].processed} vs "
        f"{nodes['raw'].processed} images processed; release p50 "
        f"{percentile(release, 50) if release else float('nan'):.0f} us"
    )
    return out


def run_ros2_loop(options: BenchOptions) -> ScenarioResult:
    from services.lib.markers import BOARD_MARKERS
    from services.lib.sim import ScenarioConfig
    from services.tools.demo import DemoConfig, gain_pct, prerender

    window_s = max(options.duration_s, QUICK_WINDOW_S if options.quick else WINDOW_S)
    period_s = ScenarioConfig().frame_period_ns / 1e9
    if not prerender(DemoConfig(), threading.Event()):
        raise RuntimeError("rendering the approach was interrupted")
    names = {m.marker_id: m.name for m in BOARD_MARKERS}
    result = ScenarioResult(
        "ros2-loop",
        params={
            "window_s": window_s,
            "service_time_s": round(SERVICE_FACTOR * period_s, 4),
            "consumer_queue": QUEUE,
            "raw": f"a ROS 2 node on the camera's images (KEEP_LAST {QUEUE - 1}), uncontrolled",
            "framegate": "the same node behind the mediator, in the bridge's loop",
            "legend": (
                "columns: raw = the node uncontrolled on the camera's images; framegate = "
                "the same node in the bridge's loop; fg/raw = 1 + the loop's gain"
            ),
        },
    )
    rows: dict[str, Row] = {}

    def row(key: str, name: str, metric: str, unit: str, higher: bool) -> Row:
        return rows.setdefault(key, Row(name, metric, unit, higher))

    for pair in range(options.pairs):
        run = _one_run(window_s, period_s, options.progress)
        loop, raw = run["nodes"]["loop"], run["nodes"]["raw"]
        for marker_id in sorted(set(loop.seen) | set(raw.seen)):
            name = names.get(marker_id, str(marker_id))
            r = row(name, f"recognitions of {name}", "recognitions", "count", True)
            r.samples("raw").append({"pair": pair, "value": raw.seen[marker_id]})
            r.samples("framegate").append({"pair": pair, "value": loop.seen[marker_id]})
        total = row(
            "total",
            f"recognitions, all markers ({window_s:g} s runs)",
            "recognitions",
            "count",
            True,
        )
        gain = gain_pct(loop.seen.total(), raw.seen.total())
        total.samples("raw").append({"pair": pair, "value": raw.seen.total()})
        total.samples("framegate").append(
            {"pair": pair, "value": loop.seen.total(), "gain_pct": gain}
        )
        done = row("processed", "images processed by the node", "images", "count", True)
        done.samples("raw").append({"pair": pair, "value": raw.processed})
        mediator, results = run["mediator"], run["results_info"]
        done.samples("framegate").append(
            {
                "pair": pair,
                "value": loop.processed,
                "camera_frames": run["camera"].puts,
                "forwarded": mediator.puts,
                "skipped": dict(results.skipped),
                "restarts": run["restarts"],
            }
        )
        if run["release_us"]:
            release = row("release", "loop: result -> slot freed p50", "us", "us", False)
            release.raw = None
            release.samples("framegate").append(
                {
                    "pair": pair,
                    "value": percentile(run["release_us"], 50),
                    "p99": percentile(run["release_us"], 99),
                    "answer_p50_us": percentile(run["answer_us"], 50),
                    "count": len(run["release_us"]),
                }
            )
    if "total" in rows:
        rows["total"].goal = ratio_goal(rows["total"], 1.0, at_least=True, what="recognitions")
        rows["total"].note = "ratio = 1 + the gain of the loop over the uncontrolled node"
    if "release" in rows:
        limit_us = round(RELEASE_SHARE_GOAL * period_s * 1e6)
        rows["release"].goal = Goal(
            f"loop release p50 <= {limit_us:g} us ({RELEASE_SHARE_GOAL:.0%} of a frame period)",
            limit_us,
            False,
            rows["release"].median("framegate"),
        )
        rows["release"].note = "result published by the node -> gate taken (ack) in the bridge"
    order = ["total", "processed", "release"]
    result.rows = [rows[k] for k in rows if k not in order] + [rows[k] for k in order if k in rows]
    return result
