"""Soak's report as text."""

from __future__ import annotations

from typing import Any


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
        f"{cam.get('skipped', {}).get('late', 0)} skipped late",
        f"  gyro/rates         {gyro.get('puts')} stored ({gyro.get('per_s')}/s), "
        f"{gyro.get('refused')} refused (dropped after waiting for credit)",
        f"  mediator           {audit['frames_decided']} frames decided: {reasons}",
        f"  mediator/images    {med.get('puts')} stored, {med.get('refused')} refused "
        "(detector's queue full)",
        f"  detector           {det.get('puts')} detections ({det.get('per_s')}/s); "
        f"{audit.get('accepted_with_reason', 0)} accepted frames with a recorded reason "
        "for no detection (consumer-lapsed)",
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
    refusals = ", ".join(
        f"{name} {counts['refused_subscriptions']}"
        for name, counts in el.items()
        if counts.get("refused_subscriptions")
    )
    stalls = ", ".join(
        f"{x['stage']} {x['from_s']:.0f}-{x['to_s']:.0f} s ({x['input_meanwhile']} inputs)"
        for x in report["stalls"]
    )
    lines += [
        "",
        f"restarts: {restarts or 'none'}",
        f"stalls: {stalls or 'none'}",
        f"subscriptions refused by producers: {refusals or 'none'}",
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
