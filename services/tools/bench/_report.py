"""The human-readable table of a report (the same dict that goes to ``--json``)."""

from __future__ import annotations

from typing import Any


def _num(value: float | None) -> str:
    if value is None:
        return "-"
    if abs(value) >= 100:
        return f"{value:,.0f}"
    if abs(value) >= 10:
        return f"{value:.1f}"
    return f"{value:.3f}"


def _side(side: dict[str, Any] | None) -> str:
    if not side or "median" not in side:
        return "-"
    return f"{_num(side['median'])} [{_num(side['min'])}..{_num(side['max'])}]"


def _cpu(side: dict[str, Any] | None) -> str:
    cpu = (side or {}).get("cpu_pct")
    if not cpu:
        return ""
    return f"{cpu.get('producer', 0):.0f}/{cpu.get('consumer', 0):.0f}"


def _is_cost(row: dict[str, Any]) -> bool:
    return str(row["metric"]).startswith("CPU") and row.get("extra") is not None


def _goal(goal: dict[str, Any] | None) -> str:
    if not goal:
        return ""
    verdict = {True: "PASS", False: "MISS", None: "n/a"}[goal["passed"]]
    return f"{verdict} {goal['text']} (measured {_num(goal['measured'])})"


def header(report: dict[str, Any]) -> str:
    machine, options = report["machine"], report["options"]
    load = machine.get("load_average_start")
    return (
        f"framegate bench: {machine['cpu_count']} cores, Python {machine['python']}, "
        f"zenoh {machine['zenoh']}, numpy {machine['numpy']}; "
        f"{options['pairs']} pair(s) of {options['duration_s']:g} s windows"
        f"{' (quick)' if options['quick'] else ''}"
        + (f"; load average at start {load[0]:.2f}" if load else "")
    )


def format_table(report: dict[str, Any]) -> str:
    """One block per scenario: median [min..max] per side, framegate/raw, CPU, goal."""
    lines = [header(report), ""]
    for name, scenario in report["scenarios"].items():
        if scenario["status"] != "ok":
            lines += [f"{name}: {scenario['status']}: {scenario['reason']}", ""]
            continue
        rows = scenario["rows"]
        units = sorted({f"{r['metric']} ({r['unit']})" for r in rows})
        lines.append(f"{name}: {', '.join(units)}")
        has_cpu = any(_cpu(r.get("raw")) or _cpu(r.get("framegate")) for r in rows)
        # What framegate adds matters for cost rows (CPU), not for rates or latencies.
        has_extra = any(_is_cost(r) for r in rows)
        table = [
            ["", "raw median [min..max]", "framegate median [min..max]", "fg/raw"]
            + (["fg-raw"] if has_extra else [])
            + (["CPU% raw p/c", "CPU% fg p/c"] if has_cpu else [])
            + ["goal"]
        ]
        for r in rows:
            table.append(
                [r["name"], _side(r.get("raw")), _side(r.get("framegate")), _num(r["ratio"])]
                + ([_num(r.get("extra")) if _is_cost(r) else ""] if has_extra else [])
                + ([_cpu(r.get("raw")), _cpu(r.get("framegate"))] if has_cpu else [])
                + [_goal(r.get("goal"))]
            )
        widths = [max(len(row[i]) for row in table) for i in range(len(table[0]))]
        for row in table:
            cells = [
                cell.ljust(width) if i in (0, len(row) - 1) else cell.rjust(width)
                for i, (cell, width) in enumerate(zip(row, widths, strict=True))
            ]
            lines.append("  " + "  ".join(cells).rstrip())
        for note in dict.fromkeys(r["note"] for r in rows if r.get("note")):
            lines.append(f"  note: {note}")
        lines.append("")
    goals = report.get("goals", [])
    if goals:
        passed = sum(1 for g in goals if g["passed"])
        lines.append(f"goals: {passed}/{len(goals)} passed")
        for g in goals:
            lines.append(f"  {g['scenario']:<14} {g['row']:<28} {_goal(g)}")
    return "\n".join(lines)
