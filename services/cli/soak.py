"""``framegate soak``: the whole pipeline at full speed for minutes; memory and lost elements.

A benchmark, not a CI check: it runs its own private pipeline on a free loopback port (so
it takes no connection flags), prints a table and optionally writes the report as JSON.
Exit code 0 when every goal is met (memory growth <= 5 % after warm-up, nothing lost, no
restarts, no stalled stage), 3 when one is missed.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from services.tools.soak import SoakConfig, run_soak

from ._common import command_parser, exit_on_sigterm

GOAL_MISSED = 3


def register(subparsers: Any) -> None:
    parser = command_parser(
        subparsers,
        "soak",
        "run the whole pipeline at full speed; report memory growth and lost elements",
        network=False,
    )
    add_arguments(parser)
    parser.set_defaults(func=run)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    d = SoakConfig()
    parser.add_argument(
        "--duration", type=float, default=d.duration_s, help="seconds (default %(default)s)"
    )
    parser.add_argument("--json", metavar="FILE", help="also write the report as JSON")
    parser.add_argument(
        "--warmup", type=float, help="seconds before memory counts (default: 1/4, at most 60)"
    )
    parser.add_argument(
        "--sample", type=float, default=d.sample_s, help="seconds between memory samples"
    )
    parser.add_argument(
        "--check", type=float, default=d.check_s, help="seconds between lost-element audits"
    )
    parser.add_argument(
        "--rate", type=float, default=d.rate, help="scenario speed of camera and gyro"
    )
    parser.add_argument("--seed", type=int, default=d.seed, help="simulator seed")
    parser.add_argument(
        "--service-factor",
        type=float,
        help="emulate a slow detector (x frame period); default: no emulated load",
    )
    parser.add_argument("--port", type=int, help="private rendezvous port (default: a free one)")
    parser.add_argument("--show-logs", action="store_true", help="print the services' logs")


def config_from_args(args: argparse.Namespace) -> SoakConfig:
    return SoakConfig(
        duration_s=args.duration,
        warmup_s=args.warmup,
        sample_s=args.sample,
        check_s=args.check,
        rate=args.rate,
        seed=args.seed,
        service_factor=args.service_factor,
        port=args.port,
        show_logs=args.show_logs,
    )


def run(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    exit_on_sigterm()
    print(
        f"soak: running camera, gyro, mediator and detector for {config.duration_s:.0f} s "
        "(Ctrl-C stops early)",
        flush=True,
    )
    report = run_soak(config)
    print(format_report(report), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2, default=str) + "\n")
    goals = report["goals"]
    if not all(v for k, v in goals.items() if k != "memory_growth_at_most"):
        print("soak: a goal was missed (see the table above)", file=sys.stderr)
        return GOAL_MISSED
    return 0


def format_report(report: dict[str, Any]) -> str:
    """The report as a plain-text table."""
    cfg = report["config"]
    lines = [
        f"soak: {report['duration_s']} s, scenario rate {cfg['rate']}x, "
        f"{report['host']['cpus']} CPUs (load {report['host']['loadavg_before'][0]} before, "
        f"{report['host']['loadavg_after'][0]} after), port {cfg['port']}",
        f"memory counts after a warm-up of {report['warmup_s']:.0f} s "
        + (
            f"(image buffers full of retained frames at {report['retention_filled_at_s']:.0f} s)"
            if report["retention_filled_at_s"] is not None
            else "(image buffers still filling: growth includes filling them)"
        ),
        "",
        f"{'process':<10} {'pid':>7} {'RSS after warm-up':>18} {'RSS at end':>11} "
        f"{'peak':>9} {'growth':>8} {'MiB/min':>8}  goal <= {cfg['growth_goal']:.0%}",
    ]
    for name, p in report["processes"].items():
        if p.get("growth") is None:
            lines.append(f"{name:<10} {p.get('pid') or '-':>7}  too few samples after warm-up")
            continue
        lines.append(
            f"{name:<10} {p['pid']:>7} {p['rss_after_warmup_mib']:>14.1f} MiB "
            f"{p['rss_end_mib']:>7.1f} MiB {p['rss_peak_mib']:>5.1f} MiB "
            f"{p['growth']:>+7.1%} {p['slope_mib_per_min']:>+8.2f}  {'ok' if p['ok'] else 'MISSED'}"
        )
    el, audit = report["elements"], report["audit"]
    cam, gyro = el.get("camera/images", {}), el.get("gyro/rates", {})
    med, det = el.get("mediator/images", {}), el.get("detector/detections", {})
    reasons = ", ".join(f"{k} {v}" for k, v in audit["decision_reasons"].items()) or "-"
    lines += [
        "",
        "elements",
        f"  camera/images      {cam.get('puts')} stored ({cam.get('per_s')}/s), "
        f"{cam.get('refused')} refused by flow control, "
        f"{cam.get('skipped_late', '?')} skipped late",
        f"  gyro/rates         {gyro.get('puts')} stored ({gyro.get('per_s')}/s), "
        f"{gyro.get('refused')} refused, "
        f"{gyro.get('dropped_after_wait', '?')} dropped after waiting",
        f"  mediator           {audit['frames_decided']} frames decided: {reasons}",
        f"  mediator/images    {med.get('puts')} stored, {med.get('refused')} refused "
        "(detector's queue full)",
        f"  detector           {det.get('puts')} detections ({det.get('per_s')}/s)",
        "",
        f"lost (goal 0), {audit['checks']} audits while running",
    ]
    labels = {
        "frames_without_decision": "camera frames without a decision "
        f"(of {audit['camera_frames_seen']} seen)",
        "accepted_not_in_mediator": "accepted frames missing from mediator/images "
        f"(of {audit['accepted']})",
        "accepted_not_identical": "accepted frames not byte-identical "
        f"(of {audit['compared_with_camera']} compared)",
        "mediator_not_accepted": "frames in mediator/images never accepted",
        "accepted_without_detection": "accepted frames without a detection "
        f"(of {audit['detected']} detected)",
    }
    for key, label in labels.items():
        lines.append(f"  {label:<62} {audit['lost'][key]}")
    for name, count in report["unqueryable"].items():
        lines.append(f"  {'stored in ' + name + ' but not queryable':<62} {count}")
    lines.append(f"  {'total':<62} {report['lost_total']}")
    restarts = {k: v for k, v in report["restarts"].items() if v}
    goals = report["goals"]
    gone = ", ".join(
        f"{name} {counts['subscriptions_gone']}"
        for name, counts in el.items()
        if counts.get("subscriptions_gone")
    )
    stalls = ", ".join(
        f"{x['stage']} {x['from_s']:.0f}-{x['to_s']:.0f} s ({x['input_meanwhile']} inputs)"
        for x in report["stalls"]
    )
    lines += [
        "",
        f"restarts: {restarts or 'none'}",
        f"stalls: {stalls or 'none'}",
        f"subscription tokens lost by producers (liveliness): {gone or 'none'}",
        "goals: "
        + ", ".join(
            f"{name} {'ok' if goals[key] else 'MISSED'}"
            for name, key in (
                ("memory", "memory_ok"),
                ("lost", "lost_ok"),
                ("restarts", "no_restarts"),
                ("stalls", "no_stalls"),
            )
        ),
    ]
    if report["stall_stacks"]:
        lines.append("stacks of every process at the first stall: see stall_stacks in --json")
    if report["check_errors"]:
        lines.append(f"audit errors: {len(report['check_errors'])} ({report['check_errors'][0]})")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """``python -m services.cli.soak``: the same command, until ``framegate`` lists it."""
    parser = argparse.ArgumentParser(prog="framegate soak", description=__doc__)
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
