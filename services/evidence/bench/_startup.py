"""``startup``: how long a command-line call takes, from exec to exit.

Two rows, each the wall time of a fresh process, median of ``STARTUP_RUNS`` runs per sample:

- ``framegate --help`` against ``python -c pass`` (the interpreter's own floor);
- ``framegate ls`` against ``STARTUP_SERVICES`` live framegate services (idle nodes with two
  buffers each, on a private loopback rendezvous), next to a raw zenoh-python script that
  does what ``ls`` does on the wire: open a session to the same rendezvous, list the
  services' liveliness tokens, ask every service for its description, close.

Goals (from the first-hour issue): ``--help`` <= ``HELP_GOAL_S``, ``ls`` <= ``LS_GOAL_S`` on
an idle 2-core machine. Both commands must succeed and ``ls`` must list every service, or
the sample is an error, not a number.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Sequence

import psutil

from middleware import RENDEZVOUS_DELAY_MS, NetworkConfig
from services.launch import free_port

from ._options import BenchOptions
from ._procs import BenchError, WorkerGroup
from ._records import Goal, Row, ScenarioResult

STARTUP_SERVICES = 4
STARTUP_RUNS = 5
QUICK_STARTUP_RUNS = 3
HELP_GOAL_S = 0.15
LS_GOAL_S = 0.4
COMMAND_TIMEOUT_S = 30.0

# The raw counterpart of ``ls``: only zenoh-python, nothing of framegate imported.
# It connects to every service's endpoint, as framegate's rendezvous does, and opens with
# the same scouting delay.
RAW_LS = """
import json, sys, zenoh
peers, tokens, infos, expected = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("scouting/delay", sys.argv[5])
conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
conf.insert_json5("connect/endpoints", peers)
with zenoh.open(conf) as session:
    # The gets end when every peer has answered; the timeout only bounds a lost answer (2 s
    # was missed at load 11 on 2 cores, failing the whole scenario).
    live = [r for r in session.liveliness().get(tokens, timeout=10.0) if r.ok is not None]
    replies = [r for r in session.get(infos, timeout=10.0) if r.ok is not None]
    if len(live) < expected or len(replies) < expected:
        sys.exit(f"raw ls saw {len(live)} tokens and {len(replies)} descriptions")
"""


def _loopback_listeners(pids: Sequence[int]) -> list[str]:
    """The loopback TCP endpoints these processes listen on."""
    found = []
    for pid in pids:
        for conn in psutil.Process(pid).net_connections(kind="tcp"):
            if conn.status == psutil.CONN_LISTEN and conn.laddr.ip == "127.0.0.1":
                found.append(f"tcp/127.0.0.1:{conn.laddr.port}")
    return found


# A run that fails is repeated this often before the scenario fails: on a loaded machine a
# peer can miss one discovery round (the raw ls saw 3 of 4 services once at load 7).
FAILED_RUN_RETRIES = 2


def _wall_s(argv: Sequence[str], env: dict[str, str], check: str | None = None) -> float:
    """One successful run's wall time; BenchError if ``FAILED_RUN_RETRIES`` + 1 runs in a row
    fail or lack ``check`` in their output."""
    for _ in range(FAILED_RUN_RETRIES + 1):
        began = time.perf_counter()
        done = subprocess.run(
            list(argv), env=env, capture_output=True, text=True, timeout=COMMAND_TIMEOUT_S
        )
        took = time.perf_counter() - began
        if done.returncode == 0 and (check is None or check in done.stdout):
            return took
    raise BenchError(
        f"{' '.join(argv[:4])} failed (exit {done.returncode}): {done.stderr.strip()[-300:]}"
    )


def startup_rows() -> dict[str, Row]:
    return {
        "help": Row(
            "framegate --help (raw: python -c pass)",
            "start-up",
            "s",
            higher_is_better=False,
            note="wall time of a fresh process, exec to exit",
        ),
        "ls": Row(
            f"framegate ls, {STARTUP_SERVICES} live services",
            "start-up",
            "s",
            higher_is_better=False,
            note=(
                "raw: zenoh-python opens a session, lists the liveliness tokens and asks "
                "every service for its description"
            ),
        ),
    }


def run_startup(options: BenchOptions) -> ScenarioResult:
    runs = QUICK_STARTUP_RUNS if options.quick else STARTUP_RUNS
    port = free_port()
    # The raw side is a peer of its own: it knows framegate's key layout, as _raw does.
    namespace = NetworkConfig().namespace
    services = [f"startup{i}" for i in range(STARTUP_SERVICES)]
    env = {**os.environ, "FRAMEGATE_LOCAL_PORT": str(port)}
    for name in ("FRAMEGATE_CONNECT", "FRAMEGATE_LISTEN", "FRAMEGATE_CONFIG"):
        env.pop(name, None)
    cli = [sys.executable, "-m", "services.cli"]
    rows = startup_rows()
    result = ScenarioResult(
        "startup",
        params={"services": STARTUP_SERVICES, "runs_per_sample": runs, "local_port": port},
    )
    with WorkerGroup() as group:
        workers = [
            group.start("fg-idle", {"service": name, "offers": ["a", "b"], "local_port": port})
            for name in services
        ]
        group.wait_ready()
        peers = _loopback_listeners([w.proc.pid for w in workers])
        _measure(rows, _commands(cli, peers, namespace, services), env, runs, options)
    rows["help"].goal = Goal(
        f"framegate --help <= {HELP_GOAL_S:g} s",
        HELP_GOAL_S,
        False,
        rows["help"].median("framegate"),
    )
    rows["ls"].goal = Goal(
        f"framegate ls <= {LS_GOAL_S:g} s", LS_GOAL_S, False, rows["ls"].median("framegate")
    )
    result.rows.extend(rows.values())
    return result


def _commands(
    cli: list[str], peers: list[str], namespace: str, services: list[str]
) -> dict[str, dict[str, tuple[list[str], str | None]]]:
    """row -> side -> (argv, text its output must contain)."""
    return {
        "help": {
            "raw": ([sys.executable, "-c", "pass"], None),
            "framegate": ([*cli, "--help"], "usage"),
        },
        "ls": {
            "raw": (
                [
                    sys.executable,
                    "-c",
                    RAW_LS,
                    json.dumps(peers),
                    f"{namespace}/@svc/*",
                    f"{namespace}/@info/*",
                    str(len(services)),
                    str(RENDEZVOUS_DELAY_MS),
                ],
                None,
            ),
            "framegate": ([*cli, "ls"], services[-1]),
        },
    }


def _measure(
    rows: dict[str, Row],
    commands: dict[str, dict[str, tuple[list[str], str | None]]],
    env: dict[str, str],
    runs: int,
    options: BenchOptions,
) -> None:
    for pair in range(options.pairs):
        for key, row in rows.items():
            for side in ("raw", "framegate"):
                argv, check = commands[key][side]
                walls = [_wall_s(argv, env, check) for _ in range(runs)]
                row.samples(side).append(
                    {"pair": pair, "value": statistics.median(walls), "runs_s": walls}
                )
        options.progress(
            f"startup pair {pair + 1}/{options.pairs}: "
            + ", ".join(
                f"{key} {row.framegate[-1]['value']:.2f} s (raw {row.raw[-1]['value']:.2f})"
                for key, row in rows.items()
                if row.raw is not None
            )
        )
