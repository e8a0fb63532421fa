"""Measure that the mediator's acceptance follows a vision handler's real speed.

One simulated camera and gyro feed two mediators, each with its own consumer: the cheap
ArUco handler (``services.nodes.detector:detect_aruco``) and the expensive multi-scale
template matcher (``examples.vision_template:find_marker``). After a warm-up it counts,
over the same window, the frames each mediator forwarded and the results each handler
stored, and reads each handler's processing time from its results::

    python examples/vision_compare.py --seconds 60

Run it from the repository root on a private rendezvous port (it picks a free one), so it
disturbs nothing else on the machine. No emulated delay anywhere: both costs are real.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from middleware import FramegateError, NetworkConfig, Node, field_text, validate_metadata

REPO = Path(__file__).resolve().parent.parent
CONSUMERS = {
    "cheap": "services.nodes.detector:detect_aruco",
    "expensive": "examples.vision_template:find_marker",
}


def deploy_yaml(seed: int) -> str:
    lines = [
        "version: 1",
        "services:",
        f"  camera: {{args: {{source: sim, seed: {seed}, loop: true}}}}",
        f"  gyro: {{args: {{source: sim, seed: {seed}, loop: true}}}}",
    ]
    for name, handler in CONSUMERS.items():
        lines += [
            f"  mediator-{name}: {{type: mediator, args: {{policy: paper, b0: 5.0}}}}",
            f"  vision-{name}: {{type: vision, args: {{handler: '{handler}', "
            f"input: mediator-{name}/images}}}}",
        ]
    return "\n".join(lines) + "\n"


@dataclass(frozen=True, slots=True)
class Counts:
    camera: int
    forwarded: dict[str, int]
    results: dict[str, int]


# How often a count is asked for before the example gives up.
ASKS = 6


def counts(node: Node) -> Counts:
    def puts(target: str) -> int:
        # A busy machine can keep a service from running past its lease for seconds (peers
        # drop it until it reconnects): ask again before giving up.
        for attempt in range(ASKS):
            try:
                return node.buffer_info(target, timeout_s=5.0).puts
            except FramegateError:
                if attempt == ASKS - 1:
                    raise
                time.sleep(1.0)
        raise AssertionError("unreachable")

    return Counts(
        puts("camera/images"),
        {name: puts(f"mediator-{name}/images") for name in CONSUMERS},
        {name: puts(f"vision-{name}/detections") for name in CONSUMERS},
    )


def processing_ms(node: Node, name: str, since_ns: int) -> float:
    """Median processing time of the handler's results stamped after ``since_ns``."""
    values = []
    for element in node.query(f"vision-{name}/detections"):
        if element.timestamp_ns > since_ns:
            root = validate_metadata(element.metadata, "detections")
            values.append(int(field_text(root, "processing_ns") or 0) / 1e6)
    return statistics.median(values) if values else float("nan")


def wait_live(node: Node, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            if all(v > 2 for v in counts(node).results.values()):
                return
        except FramegateError:
            pass
        if time.monotonic() > deadline:
            raise SystemExit(f"the pipeline did not start within {timeout_s:g} s")
        time.sleep(0.5)


def duration(text: str) -> float:
    """A flag's duration: a finite number of seconds >= 0, refused as it is parsed (before
    the pipeline starts)."""
    value = float(text)
    if not math.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"must be a number of seconds >= 0, got {text!r}")
    return value


def window(text: str) -> float:
    """The measuring window: a finite number of seconds > 0 (every rate is divided by it)."""
    value = float(text)
    if not math.isfinite(value) or value <= 0:  # -5 too: told ">= 0", then 0 was refused
        raise argparse.ArgumentTypeError(f"must be a number of seconds > 0, got {text!r}")
    return value


def main(*, seconds: float, warmup_s: float, seed: int) -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    env = dict(os.environ, FRAMEGATE_LOCAL_PORT=str(port))
    with tempfile.TemporaryDirectory() as tmp:
        deploy = Path(tmp) / "vision_compare.yaml"
        deploy.write_text(deploy_yaml(seed))
        launch = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "launch", str(deploy), "--no-colour"],
            cwd=REPO,
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            print(f"started the pipeline on port {port} (Ctrl-C stops it) ...", flush=True)
            with Node(network=NetworkConfig(local_port=port)) as node:
                wait_live(node, 120)
                time.sleep(warmup_s)
                since_ns = time.time_ns()
                first, started = counts(node), time.monotonic()
                time.sleep(seconds)
                last, elapsed = counts(node), time.monotonic() - started
                camera_hz = (last.camera - first.camera) / elapsed
                print(f"camera: {camera_hz:.1f} frames/s over {elapsed:.0f} s")
                print(
                    f"{'handler':<10} {'ms/frame':>9} {'capacity/s':>11} {'forwarded/s':>12} "
                    f"{'results/s':>10} {'accepted':>9}"
                )
                for name in CONSUMERS:
                    ms = processing_ms(node, name, since_ns)
                    forwarded = (last.forwarded[name] - first.forwarded[name]) / elapsed
                    results = (last.results[name] - first.results[name]) / elapsed
                    print(
                        f"{name:<10} {ms:>9.1f} {1000 / ms:>11.1f} {forwarded:>12.1f} "
                        f"{results:>10.1f} {forwarded / camera_hz:>9.0%}"
                    )
        finally:
            launch.terminate()
            launch.wait(timeout=30)
    return 0


if __name__ == "__main__":
    # Ctrl-C stops it even when its parent ignores SIGINT (a job a script put in the
    # background starts that way, and Python then never raises KeyboardInterrupt).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    parser = argparse.ArgumentParser(
        prog="vision_compare", description=__doc__.splitlines()[0].replace("``", "")
    )
    parser.add_argument(
        "--seconds", type=window, default=60.0, help="measuring window, s (default 60)"
    )
    parser.add_argument(
        "--warmup-s", type=duration, default=10.0, help="run before the window, s (default 10)"
    )
    parser.add_argument("--seed", type=int, default=1, help="the simulated approach (default 1)")
    args = parser.parse_args()
    try:
        code = main(seconds=args.seconds, warmup_s=args.warmup_s, seed=args.seed)
    except KeyboardInterrupt:  # Ctrl-C: the way to stop it early (main stops the pipeline)
        code = 0
    raise SystemExit(code)
