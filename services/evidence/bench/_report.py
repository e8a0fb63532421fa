"""The human-readable table of a report (the same dict that goes to ``--json``).

Compact on purpose: one line per row, at most ``WIDTH`` columns — the row, its unit, the
raw and framegate medians, framegate/raw and the goal (verdict, measured value, limit); a
scenario whose columns mean something else (``params["legend"]``) says so under its name.
Everything else (min/max, every sample, CPU per process, the goals' full texts, the
parameters) is in the JSON report.
"""

from __future__ import annotations

import textwrap
from typing import Any

WIDTH = 100
_NAME = 38
_UNIT = 6
_VALUE = 9
_RATIO = 6
_UNITS = {"% of a core": "%core", "% core": "%core", "x payload": "x pay", "us/frame": "us/fr"}


def _num(value: float | None) -> str:
    if value is None:
        return "-"
    if abs(value) >= 100:
        return f"{value:,.0f}"
    if abs(value) >= 10:
        return f"{value:.1f}"
    return f"{value:.3f}"


def _cut(text: str, width: int) -> str:
    return text if len(text) <= width else text[: width - 1] + "~"


def _median(side: dict[str, Any] | None) -> str:
    if not side or "median" not in side:
        return "-"
    return _num(side["median"])


def short_goal(goal: dict[str, Any] | None) -> str:
    """``PASS|MISS|n/a <measured> <comparison> <limit>`` (``x`` marks a multiple of raw)."""
    if not goal:
        return ""
    verdict = {True: "PASS", False: "MISS", None: "n/a"}[goal["passed"]]
    times = "x" if str(goal["text"]).endswith("x raw") else ""
    return f"{verdict} {_num(goal['measured'])} {goal['comparison']} {goal['limit']:g}{times}"


def load_warning(machine: dict[str, Any], share: float) -> str | None:
    """``figures unreliable: ...`` when the 1-min load at start exceeds ``share`` × cores."""
    load, cores = machine.get("load_average_start"), machine.get("cpu_count")
    if not load or not cores or load[0] <= share * cores:
        return None
    return (
        f"figures unreliable: load {load[0]:.2f} at start on {cores} cores "
        f"(more than {share * cores:g})"
    )


def _windows(report: dict[str, Any]) -> str:
    """How long a pair's runs are: ``--duration``, or each scenario's own window where it
    keeps one (ros2-loop's 15 s at least; the header said 0.5 s for it under --quick)."""
    default = float(report["options"]["duration_s"])
    own = {
        name: float(window)
        for name, scenario in report["scenarios"].items()
        if isinstance(window := scenario.get("params", {}).get("window_s"), int | float)
    }
    windows = {name: own.get(name, default) for name in report["scenarios"]}
    if len(set(windows.values())) == 1:
        return f"{next(iter(windows.values())):g} s"
    others = ", ".join(f"{name} {window:g} s" for name, window in own.items() if window != default)
    return f"{default:g} s ({others})"


def header(report: dict[str, Any]) -> str:
    machine, options = report["machine"], report["options"]
    load = machine.get("load_average_start")
    return _cut(
        f"framegate bench{' (quick)' if options['quick'] else ''}: "
        f"{options['pairs']} pair(s) of {_windows(report)}; "
        f"{machine['cpu_count']} cores" + (f", load {load[0]:.2f}" if load else "") + "; "
        f"Python {machine['python']}, zenoh {machine['zenoh']}",
        WIDTH,
    )


def _reason(scenario: dict[str, Any]) -> str:
    """A failed scenario's reason, its last part when long (a worker's stderr tail ends
    with the exception)."""
    reason = str(scenario["reason"])
    return reason.rsplit(" | ", 1)[-1].strip() if len(reason) > 60 else reason


def _line(cells: list[str]) -> str:
    name, unit, raw, fg, ratio, goal = cells
    return (
        f"  {_cut(name, _NAME):<{_NAME}} {_cut(unit, _UNIT):<{_UNIT}} {raw:>{_VALUE}} "
        f"{fg:>{_VALUE}} {ratio:>{_RATIO}}  {goal}"
    ).rstrip()


def format_table(report: dict[str, Any], *, notes: bool = False) -> str:
    """One line per row under its scenario, then the goals passed; ``notes``: each
    scenario's notes, wrapped."""
    lines = [header(report)]
    lines += [f"WARNING: {w}" for w in report.get("warnings", [])]
    lines += ["", _line(["row", "unit", "raw", "framegate", "fg/raw", "goal"])]
    for name, scenario in report["scenarios"].items():
        if scenario["status"] != "ok":
            lines.append(_cut(f"{name}: {scenario['status']}: {_reason(scenario)}", WIDTH))
            continue
        lines.append(name)
        if legend := scenario.get("params", {}).get("legend"):
            # Columns that mean something else here than raw Zenoh against framegate.
            lines += textwrap.wrap(legend, WIDTH, initial_indent="  ", subsequent_indent="    ")
        for r in scenario["rows"]:
            unit = _UNITS.get(str(r["unit"]), str(r["unit"]))
            lines.append(
                _line(
                    [
                        str(r["name"]),
                        unit,
                        _median(r.get("raw")),
                        _median(r.get("framegate")),
                        _num(r["ratio"]) if r.get("ratio") is not None else "",
                        short_goal(r.get("goal")),
                    ]
                )
            )
        if notes:
            for note in dict.fromkeys(r["note"] for r in scenario["rows"] if r.get("note")):
                lines += textwrap.wrap(
                    f"note: {note}", WIDTH, initial_indent="  ", subsequent_indent="    "
                )
    goals = report.get("goals", [])
    if goals:
        passed = sum(1 for g in goals if g["passed"])
        missed = sum(1 for g in goals if g["passed"] is False)
        lines += ["", f"goals: {passed}/{len(goals)} passed, {missed} missed (details: --json)"]
    return "\n".join(_cut(line, WIDTH) for line in lines)
