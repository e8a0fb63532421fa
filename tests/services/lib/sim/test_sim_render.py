"""Rendering: the generator API, rolling shutter, and the recognition report."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from services.lib.sim import (
    Bump,
    Scenario,
    ScenarioConfig,
    read_dataset,
    recognition_report,
    simulate,
)

SmallConfig = Callable[..., ScenarioConfig]


def test_frames_yields_infos_and_the_same_images_as_render(small_config: SmallConfig) -> None:
    scenario = Scenario(small_config(seed=4))
    frames = list(scenario.frames(start=1))
    assert [info.frame_id for info, _ in frames] == [1, 2, 3]
    for info, image in frames:
        assert image.dtype == np.uint8 and image.shape == (192, 256)
        assert info == scenario.frame_info(info.frame_id)
        assert np.array_equal(image, scenario.render(info.frame_id))


def test_more_motion_means_more_substeps(small_config: SmallConfig) -> None:
    steady = Scenario(small_config(bumps=()))
    shaken = Scenario(small_config(bumps=(Bump(0.0, 0.01, 0.08, "left"),)))
    assert steady.truth(2, detect=False).substeps <= 2
    assert shaken.truth(2, detect=False).substeps > 4 * steady.truth(2, detect=False).substeps


def test_rolling_shutter_renders_rows_at_their_own_time(small_config: SmallConfig) -> None:
    shaky = small_config(
        bumps=(Bump(0.0, 0.01, 0.08, "both"),), width_px=512, height_px=384, frame_count=4
    )
    global_shutter = Scenario(shaky)
    rolling = Scenario(shaky.replace(line_readout_ns=60_000))  # 23 ms from top to bottom
    assert rolling.camera.line_readout_ns == 60_000
    assert rolling.renderer.substeps(3)[1] > 1  # several row bands while shaken
    a, b = global_shutter.render(3).astype(int), rolling.render(3).astype(int)
    # Early rows are exposed almost with the global shutter; later ones (both on the wall,
    # above the floor) see the camera several milliseconds further along its motion.
    early = np.abs(a[:40] - b[:40]).mean()
    later = np.abs(a[140:180] - b[140:180]).mean()
    assert later > 2 * early


def test_report_counts_are_consistent(tmp_path: Path, small_config: SmallConfig) -> None:
    # Full resolution 3 m from the wall: the small marker is about 21 px, readable.
    config = ScenarioConfig(start_distance_m=3.0, frame_count=3, seed=1)
    simulate(config, tmp_path, progress=False)
    dataset = read_dataset(tmp_path)
    seen: list[int] = []
    report = recognition_report(dataset, on_frame=seen.append)
    assert seen == [0, 1, 2]
    assert report.frame_count == 3
    for marker in report.markers:
        assert marker.recognized <= marker.recognizable <= 3
        assert sum(b.recognizable for b in marker.bins) == marker.recognizable
    small = next(m for m in report.markers if m.name == "small")
    assert small.recognizable == 3
    assert "small" in report.table()
