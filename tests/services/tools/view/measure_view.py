"""Measure ``framegate view``: its CPU and how far the frames a client gets lag the camera.

    python -m tests.services.tools.view.measure_view --seconds 20            # the demo pipeline
    python -m tests.services.tools.view.measure_view --seconds 20 --synthetic  # 1280x1024 mono8

The demo pipeline (sim camera 1024x768 at 15 fps, gyro, mediator, detector at 1.6x) or a
synthetic 1280x1024 mono8 camera at 15 fps with a verdict per frame runs on a private port;
``framegate view`` streams it (RawImage) to one Foxglove protocol client subscribed to the
image, the verdict annotations and the verdict plot. Lag = client receive time minus the
end of the frame's exposure (when the camera puts it), and the time a plain observer beside
the viewer got the frame's notification (what the viewer adds, whatever the camera's delay).
Not a test: a shared machine's numbers vary; run it on a quiet one.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import psutil

from middleware import NetworkConfig, Node, SubscriptionMode
from services.lib.messages import DecisionRecord, frame_metadata
from services.lib.quality import Exposure
from tests.conftest import REPO, child_env, free_port
from tests.helpers.timing import scaled
from tests.services.nodes.pipeline import Pipeline
from tests.services.tools.view.foxglove_client import FoxgloveClient, stamp_ns

DEMO = """
version: 1
services:
  camera: {args: {source: sim, seed: 1, loop: true}}
  gyro: {args: {source: sim, seed: 1, loop: true}}
  mediator: {args: {policy: paper, b0: 5.0}}
  detector: {args: {input: mediator/images, queue: 2, service_factor: 1.6}}
"""
TOPICS = ["/camera/images/image", "/mediator/decisions/annotations", "/mediator/decisions/verdict"]
EXPOSURE_NS = 20_000_000


def _synthetic(port: int, stop: threading.Event) -> None:
    """A 1280x1024 mono8 camera at 15 fps and a mediator verdict per frame."""
    net = NetworkConfig(local_port=port)
    with Node("camera", net) as camera, Node("mediator", net) as mediator:
        images = camera.offer("images", kind="frame")
        decisions = mediator.offer("decisions", kind="decision")
        rng = np.random.default_rng(0)
        pictures = [rng.integers(0, 255, (1024, 1280), dtype=np.uint8) for _ in range(4)]
        period_ns = 1_000_000_000 // 15
        next_ns = time.time_ns()
        frame_id = 0
        while not stop.is_set():
            next_ns += period_ns
            time.sleep(max(0.0, (next_ns - time.time_ns()) / 1e9))
            end_ns = time.time_ns()
            exposure = Exposure(end_ns - EXPOSURE_NS, EXPOSURE_NS)
            image = pictures[frame_id % 4]
            images.put(
                exposure.start_ns, image.tobytes(), frame_metadata(frame_id, exposure, image, None)
            )
            record = DecisionRecord(
                exposure.start_ns, frame_id, 1.0, 0.8, 0.5, True, "quality", "paper", 5.0, 0
            )
            key = time.time_ns()
            decisions.put(key, b"", record.metadata(key))
            frame_id += 1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--synthetic", action="store_true", help="1280x1024 mono8 camera")
    args = parser.parse_args()
    stop = threading.Event()
    pipe, camera = None, None
    if args.synthetic:
        port = free_port()
        camera = threading.Thread(target=_synthetic, args=(port, stop), daemon=True)
        camera.start()
    else:
        pipe = Pipeline(Path(tempfile.mkdtemp()), DEMO)
        port = pipe.port
    ws_port = free_port()
    env = child_env()
    env["FRAMEGATE_LOCAL_PORT"] = str(port)
    viewer = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "view", "--port", str(ws_port), "--json"],
        stdout=subprocess.DEVNULL, cwd=REPO, env=env,
    )  # fmt: skip
    try:
        client = None
        deadline = time.monotonic() + scaled(120)
        while client is None and time.monotonic() < deadline:
            try:
                client = FoxgloveClient(f"ws://127.0.0.1:{ws_port}")
            except OSError:
                time.sleep(0.5)
        assert client is not None, "the viewer did not start"
        client.wait_for_topics(set(TOPICS), 120)
        client.subscribe(TOPICS)
        while (got := client.receive(5.0)) is None or got.topic != TOPICS[0]:
            pass  # warm up: the first image arrived
        # When the camera put each frame, as a plain observer beside the viewer sees it.
        put_ns: dict[int, int] = {}
        watcher = Node(network=NetworkConfig(local_port=port))
        observed = watcher.subscribe("camera/images", queue_size=64, mode=SubscriptionMode.OBSERVE)

        def observe() -> None:
            while not stop.is_set():
                note = observed.take(timeout_s=scaled(0.2))
                if note is not None:
                    put_ns[note.timestamp_ns] = time.time_ns()

        threading.Thread(target=observe, daemon=True).start()
        proc = psutil.Process(viewer.pid)
        cpu0, wall0 = proc.cpu_times(), time.monotonic()
        lags_ms, lags_start_ms, lags_put_ms = [], [], []
        counts = {t: 0 for t in TOPICS}
        while time.monotonic() - wall0 < args.seconds:
            got = client.receive(1.0)
            if got is None:
                continue
            counts[got.topic] += 1
            if got.topic == TOPICS[0]:
                start = stamp_ns(got.message)
                exposure = EXPOSURE_NS if args.synthetic else 60_000_000
                lags_start_ms.append((got.received_ns - start) / 1e6)
                lags_ms.append((got.received_ns - start - exposure) / 1e6)
                if start in put_ns:
                    lags_put_ms.append((got.received_ns - put_ns[start]) / 1e6)
        cpu1, wall1 = proc.cpu_times(), time.monotonic()
        busy = (cpu1.user + cpu1.system) - (cpu0.user + cpu0.system)
        first = statistics.quantiles(lags_ms, n=100)
        print(
            f"frames {'1280x1024 synthetic' if args.synthetic else 'demo 1024x768'}, "
            f"{args.seconds:g} s; messages {counts}"
        )
        print(f"viewer CPU {100 * busy / (wall1 - wall0):.1f} % of one core")
        print(
            f"lag since the camera put the frame: p50 {statistics.median(lags_ms):.1f} ms, "
            f"p90 {first[89]:.1f} ms; since exposure start p50 "
            f"{statistics.median(lags_start_ms):.1f} ms"
        )
        print(
            f"lag behind an observer's notification of the same frame: p50 "
            f"{statistics.median(lags_put_ms):.1f} ms (n={len(lags_put_ms)})"
        )
        print(f"load average {psutil.getloadavg()}")
        client.close()
        stop.set()
        observed.close()
        watcher.close()
    finally:
        viewer.terminate()
        viewer.wait(timeout=scaled(10))
        stop.set()
        if camera is not None:
            camera.join(timeout=scaled(10))  # its Zenoh sessions close before the interpreter exits
        if pipe is not None:
            pipe.close()


if __name__ == "__main__":
    main()
