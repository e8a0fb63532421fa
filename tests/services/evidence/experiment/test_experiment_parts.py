"""The experiment's parts that need no processes: configuration, scoring, run plans, plots."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from middleware import ConfigError
from services.evidence.experiment import (
    ExperimentConfig,
    FrameDetections,
    RunKind,
    RunSettings,
    deployment_for,
    recognized_frames,
    run_order,
    scenario_for,
    scenario_hash,
)
from services.evidence.experiment._plots import (
    plot_gyro_exposures,
    plot_quality_vs_blur,
    plot_timeline,
)
from services.lib.camera_model import CameraModel
from services.lib.messages import DecisionRecord, detections_metadata
from services.lib.sim import Dataset, FrameInfo, FrameTruth, GyroTrace, MarkerTruth


def _marker(name: str, marker_id: int, centre: tuple[float, float]) -> MarkerTruth:
    return MarkerTruth(name, marker_id, True, 20.0, 2.0, centre, True)


def _truth(frame_id: int, blur_px: float = 1.0) -> FrameTruth:
    markers = (
        _marker("large", 0, (500.0, 300.0)),
        _marker("medium", 1, (480.0, 400.0)),
        _marker("small", 2, (540.0, 400.0)),
    )
    return FrameTruth(frame_id, blur_px, 10.0, 3, markers)


def _square(cx: float, cy: float, half: float = 10.0) -> list[float]:
    return [cx - half, cy - half, cx + half, cy - half, cx + half, cy + half, cx - half, cy + half]


def test_detections_read_back_with_marker_centres() -> None:
    metadata = detections_metadata(
        1_000, 4, "camera/images", 107_000_000, [(0, _square(500, 300)), (2, _square(540, 401))]
    )
    frame = FrameDetections.from_metadata(metadata)
    assert frame.frame_id == 4 and frame.processing_ns == 107_000_000
    assert frame.markers == ((0, 500.0, 300.0), (2, 540.0, 401.0))


def test_a_marker_counts_only_near_its_true_position() -> None:
    truth = [_truth(0), _truth(1), _truth(2)]
    detections = [
        FrameDetections(0, 0, ((0, 503.0, 302.0), (1, 480.0, 400.0))),
        # Id 2 decoded, but 100 px from where the small marker is: a false decode.
        FrameDetections(1, 0, ((2, 640.0, 400.0),)),
        FrameDetections(2, 0, ((2, 551.9, 400.0),)),  # within size/2 + blur = 12 px
        FrameDetections(9, 0, ((0, 500.0, 300.0),)),  # no such frame: ignored
    ]
    found = recognized_frames(detections, truth)
    assert found == {"large": [0], "medium": [0], "small": [2]}


def test_run_order_puts_all_first_and_rotates_the_timed_runs() -> None:
    runs = tuple(RunKind)
    assert run_order(runs, 0) == [
        RunKind.ALL, RunKind.UNCONTROLLED, RunKind.FILTERED, RunKind.BEYOND,
    ]  # fmt: skip
    assert run_order(runs, 1) == [
        RunKind.ALL, RunKind.FILTERED, RunKind.BEYOND, RunKind.UNCONTROLLED,
    ]  # fmt: skip
    assert run_order(runs, 3) == run_order(runs, 0)


def _dataset(tmp_path: Path, frames: int = 30) -> Dataset:
    period = 66_666_667
    infos = tuple(FrameInfo(i, 500_000_000 + i * period, 60_000_000) for i in range(frames))
    t_ns = np.arange(0, 500_000_000 + frames * period + 500_000_000, 1_000_000)
    rates = np.stack([0.1 * np.sin(t_ns / 1e8), 0.05 * np.cos(t_ns / 1.3e8), 0 * t_ns], axis=1)
    camera = CameraModel(1024, 768, 558.5, 558.5, 511.5, 383.5, gyro_time_offset_ns=2_500_000)
    truth = tuple(_truth(i, blur_px=float(i % 5)) for i in range(frames))
    files = tuple(f"frames/{i:06d}.png" for i in range(frames))
    return Dataset(tmp_path, camera, infos, files, GyroTrace(t_ns, rates), truth, None)


def test_deployments_follow_the_papers_configurations(tmp_path: Path) -> None:
    dataset = _dataset(tmp_path)
    settings = RunSettings(queue=2, service_factor=1.6, b0_px=5.0, startup_s=5.0)

    def args(kind: RunKind) -> dict[str, tuple[str, ...]]:
        return {s.name: s.args for s in deployment_for(kind, dataset, settings).services}

    every = args(RunKind.ALL)
    assert set(every) == {"camera", "gyro", "detector"}
    assert "--lossless" in every["camera"]
    assert every["detector"][every["detector"].index("--queue") + 1] == "38"
    assert "--service-factor" not in every["detector"]
    uncontrolled = args(RunKind.UNCONTROLLED)
    assert "--lossless" not in uncontrolled["camera"]
    detector = uncontrolled["detector"]
    assert detector[detector.index("--input") + 1] == "camera/images"
    assert detector[detector.index("--queue") + 1] == "2"
    assert detector[detector.index("--service-factor") + 1] == "1.6"
    filtered, beyond = args(RunKind.FILTERED), args(RunKind.BEYOND)
    assert filtered["mediator"][:2] == ("--policy", "paper")
    assert beyond["mediator"][:2] == ("--policy", "adaptive")
    assert filtered["detector"][filtered["detector"].index("--input") + 1] == "mediator/images"
    assert all(not s.restart for s in deployment_for(RunKind.BEYOND, dataset, settings).services)


def test_scenario_is_the_simulator_default_but_for_seed_and_length() -> None:
    assert scenario_for(3, None).frame_count == 319
    assert scenario_for(3, 60).frame_count == 60
    assert scenario_for(3, None).replace(seed=0) == scenario_for(0, None)
    assert scenario_hash(scenario_for(1, None)) == scenario_hash(scenario_for(1, None))
    assert scenario_hash(scenario_for(1, None)) != scenario_hash(scenario_for(2, None))


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"seeds": ()}, "at least one seed"),
        ({"seeds": (1, 1)}, "seeds repeat"),
        ({"queue": 0}, "--queue must be >= 1, got 0"),
        ({"service_factor": 0.0}, "--service-factor must be > 0"),
        ({"b0_px": -1.0}, "--b0 must be > 0 px, got -1.0"),
        ({"frames": 1}, "--frames must be >= 2"),
        ({"runs": (RunKind.FILTERED,)}, "'all' run is the reference"),
        ({"startup_s": 12.0}, "--startup must be 1-9 s, got 12.0"),
    ],
)
def test_bad_configuration_names_the_value(
    tmp_path: Path, changes: dict[str, object], message: str
) -> None:
    with pytest.raises(ConfigError, match=message):
        ExperimentConfig(out=tmp_path, **changes)  # type: ignore[arg-type]


def test_quick_means_sixty_frames_and_the_cache_defaults_to_out(tmp_path: Path) -> None:
    assert ExperimentConfig(out=tmp_path, quick=True).frame_count == 60
    assert ExperimentConfig(out=tmp_path).frame_count is None
    assert ExperimentConfig(out=tmp_path).dataset_cache == tmp_path / "datasets"


def _decision(frame_id: int, accepted: bool, q: float, load: float) -> DecisionRecord:
    return DecisionRecord(
        1_000 + frame_id, frame_id, -5 * np.log(q), q, load, accepted, "r", "paper", 5.0, 10
    )


def test_figures_are_written(tmp_path: Path) -> None:
    dataset = _dataset(tmp_path)
    decisions = [_decision(i, i % 3 != 0, 0.2 + 0.02 * i, 0.5) for i in range(0, 30, 1) if i != 7]
    fig7 = plot_gyro_exposures(dataset, decisions, tmp_path / "fig7.png", title="test")
    fig8 = plot_quality_vs_blur(
        {"seed 1": ([1.0, 2.0, 3.0], [0.8, 0.6, 0.5], [1.1, 2.1, 2.9])},
        0.99, 1.0, tmp_path / "fig8.png", b0_px=5.0,
    )  # fmt: skip
    timeline = plot_timeline(
        dataset, decisions, {"all": list(range(30)), "filtered": [0, 3, 5]},
        tmp_path / "timeline.png",
    )  # fmt: skip
    for path in (fig7, fig8, timeline):
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
