"""The experiment's figures: gyro rates over exposures (Fig. 7), estimated against true blur
(Fig. 8), and the filtered run over time.

Figures are drawn on ``matplotlib.figure.Figure`` directly, never through pyplot, so no
display backend or global state is involved.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from services.lib.messages import DecisionRecord
from services.lib.sim import Dataset

_ACCEPTED = "#2ca02c"
_REJECTED = "#d62728"
_DROPPED = "#7f7f7f"
_WINDOW_FRAMES = 24


def _frame_times_s(dataset: Dataset) -> np.ndarray:
    starts = np.array([f.exposure_start_ns for f in dataset.frames], dtype=np.int64)
    times: np.ndarray = (starts - starts[0]) / 1e9
    return times


def _busiest_window(decisions: Mapping[int, DecisionRecord], frames: int) -> int:
    """First frame of the window where quality decided most often: the most frames rejected
    while the detector still had room (load < 1), where q <= load did the rejecting."""
    rejected = np.zeros(frames)
    for frame_id, decision in decisions.items():
        if 0 <= frame_id < frames and not decision.accepted and decision.load < 1.0:
            rejected[frame_id] = 1.0
    width = min(_WINDOW_FRAMES, frames)
    sums = np.convolve(rejected, np.ones(width), mode="valid")
    return int(np.argmax(sums)) if sums.size else 0


def plot_gyro_exposures(
    dataset: Dataset, decisions: Sequence[DecisionRecord], out: Path, *, title: str = ""
) -> Path:
    """Fig. 7: the gyro's angular rates about the camera's x and y axes over a window of the
    approach, every exposure shaded by what the mediator did with the frame."""
    by_frame = {d.frame_id: d for d in decisions}
    frames = len(dataset)
    first = _busiest_window(by_frame, frames)
    last = min(frames, first + _WINDOW_FRAMES) - 1
    epoch_ns = dataset.frames[first].exposure_start_ns
    offset_ns = dataset.camera.gyro_time_offset_ns
    lo_ns = epoch_ns - dataset.frames[first].exposure_ns
    hi_ns = dataset.frames[last].exposure_start_ns + 2 * dataset.frames[last].exposure_ns
    gyro = dataset.gyro.between(lo_ns + offset_ns, hi_ns + offset_ns)
    rotation = np.asarray(dataset.camera.gyro_to_camera, dtype=np.float64).reshape(3, 3)
    rates_deg_s = np.degrees(gyro.rate_rad_s @ rotation.T)
    t_s = (gyro.t_ns - offset_ns - epoch_ns) / 1e9

    fig = Figure(figsize=(11, 5.2), layout="constrained")
    ax = fig.add_subplot()
    for index in range(first, last + 1):
        info = dataset.frames[index]
        start = (info.exposure_start_ns - epoch_ns) / 1e9
        decision = by_frame.get(index)
        colour = _DROPPED if decision is None else _ACCEPTED if decision.accepted else _REJECTED
        ax.axvspan(start, start + info.exposure_ns / 1e9, color=colour, alpha=0.22, lw=0)
        if decision is not None and decision.quality is not None:
            label = f"q {decision.quality:.2f} L {decision.load:.1f}"
            ax.text(start + info.exposure_ns / 2e9, 0.98, label,
                    transform=ax.get_xaxis_transform(), ha="center", va="top",
                    fontsize=7, rotation=90)  # fmt: skip
    ax.plot(t_s, rates_deg_s[:, 0], lw=1.0, color="#1f77b4", label="about camera x (pitch)")
    ax.plot(t_s, rates_deg_s[:, 1], lw=1.0, color="#ff7f0e", label="about camera y (yaw)")
    ax.axhline(0.0, color="black", lw=0.5)
    low, high = ax.get_ylim()
    ax.set_ylim(low, high + 0.3 * (high - low))  # room for the q and load labels
    ax.set_xlabel(f"time since frame {first}'s exposure start (s)")
    ax.set_ylabel("angular rate (deg/s)")
    handles, _labels = ax.get_legend_handles_labels()
    handles += [
        Patch(color=_ACCEPTED, alpha=0.4, label="exposure, accepted"),
        Patch(color=_REJECTED, alpha=0.4, label="exposure, rejected"),
        Patch(color=_DROPPED, alpha=0.4, label="exposure, no decision"),
    ]
    fig.legend(handles=handles, loc="outside lower center", fontsize=8, ncol=5)
    ax.set_title(
        (title + "\n" if title else "")
        + f"Fig. 7: gyro rates during exposure, frames {first}-{last} "
        "(quality q and detector load L of each frame at the top)",
        fontsize=10,
    )
    fig.savefig(out, dpi=120)
    return out


def plot_quality_vs_blur(
    series: Mapping[str, tuple[Sequence[float], Sequence[float], Sequence[float]]],
    pearson: float,
    spearman: float,
    out: Path,
    *,
    b0_px: float,
) -> Path:
    """Fig. 8: the mediator's estimated blur (left) and quality q (right) against the true
    blur at the image centre; ``series`` maps a label (seed) to (estimated, q, true)."""
    fig = Figure(figsize=(11, 4.8), layout="constrained")
    left, right = fig.subplots(1, 2)
    top = 1.0
    count = 0
    for label, (estimated, q, true) in series.items():
        left.scatter(true, estimated, s=8, alpha=0.6, label=label)
        right.scatter(true, q, s=8, alpha=0.6, label=label)
        if len(true):
            top = max(top, float(np.max(true)), float(np.max(estimated)))
        count += len(true)
    line = np.linspace(0.0, top, 100)
    left.plot(line, line, color="black", lw=0.8, ls="--", label="estimate = truth")
    right.plot(line, np.exp(-line / b0_px), color="black", lw=0.8, ls="--",
               label=f"exp(-true blur / {b0_px:g} px)")  # fmt: skip
    left.set_xlabel("true blur at the image centre (px)")
    left.set_ylabel("estimated blur, mediator (px)")
    right.set_xlabel("true blur at the image centre (px)")
    right.set_ylabel("quality q = exp(-estimated blur / b0)")
    left.text(
        0.03, 0.97, f"Pearson r = {pearson:.3f}\nSpearman ρ = {spearman:.3f}\nn = {count} frames",
        transform=left.transAxes, va="top", fontsize=10,
        bbox={"boxstyle": "round", "facecolor": "white", "alpha": 0.85},
    )  # fmt: skip
    left.legend(fontsize=8, loc="lower right")
    right.legend(fontsize=8, loc="upper right")
    fig.suptitle("Fig. 8: gyro-estimated blur and quality against the true blur", fontsize=11)
    fig.savefig(out, dpi=120)
    return out


def plot_timeline(
    dataset: Dataset,
    decisions: Sequence[DecisionRecord],
    processed: Mapping[str, Sequence[int]],
    out: Path,
    *,
    title: str = "",
) -> Path:
    """The filtered run over time: load and q with accept/reject (top), the true blur at the
    image centre (middle) and which frames each run's detector processed (bottom)."""
    times = _frame_times_s(dataset)
    fig = Figure(figsize=(12, 7.5), layout="constrained")
    top, middle, bottom = fig.subplots(3, 1, sharex=True, height_ratios=(2.2, 1.4, 1.2))
    ordered = sorted(decisions, key=lambda d: d.frame_id)
    valid = [d for d in ordered if 0 <= d.frame_id < len(times)]
    t = np.array([times[d.frame_id] for d in valid])
    load = np.array([d.load for d in valid])
    top.step(t, load, where="post", color="black", lw=0.9, label="load (detector queue fill)")
    for accepted, colour, label in ((True, _ACCEPTED, "accepted"), (False, _REJECTED, "rejected")):
        chosen = [d for d in valid if d.accepted == accepted and d.quality is not None]
        top.scatter([times[d.frame_id] for d in chosen], [d.quality for d in chosen], s=12,
                    color=colour, label=f"q, {label} ({len(chosen)})", zorder=3)  # fmt: skip
    top.set_ylabel("q, load")
    top.set_ylim(-0.05, 1.1)
    top.legend(fontsize=8, loc="lower left", ncol=3)
    truth = dataset.truth or ()
    middle.plot(times[: len(truth)], [f.centre_blur_px for f in truth], color="#9467bd", lw=0.9)
    middle.set_ylabel("true centre\nblur (px)")
    names = list(processed)
    for row, name in enumerate(names):
        ids = [i for i in processed[name] if 0 <= i < len(times)]
        bottom.scatter(times[ids], np.full(len(ids), row), marker="|", s=60, lw=1.0)
    bottom.set_yticks(range(len(names)), names)
    bottom.set_ylim(-0.7, len(names) - 0.3)
    bottom.set_ylabel("processed")
    bottom.set_xlabel("time since the first exposure (s)")
    fig.suptitle((title + ": " if title else "") + "the filtered run over time", fontsize=11)
    fig.savefig(out, dpi=110)
    return out


def plot_captured(results: Mapping[str, object], path: Path) -> None:
    """Captured fraction of the oracle's gain (all markers summed) per policy across N, one
    panel per floor, one line style per service factor (the sweep's figure)."""
    config = results["config"]
    points = results["points"]
    assert isinstance(config, Mapping) and isinstance(points, Sequence)
    floors = list(config["floors"])
    policies = list(config["policies"])
    factors = list(config["factors"])
    figure = Figure(figsize=(4.2 * len(floors), 3.6), layout="constrained")
    axes = figure.subplots(1, len(floors), sharey=True, squeeze=False)[0]
    styles = ["-", "--", ":", "-."]
    colours = ["#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b"]
    for ax, floor in zip(axes, floors, strict=True):
        for p_index, policy in enumerate(policies):
            for f_index, factor in enumerate(factors):
                chosen = sorted(
                    (pt["queue"], pt["summary"][policy]["total"]["captured"]["mean"])
                    for pt in points
                    if pt["floor"] == floor and pt["service_factor"] == factor
                )
                xs = [q for q, v in chosen if v is not None]
                ys = [100 * v for q, v in chosen if v is not None]
                ax.plot(
                    xs, ys, styles[f_index % len(styles)], marker="o",
                    color=colours[p_index % len(colours)],
                    label=f"{policy}, factor {factor:g}",
                )  # fmt: skip
        ax.axhline(0, color="black", linewidth=0.6)
        ax.axhline(100, color="grey", linewidth=0.6, linestyle=":")
        ax.set_title(f"floor: {floor}")
        ax.set_xlabel("detector queue N")
        ax.set_xticks(sorted({pt["queue"] for pt in points}))
    axes[0].set_ylabel("captured of the oracle's gain (%)")
    axes[-1].legend(fontsize=6, loc="best")
    figure.savefig(path, dpi=120)
