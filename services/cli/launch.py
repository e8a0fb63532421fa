"""``framegate launch FILE [--host NAME]``: start this host's services from a deploy file.

``--check`` validates the file and prints the plan without starting anything (``--json``:
as JSON). While it
runs, ``--status`` prints one line per service every few seconds (pid, uptime, restarts,
each buffer's rate). One launcher per deploy file and host: a second one refuses at once,
naming the first one's pid. A service that died by a signal is reported, and the launcher
then exits with code 1.
"""

from __future__ import annotations

import argparse
import shlex
import threading
import time
from pathlib import Path
from typing import Any

from middleware import ConfigError, NetworkConfig
from services.launch import (
    START_DELAY_S,
    Deployment,
    LaunchLock,
    ProcessSpec,
    Supervisor,
    load_deployment,
    process_specs,
)
from services.lib.argtypes import positive_float

from ._common import command_parser, network, print_json, report_failures, stop_on_signals

DEFAULT_STATUS_S = 5.0
STATUS_COLUMNS = 100


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers,
        "launch",
        "start the services a deploy file assigns to this host",
        json_flag=True,
    )
    parser.add_argument("file", help="deploy file (YAML), e.g. deploy/local.yaml")
    parser.add_argument("--host", help="which host of the file this machine is")
    parser.add_argument(
        "--duration",
        type=positive_float,
        metavar="S",
        help=f"run the services S seconds, counted from their shared start (about"
        f" {START_DELAY_S:g} s after the launch; rendering not counted), then stop them",
    )
    parser.add_argument("--no-colour", action="store_true", help="plain log prefixes")
    parser.add_argument(
        "--check",
        action="store_true",
        help="validate the file and print what would start; start nothing (exit 0 or 1)",
    )
    parser.add_argument(
        "--status",
        nargs="?",
        type=positive_float,
        const=DEFAULT_STATUS_S,
        metavar="S",
        help=f"print one status line per service every S seconds (default {DEFAULT_STATUS_S:g})",
    )
    parser.set_defaults(func=run)


def _plan(
    args: argparse.Namespace, host: str | None = None, *, here: bool = True
) -> tuple[Deployment, list[ProcessSpec]]:
    deployment = load_deployment(args.file)
    text = Path(args.file).read_text()
    # defaults -> deploy file -> environment -> flags, for every process.
    specs = process_specs(
        deployment,
        host or args.host,
        NetworkConfig(),
        text=text,
        override=lambda net: network(args, net),
        here=here,
    )
    return deployment, specs


def _check_every_host(args: argparse.Namespace, deployment: Deployment) -> int:
    """``--check`` of a file of several hosts with no ``--host``: every host's share in
    turn, as each machine would run it (a launch must still pick one)."""
    plans = [(host, _plan(args, host, here=False)[1]) for host in sorted(deployment.hosts)]
    if args.json:
        data = plan_json(deployment, None, [spec for _, specs in plans for spec in specs])
        print_json(data)
        return 0
    for host, specs in plans:
        print_plan(deployment, host, specs, ok=False)
    print(f"ok: nothing started (--check of every host: {', '.join(h for h, _ in plans)})")
    return 0


def print_plan(
    deployment: Deployment, host: str | None, specs: list[ProcessSpec], *, ok: bool = True
) -> None:
    """What ``launch`` would start, one block per process."""
    where = f" on host {host}" if host else ""
    print(f"{deployment.path}: {len(specs)} process{'' if len(specs) == 1 else 'es'}{where}")
    by_name = {s.name: s for s in deployment.services}
    for spec in specs:
        svc = by_name[spec.name]
        restart = "restart on exit" if spec.restart else "no restart"
        print(f"  {spec.name:<12} type {svc.type:<9} host {svc.host:<10} {restart}")
        # The command line without the interpreter: what `framegate ...` would run.
        command = " ".join(shlex.quote(a) for a in spec.argv[3:])
        print(f"    framegate {command}")
    if ok:
        print("ok: nothing started (--check)")


def plan_json(deployment: Deployment, host: str | None, specs: list[ProcessSpec]) -> Any:
    """The plan of ``--check --json``: each process with its type, host and command line."""
    by_name = {s.name: s for s in deployment.services}
    return {
        "file": str(deployment.path),
        "host": host,
        "processes": [
            {
                "name": spec.name,
                "type": by_name[spec.name].type,
                "host": by_name[spec.name].host,
                "restart": spec.restart,
                "command": ["framegate", *spec.argv[3:]],
            }
            for spec in specs
        ],
        "started": False,
    }


def _duration(seconds: float | None) -> str:
    if seconds is None:
        return "down"
    whole = int(seconds)
    if whole < 60:
        return f"{whole}s"
    if whole < 3600:
        return f"{whole // 60}m{whole % 60:02d}s"
    return f"{whole // 3600}h{whole % 3600 // 60:02d}m"


def status_lines(
    supervisor: Supervisor,
    rates: dict[str, list[tuple[str, float, int]]],
    silent: frozenset[str] = frozenset(),
) -> list[str]:
    """One line per process: pid, uptime, restarts, then each buffer's rate and skips.

    ``rates`` maps a service to (buffer, Hz, skipped) of each of its buffers; a service in
    ``silent`` answered an earlier tick but not this one, and its line says so (the line
    without buffers read as if the service had none).
    """
    pids, ups, restarts = supervisor.pids(), supervisor.uptimes(), supervisor.restarts()
    width = max((len(n) for n in pids), default=4)
    lines = []
    for name, pid in pids.items():
        head = (
            f"[status] {name:<{width}} pid {pid if pid else '-':<7} up {_duration(ups[name]):<7}"
            f" restarts {restarts[name]}"
        )
        parts = [
            f"{buffer} {hz:.1f} Hz" + (f" ({skipped} skipped)" if skipped else "")
            for buffer, hz, skipped in rates.get(name, [])
        ]
        if not parts and name in silent:
            parts = ["no answer this tick"]
        line = head + ("  " + ", ".join(parts) if parts else "")
        if len(line) > STATUS_COLUMNS:
            line = line[: STATUS_COLUMNS - 3] + "..."
        lines.append(line)
    return lines


def _status_loop(
    supervisor: Supervisor,
    net: NetworkConfig,
    every_s: float,
    stop: threading.Event,
    emit: Any,
) -> None:
    from middleware import FramegateError, Node

    node: Node | None = None
    answered: set[str] = set()  # services that answered some tick
    try:
        while not stop.wait(every_s):
            rates: dict[str, list[tuple[str, float, int]]] = {}
            try:
                if node is None:
                    node = Node(network=net)
                # Short: a Ctrl-C waits for this call before the launcher can end.
                for info in node.services(timeout_s=min(1.0, every_s)):
                    rates[info.service] = [
                        (b.buffer, b.rate_hz, sum(b.skipped.values())) for b in info.buffers
                    ]
            except FramegateError:
                pass  # the pids and restarts are still worth a line
            if stop.is_set() or supervisor.stopping:
                break  # a tick during the stop would show the services half gone
            answered |= rates.keys()
            running = {n for n, pid in supervisor.pids().items() if pid}
            silent = frozenset((answered & running) - rates.keys())
            for line in status_lines(supervisor, rates, silent):
                emit(line)
            if node is not None and silent and not rates:
                # None of the services that answered before did, while their processes
                # run: this session, not they, is likely at fault (seen on a loaded
                # machine: the launcher's link to the camera stopped being read, and every
                # later tick came back empty for 25 minutes while `ls` saw all four).
                # The next tick asks through a new one.
                node.close()
                node = None
    finally:
        if node is not None:
            node.close()


def _refuse_if_running(net: NetworkConfig, names: list[str]) -> None:
    """ConfigError if a service this launch would start is live already (a demo, another
    deploy file): each of ours would fail to offer its name and be restarted in a loop.
    Not asked when this launch starts the router its services meet through (see
    ``_launch``): nothing can be live on it yet, and a client's session would wait for it."""
    from middleware import Node

    with Node(network=net) as node:
        taken = node.offered_services(names)
        if not taken:
            return
        where = {i.service: f"pid {i.pid} on host {i.host}" for i in node.services(timeout_s=1.0)}
    raise ConfigError(
        f"service {taken[0]!r} is live already ({where.get(taken[0], 'another process')}); "
        "stop it first (a demo, or a launch of another file), or rename the service"
    )


def run(args: argparse.Namespace) -> int:
    if args.json and not args.check:
        raise ConfigError("--json prints the plan of --check; a running launch prints its logs")
    if args.check and args.host is None:
        deployment = load_deployment(args.file)
        if len(deployment.hosts) > 1:
            return _check_every_host(args, deployment)
    deployment, specs = _plan(args)
    if args.check:
        if args.json:
            print_json(plan_json(deployment, args.host, specs))
        else:
            print_plan(deployment, args.host, specs)
        return 0
    if not specs:  # another host's share only: this one would wait for a Ctrl-C, running nothing
        raise ConfigError(
            f"{args.file}: no service runs on host {args.host!r}; nothing to launch here"
        )
    chosen = [s for s in deployment.for_host(args.host) if s.type != "router"]
    net = network(args, deployment.network_for(chosen[0]) if chosen else None)
    with LaunchLock(args.file, args.host, net):
        return _launch(args, deployment, net)


def _prerender(deployment: Deployment, host: str | None, stop: threading.Event) -> bool:
    """Render each approach a ``prerendered`` camera or gyro of this host plays, once, with
    the demo's progress bar and cache, before anything starts; False if stopped."""
    from services.nodes import service
    from services.tools.demo import prerender_approach

    done: set[tuple[int, str, str | None]] = set()
    for svc in deployment.for_host(host):
        if svc.type not in ("camera", "gyro"):
            continue
        parser = argparse.ArgumentParser(add_help=False)
        service(svc.type).add_arguments(parser)
        parsed, _ = parser.parse_known_args(list(svc.args))  # checked by _plan already
        key = (parsed.seed, parsed.floor, parsed.path)
        if parsed.source != "prerendered" or key in done:
            continue
        done.add(key)
        cache = Path(parsed.path) if parsed.path else None
        if not prerender_approach(parsed.seed, parsed.floor, cache, stop):
            return False
    return True


def run_seconds(duration_s: float | None, specs: list[ProcessSpec], now_ns: int) -> float | None:
    """How long the supervisor runs for ``--duration``: the services wait for their shared
    start instant (``FRAMEGATE_START_AT_NS``), and ``--duration`` counts from there, so
    ``--duration 2`` gives 2 s of frames (it gave none: the 2 s went by in the start delay)."""
    if duration_s is None:
        return None
    starts = [int(v) for spec in specs for k, v in spec.env if k == "FRAMEGATE_START_AT_NS"]
    wait_s = max(0, max(starts, default=now_ns) - now_ns) / 1e9
    return wait_s + duration_s


def _launch(args: argparse.Namespace, deployment: Deployment, net: NetworkConfig) -> int:
    stop = stop_on_signals()
    ours = deployment.for_host(args.host)
    if not any(s.type == "router" for s in ours):
        _refuse_if_running(net, [s.name for s in ours if s.type != "router"])
    if stop.is_set() or not _prerender(deployment, args.host, stop):
        return 0  # stopped while checking or rendering: start nothing
    # Planned again after the rendering: the processes share a start instant, which a plan
    # made before minutes of rendering would have put that far in the past.
    _, specs = _plan(args)
    supervisor = Supervisor(specs, colour=False if args.no_colour else None)
    print(f"launching {', '.join(s.name for s in specs)} (Ctrl-C stops everything)", flush=True)
    status_stop = threading.Event()
    status: threading.Thread | None = None
    if args.status is not None:
        status = threading.Thread(
            target=_status_loop,
            args=(supervisor, net, args.status, status_stop, lambda t: print(t, flush=True)),
            name="fg-launch-status",
        )
    try:
        # Inside the try: a second signal while children are being started still stops
        # every child started so far (a first one only sets `stop`).
        supervisor.start()
        if status is not None:
            status.start()
        supervisor.run(run_seconds(args.duration, specs, time.time_ns()), stop=stop)
    except KeyboardInterrupt:  # a second Ctrl-C while stopping
        supervisor.stop(timeout_s=0.0)
    finally:
        # Joined, not left as a daemon: its Zenoh session must close before finalisation.
        status_stop.set()
        if status is not None and status.is_alive():
            status.join()
    # A service that died and was restarted, running again at the stop, was said when it
    # died; a clean stop of a pipeline that is up is a success (as systemd must see it).
    return report_failures(supervisor.failures(recovered=False))
