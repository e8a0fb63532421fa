"""``framegate demo``: the paper's effect on this host, filtered against uncontrolled.

Five processes meet through the loopback rendezvous (no router, no configuration): a camera
and a gyro playing the simulated bumpy approach, the mediator, the detector behind it, and
a second detector of the same speed that takes the camera's frames directly ("uncontrolled",
the paper's baseline). Both detectors emulate a computer ``service_factor`` times too slow
for the frame rate, so frames must be left out: the uncontrolled one loses the oldest of its
queue whenever a frame arrives while it is full, the mediator leaves out the blurred ones.
This process only watches, through the same public API any client uses, and compares the
markers each detector recognized.

The camera's source is ``prerendered`` by default: the approach is rendered once (with a
progress bar) and cached per seed, so the camera keeps its frame rate even on two cores;
``source="sim"`` renders live, which a small machine cannot do at 15 frames/s (the camera
then counts late skips, shown in the status line).

Buffering: the uncontrolled detector observes camera/images (``--observe``): while its
queue is full the oldest queued frame makes room for the newest, as a ROS 2 image subscriber's
keep-last queue does (the blind queue a robot has without framegate), without holding the
camera back for the mediator.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from middleware import (
    BufferInfo,
    ConfigError,
    FramegateError,
    NetworkConfig,
    Node,
    TimeRange,
    now_ns,
    tightest_flow,
)
from services.launch import (
    LOCAL_HOST,
    Deployment,
    ServiceSpec,
    Supervisor,
    pipeline,
    process_specs,
)
from services.launch._pipeline import to_argv
from services.lib.decisions import DEFAULT_POLICY, POLICIES
from services.lib.markers import BOARD_MARKERS
from services.lib.messages import read_detections

# The detector behind the mediator and the one fed by the camera directly.
FILTERED = "detector"
UNCONTROLLED = "uncontrolled"
SOURCES = ("prerendered", "sim")
STATUS_COLUMNS = 100


@dataclass(frozen=True, slots=True)
class DemoConfig:
    """What the demo runs."""

    duration_s: float = 45.0
    seed: int = 1
    policy: str = DEFAULT_POLICY
    b0_px: float = 5.0
    queue: int = 2
    service_factor: float = 1.6
    source: str = "prerendered"
    # The rough floor blurs enough frames for the mediator's choice to matter: on the default
    # floor few frames are too blurred to recognize a marker, so filtering gains little.
    floor: str = "rough"
    cache: Path | None = None
    show_logs: bool = False

    def __post_init__(self) -> None:
        if self.policy not in POLICIES:
            raise ConfigError(f"--policy {self.policy!r}: choose one of {', '.join(POLICIES)}")
        if self.source not in SOURCES:
            raise ConfigError(f"--source {self.source!r}: choose one of {', '.join(SOURCES)}")


def demo_pipeline(
    config: DemoConfig, detector: dict[str, Any] | None, name: str = "demo"
) -> Deployment:
    """The pipeline (deploy/local.yaml) with the demo's source, floor and policy; the
    detector with ``detector``'s settings, or none (another consumer takes its place)."""
    source: dict[str, Any] = {"source": config.source, "seed": config.seed}
    if config.floor != "default":
        source["floor"] = config.floor
    if config.cache is not None and config.source == "prerendered":
        source["path"] = str(config.cache)
    return pipeline(
        {
            "camera": source,
            "gyro": source,
            "mediator": {"policy": config.policy, "b0": config.b0_px},
            "detector": detector,
        },
        name=name,
    )


def demo_deployment(config: DemoConfig) -> Deployment:
    """The demo's pipeline plus the uncontrolled detector on camera/images."""
    detector = {"queue": config.queue, "service_factor": config.service_factor}
    base = demo_pipeline(config, detector)
    uncontrolled = ServiceSpec(
        UNCONTROLLED,
        "detector",
        LOCAL_HOST,
        to_argv({"name": UNCONTROLLED, "input": "camera/images", **detector, "observe": True}),
    )
    return Deployment(base.path, base.network, base.hosts, (*base.services, uncontrolled))


def prerender(config: DemoConfig, stop: threading.Event) -> bool:
    """Render the demo's approach once (see ``prerender_approach``); False if stopped."""
    if config.source != "prerendered":
        return True
    return prerender_approach(config.seed, config.floor, config.cache, stop)


def prerender_approach(seed: int, floor: str, cache: Path | None, stop: threading.Event) -> bool:
    """Render the approach of ``seed`` and ``floor`` once (progress bar on stderr) so that
    a ``prerendered`` camera and gyro find it cached (``cache``: the default user cache).

    The render runs in a child process, so that one Ctrl-C ends it at once (a render is
    minutes of CPU). False when ``stop`` interrupted it."""
    from services.lib.sim import ScenarioConfig, approach_cache_dir, scenario_hash

    scenario = ScenarioConfig(seed=seed).with_floor(floor)
    cache = cache or approach_cache_dir()
    if (cache / scenario_hash(scenario)).is_dir():
        return True
    print(f"rendering the approach once (cached in {cache})", file=sys.stderr, flush=True)
    code = (
        "import sys; from pathlib import Path; "
        "from services.lib.sim import ScenarioConfig, cached_dataset; "
        "cached_dataset(ScenarioConfig(seed=int(sys.argv[1])).with_floor(sys.argv[2]), "
        "Path(sys.argv[3]))"
    )
    child = subprocess.Popen(
        [sys.executable, "-c", code, str(seed), floor, str(cache)],
        start_new_session=True,  # our Ctrl-C handling decides when it stops
    )
    try:
        while child.poll() is None:
            if stop.wait(0.2):
                child.kill()
                child.wait()
                shutil.rmtree(cache / f"{scenario_hash(scenario)}.partial-{child.pid}", True)
                return False
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    if child.returncode != 0:
        raise ConfigError(f"rendering the approach into {cache} failed (exit {child.returncode})")
    return True


@dataclass
class Status:
    """What the status view shows, read from the services' own buffer descriptions."""

    buffers: dict[str, BufferInfo] = field(default_factory=dict)

    def get(self, name: str) -> BufferInfo | None:
        return self.buffers.get(name)

    def update(self, newer: Status) -> None:
        """Take ``newer``'s descriptions; a buffer it lacks (its service answered late: a
        busy machine, a stopped process) keeps its last one, so no count drops to zero."""
        self.buffers.update(newer.buffers)

    def counts(self) -> dict[str, Any]:
        cam, gyro = self.get("camera/images"), self.get("gyro/rates")
        out, dec = self.get("mediator/images"), self.get("mediator/decisions")
        det = self.get(f"{FILTERED}/detections")
        raw = self.get(f"{UNCONTROLLED}/detections")
        # The load the mediator compares with (observers are no load).
        tightest = tightest_flow(out.subscriptions) if out else None
        load = tightest.fill if tightest is not None else 0.0
        accepted = out.puts if out else 0
        frames = cam.puts if cam else 0
        return {
            "frames": frames,
            "camera_hz": cam.rate_hz if cam else 0.0,
            "late": cam.skipped.get("late", 0) if cam else 0,
            "dropped_at_camera": cam.refused if cam else 0,
            "gyro_samples": gyro.puts if gyro else 0,
            "decisions": dec.puts if dec else 0,
            "accepted": accepted,
            # Every frame the mediator did not forward (a policy may record several decisions
            # per frame, e.g. hold then forward, so decisions - accepted would overcount).
            "rejected": max(0, frames - accepted),
            "load": load,
            "processed_filtered": det.puts if det else 0,
            "processed_uncontrolled": raw.puts if raw else 0,
        }


def read_status(node: Node) -> Status:
    status = Status()
    try:
        for service in node.services(timeout_s=1.0):
            for buffer in service.buffers:
                status.buffers[buffer.name] = buffer
    except FramegateError:
        pass
    return status


def gain_pct(filtered: int, uncontrolled: int) -> float | None:
    """How many more recognitions the filtered detector made, in % of the uncontrolled
    one's (None while the uncontrolled one has none)."""
    return None if uncontrolled <= 0 else 100.0 * (filtered - uncontrolled) / uncontrolled


def _gain_text(filtered: int, uncontrolled: int) -> str:
    gain = gain_pct(filtered, uncontrolled)
    return "  n/a" if gain is None else f"{gain:+4.0f}%"


# Printed once above the status lines: what each group means.
STATUS_LEGEND = (
    "cam: frames, rate, late skips | med: frames the mediator forwarded (fwd) and left out\n"
    "(left), load | found: markers recognized behind the mediator vs uncontrolled, gain"
)


def status_line(counts: dict[str, Any], seen: dict[str, int], elapsed_s: float) -> str:
    """One line of at most ``STATUS_COLUMNS`` characters: the camera's frames, rate and late
    skips; the mediator's forwarded and rejected frames and load; the markers recognized
    behind the mediator against those of the uncontrolled detector, and the gain."""
    filtered, raw = seen.get(FILTERED, 0), seen.get(UNCONTROLLED, 0)
    line = (
        f"{elapsed_s:5.1f}s cam {counts['frames']:5d} {counts['camera_hz']:4.1f}/s "
        f"{counts['late']:4d} late | med {counts['accepted']:5d} fwd {counts['rejected']:5d} "
        f"left load {counts['load']:.2f} | found {filtered:5d} vs {raw:5d} "
        f"{_gain_text(filtered, raw)}"
    )
    return line[:STATUS_COLUMNS]


class MarkerTally:
    """Per board marker, the processed frames of one detector that recognized it."""

    def __init__(self, service: str) -> None:
        self.buffer = f"{service}/detections"
        self._names = {m.marker_id: m.name for m in BOARD_MARKERS}
        self._after_ns = 0
        self.seen: Counter[str] = Counter()

    def update(self, node: Node) -> None:
        try:
            # Up to now, not open-ended: any peer may answer the query, and one element
            # stamped far ahead became ``_after_ns``, so no later detection was counted.
            asked = TimeRange(self._after_ns + 1, max(self._after_ns + 1, now_ns()))
            elements = node.query(self.buffer, time_range=asked)
        except FramegateError:
            return
        for element in elements:
            _frame, ids = read_detections(element.metadata)
            for marker_id in set(ids):
                self.seen[self._names.get(marker_id, str(marker_id))] += 1
            self._after_ns = max(self._after_ns, element.timestamp_ns)

    @property
    def total(self) -> int:
        return sum(self.seen.values())


def refuse_if_running(node: Node, names: list[str], local_port: int) -> None:
    """ConfigError if a service of the demo is live already (another demo or a launch on
    this rendezvous): ours would fail to offer their names and be restarted again and again,
    while the status and the summary read the other pipeline's buffers. The advice names a
    rendezvous port other than ``local_port``, the one in use."""
    taken = node.offered_services(names)
    if not taken:
        return
    where = {i.service: f"pid {i.pid} on host {i.host}" for i in node.services(timeout_s=1.0)}
    first = taken[0]
    other_port = local_port + 1 if local_port < 65535 else local_port - 1
    raise ConfigError(
        f"service {first!r} is live already ({where.get(first, 'another process')}): another "
        "demo or launch runs on this rendezvous; stop it, or give this demo its own "
        f"(FRAMEGATE_LOCAL_PORT={other_port} framegate demo)"
    )


def run_demo(
    config: DemoConfig,
    network: NetworkConfig,
    stop: threading.Event | None = None,
    *,
    status_out: TextIO | None = None,
) -> dict[str, Any]:
    """Run the pipeline for ``duration_s`` (or until ``stop``) with a status line per second
    on ``status_out`` (stdout; stderr when stdout carries JSON); return a summary read from
    the services' buffers."""
    stop = stop or threading.Event()
    out = status_out or sys.stdout
    deployment = demo_deployment(config)
    with Node(network=network) as node:  # before minutes of rendering, not after
        refuse_if_running(node, [svc.name for svc in deployment.services], network.local_port)
    if not prerender(config, stop):
        return {}
    # After the rendering: the specs carry the shared start instant, and a start taken
    # before minutes of rendering would make the camera begin that far behind its timeline.
    specs = process_specs(deployment, None, network)
    # The services' lines (and the supervisor's own, such as a kill at the stop) go where
    # the status lines go: never into the JSON summary on stdout.
    supervisor = Supervisor(
        specs, quiet=not config.show_logs, out=lambda line: print(line, file=out, flush=True)
    )
    started = time.monotonic()
    last_print = 0.0
    known = Status()  # each buffer as last described
    counts: dict[str, Any] = known.counts()
    tallies = {name: MarkerTally(name) for name in (FILTERED, UNCONTROLLED)}
    with Node(network=network) as node:

        def refresh() -> None:
            nonlocal counts
            known.update(read_status(node))
            counts = known.counts()
            for tally in tallies.values():
                tally.update(node)

        def tick() -> None:
            nonlocal last_print
            now = time.monotonic()
            if now - last_print < 1.0:
                return
            last_print = now
            refresh()
            seen = {name: t.total for name, t in tallies.items()}
            print(status_line(counts, seen, now - started), file=out, flush=True)
            # The last reading is taken while the services still run, once the duration is
            # up (readings come a second apart: the run ends within a second after it).
            if now - started >= config.duration_s:
                stop.set()

        # One may have started while we rendered.
        refuse_if_running(node, [spec.name for spec in specs], network.local_port)
        print(STATUS_LEGEND, file=out, flush=True)
        supervisor.start()
        try:
            supervisor.run(None, on_tick=tick, stop=stop)
        except KeyboardInterrupt:
            supervisor.stop()
    markers = sorted(set(tallies[FILTERED].seen) | set(tallies[UNCONTROLLED].seen))
    return {
        **counts,
        "policy": config.policy,
        "source": config.source,
        "floor": config.floor,
        "restarts": supervisor.restarts(),
        # Children that died by a signal or found their name taken: the CLI exits 1.
        "failures": supervisor.failures(),
        "markers": {
            name: {
                "filtered": tallies[FILTERED].seen[name],
                "uncontrolled": tallies[UNCONTROLLED].seen[name],
            }
            for name in markers
        },
        "recognitions_filtered": tallies[FILTERED].total,
        "recognitions_uncontrolled": tallies[UNCONTROLLED].total,
        "gain_pct": gain_pct(tallies[FILTERED].total, tallies[UNCONTROLLED].total),
        "duration_s": round(time.monotonic() - started, 1),
    }


# Below this share of its frames the camera did not keep its rate (it warns at the same 90 %).
KEPT_RATE_SHARE = 0.9


def _late_note(summary: dict[str, Any]) -> str:
    """A line saying why the camera skipped many frames, or "". The demo hides the services'
    logs, so the camera's own warning (below 90 % of its rate) is not seen without --logs."""
    frames, late = summary["frames"], summary["late"]
    if frames + late == 0 or frames >= KEPT_RATE_SHARE * (frames + late):
        return ""
    why = (
        "rendering live is too slow here; --source prerendered keeps the rate"
        if summary["source"] == "sim"
        else "the machine is busy; --logs shows the camera's own warning"
    )
    # Rounded down: 89.5 % must not print as "90 % (below 90 %)".
    kept_pct = 100 * frames // (frames + late)
    return f"              it kept {kept_pct} % of its frames (below 90 %):\n              {why}\n"


def print_summary(summary: dict[str, Any]) -> None:
    """The summary as a short table: recognitions per marker, filtered vs uncontrolled."""
    if not summary:
        return
    out = sys.stdout
    out.write(
        f"\nsummary after {summary['duration_s']} s ({summary['source']} camera, "
        f"{summary['floor']} floor, policy {summary['policy']}):\n"
        f"  camera      {summary['frames']} frames, {summary['late']} skipped late\n"
        f"{_late_note(summary)}"
        f"  mediator    {summary['accepted']} forwarded, {summary['rejected']} left out "
        f"(load {summary['load']:.2f})\n"
        f"  detectors   {summary['processed_filtered']} frames processed behind the "
        f"mediator, {summary['processed_uncontrolled']} uncontrolled\n"
    )
    out.write(f"\n  {'recognitions':<14}{'filtered':>10}{'uncontrolled':>14}{'gain':>8}\n")
    rows = [(name, v["filtered"], v["uncontrolled"]) for name, v in summary["markers"].items()]
    rows.append(("total", summary["recognitions_filtered"], summary["recognitions_uncontrolled"]))
    for name, filtered, raw in rows:
        out.write(f"  {name:<14}{filtered:>10}{raw:>14}{_gain_text(filtered, raw):>8}\n")
