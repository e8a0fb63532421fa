"""A semantic fuzzer for the running pipeline: hostile camera, gyro and consumers.

    python -m tests.fuzz.pipeline --elements 10000        # the long run
    (tests/fuzz/test_pipeline_fuzz.py runs a few hundred in CI)

It launches the four services (``framegate launch``, deploy/local.yaml's pipeline) with the
mediator pointed at ``fuzzcam/images`` and ``fuzzgyro/rates``, which this process offers as
a hostile camera and gyro: hypothesis strategies generate metadata that passes its XSD but
means nothing sane (exposures of centuries, exposures far from the key, focal lengths of
1e-300, non-rotation matrices, clock offsets of years, payloads that do not match the
size, gyro batches out of order, overlapping, counting wrong, with rates of 1e300 or NaN),
interleaved with good frames each preceded by gyro data that covers it. Hostile consumers
ride along: ``framegate watch --flow-control --queue 1 --delay 5`` on every buffer (real CLI
processes), in-process flow-controlled and observing subscriptions that never take, and
queries with malformed time ranges. The real camera and gyro keep running as well
(replaying a few simulated frames in a loop).

After each batch it checks that every service is alive with the pid it started with (the
launcher restarts a crashed service, so a new pid means a crash), answers ``info``, has
recorded a decision for every good frame it was given, and forwards good frames to the
detector. A failure names the batch that caused it (hypothesis prints the exact elements).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import psutil
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from middleware import (
    FlowControlRefused,
    FramegateError,
    Node,
    QueryError,
    Subscription,
    SubscriptionMode,
    make_metadata,
)
from services.launch import pipeline_yaml
from services.lib.messages import DecisionRecord
from tests.conftest import REPO, child_env
from tests.helpers.frames import simulated_frames
from tests.helpers.timing import scaled
from tests.services.nodes.pipeline import Pipeline

SERVICES = ("camera", "gyro", "mediator", "detector")
FUZZ_CAMERA, FUZZ_GYRO = "fuzzcam/images", "fuzzgyro/rates"
BUFFERS = (
    "camera/images",
    "gyro/rates",
    "mediator/images",
    "mediator/decisions",
    "detector/detections",
    FUZZ_CAMERA,
    FUZZ_GYRO,
)
GYRO_DTYPE = np.dtype([("t", "<i8"), ("w", "<f8", (3,))])
WIDTH, HEIGHT = 32, 24
MS = 1_000_000
IDENTITY = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
GOOD_CAMERA: dict[str, Any] = {
    "width_px": WIDTH,
    "height_px": HEIGHT,
    "fx_px": 30.0,
    "fy_px": 30.0,
    "cx_px": WIDTH / 2,
    "cy_px": HEIGHT / 2,
    "line_readout_ns": 0,
    "gyro_to_camera": IDENTITY,
    "gyro_time_offset_ns": 0,
}
# How long the services get to decide a batch's good frames (a loaded host is slow).
SETTLE_S = 30.0
INT64_MAX = 2**63 - 1

# -- what a hostile element is -----------------------------------------------------------------


@dataclass(frozen=True)
class Element:
    """One step of the hostile camera/gyro/consumer: ``kind`` says which, ``spec`` how."""

    kind: str  # good | frame | gyro | query | subscribe
    spec: dict[str, Any] = field(default_factory=dict)


_absurd_double = st.one_of(
    st.sampled_from([1e-300, 5e-324, 1e300, -1e300, 1.7976931348623157e308, 0.0, -0.0]),
    st.floats(allow_nan=False, allow_infinity=False),
)
_absurd_long = st.one_of(
    st.sampled_from([0, 1, INT64_MAX, -(2**63)]), st.integers(-(2**63), INT64_MAX)
)
_camera = st.fixed_dictionaries(
    {},
    optional={
        "fx_px": _absurd_double.filter(lambda v: v > 0),
        "fy_px": _absurd_double.filter(lambda v: v > 0),
        "cx_px": _absurd_double,
        "cy_px": _absurd_double,
        "width_px": st.integers(1, 65535),
        "height_px": st.integers(1, 65535),
        "line_readout_ns": st.integers(0, INT64_MAX),
        "gyro_to_camera": st.lists(_absurd_double, min_size=9, max_size=9),
        "gyro_time_offset_ns": _absurd_long,
    },
)
_frame = st.fixed_dictionaries(
    {
        "camera": st.one_of(st.none(), _camera),
        "payload_bytes": st.one_of(st.just(WIDTH * HEIGHT), st.integers(0, 3 * WIDTH * HEIGHT)),
    },
    optional={
        "frame_id": st.integers(0, INT64_MAX),
        "exposure_ns": st.integers(1, INT64_MAX),
        "exposure_start_ns": st.integers(0, INT64_MAX),
        "exposure_shift_ns": st.integers(-(10**12), 10**12),
        "encoding": st.sampled_from(["mono8", "bgr8", "rgb8", " mono8 ", "\tbgr8\n"]),
        "width_px": st.integers(1, 65535),
        "height_px": st.integers(1, 65535),
    },
)
_rate = st.one_of(
    st.floats(-1e3, 1e3), st.sampled_from([math.nan, math.inf, -math.inf, 1e300, -1e300])
)
_gyro = st.fixed_dictionaries(
    {
        "samples": st.integers(0, 60),
        "rates": st.lists(st.tuples(_rate, _rate, _rate), min_size=1, max_size=4),
        "order": st.sampled_from(["sorted", "reversed", "shuffled", "duplicated", "overlap"]),
    },
    optional={
        "count": st.integers(1, 1_000_000),
        "rate_hz": _absurd_double.filter(lambda v: v > 0),
        "time_shift_ns": st.one_of(_absurd_long, st.integers(-(10**10), 10**10)),
        "extra_bytes": st.integers(1, 31),
    },
)
_bad_range = st.one_of(
    st.sampled_from(
        [
            "[now(-99999999999999999999s)..]",
            "[" + "9" * 5000 + "..]",
            "[1;2s]",
            "]..0[",
            f"[{2**63}..]",
            "[now(-1e400s)..]",
            "[..now(+\u0661s)]",
        ]
    ),
    st.text(max_size=30),
)
elements = st.one_of(
    st.just(Element("good")),
    _frame.map(lambda s: Element("frame", s)),
    _gyro.map(lambda s: Element("gyro", s)),
    st.tuples(st.sampled_from(BUFFERS), _bad_range).map(
        lambda t: Element("query", {"target": t[0], "range": t[1]})
    ),
    st.tuples(st.sampled_from(BUFFERS), st.sampled_from(list(SubscriptionMode))).map(
        lambda t: Element("subscribe", {"target": t[0], "mode": t[1].value})
    ),
)

# -- playing it --------------------------------------------------------------------------------


@dataclass
class Tally:
    """What was played and what the checks saw."""

    counts: Counter[str] = field(default_factory=Counter)
    good_keys: list[int] = field(default_factory=list)
    batches: int = 0

    @property
    def hostile(self) -> int:
        return sum(v for k, v in self.counts.items() if k.startswith("hostile-"))


class PipelineFuzzer:
    """The pipeline under test plus the hostile camera, gyro and consumers."""

    def __init__(self, workdir: Path, *, cli_watchers: bool = True) -> None:
        # The real camera and gyro are bystanders (the mediator is given the hostile ones):
        # they loop a few simulated frames instead of rendering live, which kept a core busy
        # for the whole run and, on a loaded machine, starved the services under test.
        replay = {
            "source": "replay",
            "path": str(simulated_frames(workdir / "approach")),
            "seed": None,
        }
        overrides = {
            "camera": replay,
            "gyro": replay,
            "mediator": {"camera": FUZZ_CAMERA, "gyro": FUZZ_GYRO},
            "detector": {"service_factor": 0.0},
        }
        self.pipe = Pipeline(workdir, pipeline_yaml(overrides))  # type: ignore[arg-type]
        self.camera_node = Node(FUZZ_CAMERA.split("/")[0], network=self.pipe.network)
        self.gyro_node = Node(FUZZ_GYRO.split("/")[0], network=self.pipe.network)
        self.frames = self.camera_node.offer("images", kind="frame")
        self.rates = self.gyro_node.offer("rates", kind="gyro")
        self.tally = Tally()
        self._subs: list[Subscription] = []
        self._watchers: list[subprocess.Popen[bytes]] = []
        self._last_key_ns = 0
        self._frame_id = 0
        self.pids = self._wait_for_services()
        if not self.frames.wait_for_subscribers(1, timeout_s=scaled(60)):
            raise AssertionError("the mediator never subscribed to " + FUZZ_CAMERA)
        if cli_watchers:
            self._start_watchers()

    # -- set-up ---------------------------------------------------------------------------------
    def _wait_for_services(self) -> dict[str, int]:
        deadline = time.monotonic() + scaled(120)
        while time.monotonic() < deadline:
            pids = {s: self.pipe.pid(s) for s in SERVICES}
            if all(pids.values()):
                return {s: p for s, p in pids.items() if p is not None}
            time.sleep(0.2)
        raise AssertionError(f"services did not come up\n{self.pipe.log()}")

    def _start_watchers(self) -> None:
        """``framegate watch --flow-control --queue 1 --delay 5`` on every buffer."""
        env = child_env()
        env["FRAMEGATE_LOCAL_PORT"] = str(self.pipe.port)
        for target in BUFFERS:
            command = [sys.executable, "-m", "services.cli", "watch", target, "--flow-control"]
            command += ["--queue", "1", "--delay", "5", "--json", "--timeout", "60"]
            self._watchers.append(
                subprocess.Popen(
                    command,
                    cwd=REPO,
                    env=env,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )
            )
        self.tally.counts["hostile-cli-watchers"] += len(self._watchers)

    # -- one element ----------------------------------------------------------------------------
    def _key(self) -> int:
        """A fresh, strictly increasing key near now (both buffers refuse older keys)."""
        self._last_key_ns = max(time.time_ns(), self._last_key_ns + 1)
        return self._last_key_ns

    def play(self, element: Element) -> None:
        handler: Callable[[dict[str, Any]], None] = getattr(self, f"_play_{element.kind}")
        handler(element.spec)

    def _put(self, producer: Any, key: int, payload: bytes, metadata: bytes, what: str) -> bool:
        try:
            producer.put(key, payload, metadata)
        except FlowControlRefused:
            self.tally.counts[f"{what}-refused-flow"] += 1
            return False
        except FramegateError as exc:
            self.tally.counts[f"{what}-refused-{type(exc).__name__}"] += 1
            return False
        self.tally.counts[what] += 1
        return True

    def _play_good(self, _spec: dict[str, Any]) -> None:
        """Gyro covering a 10 ms exposure (tiny rotation: sharp), then the frame itself."""
        frame_key = self._key()  # the exposure starts at the key
        t = np.arange(frame_key - 20 * MS, frame_key + 30 * MS, MS, dtype=np.int64)
        records = np.zeros(t.size, GYRO_DTYPE)
        records["t"] = t
        records["w"] = 1e-4
        gyro_key = self._key()
        gyro_fields = {
            "count": int(t.size),
            "first_ns": int(t[0]),
            "last_ns": int(t[-1]),
            "rate_hz": 1000.0,
            "layout": "i8,f8,f8,f8",
        }
        gyro_meta = make_metadata("gyro", gyro_key, gyro_fields)
        self._put(self.rates, gyro_key, records.tobytes(), gyro_meta, "good-gyro")
        self._frame_id += 1
        fields = {
            "frame_id": self._frame_id,
            "exposure_start_ns": frame_key,
            "exposure_ns": 10 * MS,
            "encoding": "mono8",
            "width_px": WIDTH,
            "height_px": HEIGHT,
            "camera": GOOD_CAMERA,
        }
        metadata = make_metadata("frame", frame_key, fields)
        if self._put(self.frames, frame_key, bytes(WIDTH * HEIGHT), metadata, "good-frame"):
            self.tally.good_keys.append(frame_key)

    def _play_frame(self, spec: dict[str, Any]) -> None:
        key = self._key()
        self._frame_id += 1
        fields: dict[str, Any] = {
            "frame_id": spec.get("frame_id", self._frame_id),
            "exposure_start_ns": spec.get(
                "exposure_start_ns",
                min(INT64_MAX, max(0, key + spec.get("exposure_shift_ns", 0))),
            ),
            "exposure_ns": spec.get("exposure_ns", 10 * MS),
            "encoding": spec.get("encoding", "mono8"),
            "width_px": spec.get("width_px", WIDTH),
            "height_px": spec.get("height_px", HEIGHT),
        }
        if spec["camera"] is not None:
            fields["camera"] = {**GOOD_CAMERA, **spec["camera"]}
        metadata = make_metadata("frame", key, fields)
        self._put(self.frames, key, bytes(spec["payload_bytes"]), metadata, "hostile-frame")

    def _play_gyro(self, spec: dict[str, Any]) -> None:
        key = self._key()
        n = spec["samples"]
        shift = spec.get("time_shift_ns", 0)
        times = [min(INT64_MAX, max(0, key + (i - n) * MS + shift)) for i in range(n)]
        t = np.array(times, dtype=np.int64)
        order = spec["order"]
        if order == "reversed":
            t = t[::-1]
        elif order == "shuffled":
            t = np.random.default_rng(n).permutation(t)
        elif order == "duplicated" and n:
            t[:] = t[0]
        elif order == "overlap":
            t = np.maximum(t - 30 * MS, 0)  # re-covers what earlier batches covered
        records = np.zeros(n, GYRO_DTYPE)
        records["t"] = t
        rates = spec["rates"]
        for i in range(n):
            records["w"][i] = rates[i % len(rates)]
        payload = records.tobytes() + bytes(spec.get("extra_bytes", 0))
        first = int(t.min()) if n else key
        last = int(t.max()) if n else key
        metadata = make_metadata(
            "gyro",
            key,
            {
                "count": spec.get("count", max(n, 1)),
                "first_ns": max(0, first),
                "last_ns": max(0, last),
                "rate_hz": spec.get("rate_hz", 1000.0),
                "layout": "i8,f8,f8,f8",
            },
        )
        self._put(self.rates, key, payload, metadata, "hostile-gyro")

    def _play_query(self, spec: dict[str, Any]) -> None:
        try:
            self.pipe.node.query(spec["target"], time_range=spec["range"], timeout_s=scaled(5.0))
            self.tally.counts["hostile-query-answered"] += 1
        except QueryError:
            self.tally.counts["hostile-query-refused"] += 1
        except FramegateError as exc:
            self.tally.counts[f"hostile-query-{type(exc).__name__}"] += 1

    def _play_subscribe(self, spec: dict[str, Any]) -> None:
        """A subscription with queue 1 that never takes (it holds the producer if FLOW)."""
        if len(self._subs) >= 12:  # keep a rolling few, so good frames get through sometimes
            old = self._subs.pop(0)
            old.close()
        try:
            sub = self.pipe.node.subscribe(
                spec["target"], queue_size=1, mode=SubscriptionMode(spec["mode"]), wait_s=0
            )
        except FramegateError as exc:
            self.tally.counts[f"hostile-subscribe-{type(exc).__name__}"] += 1
            return
        self._subs.append(sub)
        self.tally.counts["hostile-subscribe"] += 1

    # -- the checks -----------------------------------------------------------------------------
    def release_consumers(self) -> None:
        """Close the in-process hostile subscriptions, so good frames can flow for the check."""
        for sub in self._subs:
            sub.close()
        self._subs.clear()

    def check(self, good_keys: list[int], since_ns: int, refused_before: int) -> None:
        """Every service alive with its first pid and answering; every good frame decided."""
        for service, pid in self.pids.items():
            now = self.pipe.pid(service)
            if now != pid:
                raise AssertionError(
                    f"{service} died (pid {pid} -> {now}) during batch {self.tally.batches}"
                    f"\n{self.pipe.log()}"
                )
        for watcher in self._watchers:
            if watcher.poll() is not None:
                raise AssertionError(f"a hostile CLI watcher ended: {watcher.args!r}")
        deadline = time.monotonic() + SETTLE_S
        missing = set(good_keys)
        while time.monotonic() < deadline:
            missing -= self._decided(since_ns)
            # The mediator's rule for its own bookkeeping: a decision record refused by a
            # flow-controlled consumer of mediator/decisions is counted and dropped.
            dropped = self.pipe.count("mediator/decisions", "refused") - refused_before
            if len(missing) <= dropped:
                break
            time.sleep(0.5)
        else:
            raise AssertionError(
                f"no decision recorded for good frames {sorted(missing)[:5]} "
                f"({len(missing)} of {len(good_keys)}, {dropped} counted as dropped) in batch "
                f"{self.tally.batches}; {self._diagnosis()}"
            )
        self.tally.counts["good-frames-decided"] += len(good_keys) - len(missing)
        self.tally.counts["good-frames-decision-dropped-and-counted"] += len(missing)
        self.tally.counts["checks"] += 1

    def _diagnosis(self) -> str:
        """What the mediator was doing: its counters, CPU and log (without the churn)."""
        parts = []
        for target in ("mediator/decisions", "mediator/images"):
            try:
                info = self.pipe.info(target)
                parts.append(f"{target}: puts {info.puts}, refused {info.refused}")
            except FramegateError as exc:
                parts.append(f"{target}: {exc}")
        # Is the mediator still subscribed to our frames (flow, queue 8), and is it taking?
        subs = self.frames.info().subscriptions
        parts.append(
            f"{FUZZ_CAMERA} subscriptions: "
            + (", ".join(f"{s.mode.value} {s.queued}/{s.queue_size}" for s in subs) or "none")
        )
        try:
            cpu = psutil.Process(self.pids["mediator"]).cpu_times()
            parts.append(f"mediator CPU user {cpu.user:.1f} s, system {cpu.system:.1f} s")
        except psutil.Error as exc:
            parts.append(f"mediator: {exc}")
        log = [line for line in self.pipe.lines if "no longer waiting" not in line][-60:]
        return "; ".join(parts) + "\n" + "\n".join(log)

    def _decided(self, since_ns: int) -> set[int]:
        try:
            found = self.pipe.node.query("mediator/decisions", time_range=f"[{since_ns}..]")
        except FramegateError:
            return set()
        return {DecisionRecord.from_metadata(e.metadata).frame_timestamp_ns for e in found}

    def check_forwarding(self, within_s: float = 30.0) -> None:
        """With the hostile subscriptions gone, good frames reach the detector again.

        Within ``within_s``: the first check follows a cold start, and on a loaded 2-core CI
        machine a fresh mediator took over 5 s to decide its first frame.
        """
        before = self.pipe.count("mediator/images")
        deadline = time.monotonic() + scaled(within_s)
        tries = 0
        while time.monotonic() < deadline:
            tries += 1
            self._play_good({})
            if self.pipe.counter("mediator/images") > before:
                self.tally.counts["forwarding-checks"] += 1
                return
            time.sleep(0.25)
        raise AssertionError(
            f"no good frame was forwarded in {scaled(within_s):g} s ({tries} tries)\n"
            + self.pipe.log()
        )

    def stop_watchers(self) -> None:
        for watcher in self._watchers:
            watcher.terminate()
        for watcher in self._watchers:
            try:
                watcher.wait(timeout=scaled(10))
            except subprocess.TimeoutExpired:
                watcher.kill()
                watcher.wait()
        self._watchers.clear()

    def close(self) -> None:
        self.stop_watchers()
        self.release_consumers()
        self.camera_node.close()
        self.gyro_node.close()
        self.pipe.close()


def run(total: int, batch: int, *, seed: int | None = None, cli_watchers: bool = True) -> Tally:
    """Play ``total`` generated elements in batches of ``batch``, checking after each."""
    with tempfile.TemporaryDirectory(prefix="fg-pipeline-fuzz-") as tmp:
        fuzzer = PipelineFuzzer(Path(tmp), cli_watchers=cli_watchers)
        try:
            batches = max(1, math.ceil(total / batch))

            @settings(
                max_examples=batches,
                phases=[Phase.generate],
                deadline=None,
                database=None,
                suppress_health_check=list(HealthCheck),
                derandomize=seed is not None,
            )
            @given(st.lists(elements, min_size=batch, max_size=batch))
            def one_batch(played: list[Element]) -> None:
                since_ns = time.time_ns()
                refused_before = fuzzer.pipe.count("mediator/decisions", "refused")
                if fuzzer.tally.batches >= batches / 2:
                    fuzzer.stop_watchers()  # the second half: decisions must all be recorded
                fuzzer.tally.good_keys.clear()
                for element in played:
                    fuzzer.play(element)
                fuzzer.tally.batches += 1
                good = list(fuzzer.tally.good_keys)
                fuzzer.check(good, since_ns, refused_before)
                fuzzer.release_consumers()
                fuzzer.check_forwarding()

            one_batch()
            return fuzzer.tally
        finally:
            fuzzer.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tests.fuzz.pipeline", description=__doc__)
    parser.add_argument("--elements", type=int, default=10_000, help="generated elements")
    parser.add_argument("--batch", type=int, default=100, help="elements between checks")
    parser.add_argument("--seed", type=int, help="derandomize (the same elements every run)")
    parser.add_argument("--no-cli-watchers", action="store_true", help="skip the CLI watchers")
    parser.add_argument("--json", type=Path, help="write the tally here")
    args = parser.parse_args(argv)
    started = time.monotonic()
    tally = run(args.elements, args.batch, seed=args.seed, cli_watchers=not args.no_cli_watchers)
    summary = {
        "hostile_elements": tally.hostile,
        "batches": tally.batches,
        "seconds": round(time.monotonic() - started, 1),
        "counts": dict(sorted(tally.counts.items())),
    }
    print(json.dumps(summary, indent=2))
    if args.json:
        args.json.write_text(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
