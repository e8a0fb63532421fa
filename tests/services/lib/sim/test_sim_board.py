"""The rendered board is the board ``services.lib.markers`` describes."""

from __future__ import annotations

import numpy as np

import services.lib.sim
from services.lib.markers import BOARD_MARKERS, detect_markers
from services.lib.sim import Scenario, ScenarioConfig


def test_front_door_lists_a_sorted_all() -> None:
    assert services.lib.sim.__all__ == sorted(services.lib.sim.__all__)


def test_markers_decode_where_the_truth_puts_them_when_close() -> None:
    # Last frames of the approach, no bumps: medium and small are large and sharp.
    config = ScenarioConfig(bumps=(), start_distance_m=2.2, frame_count=1)
    scenario = Scenario(config)
    truth = scenario.truth(0)
    found = {d.name: d for d in detect_markers(scenario.render(0))}
    for marker in ("medium", "small"):
        expected = truth.marker(marker)
        assert expected.in_view and expected.detected_sharp
        assert np.allclose(found[marker].centre_px, expected.centre_px, atol=1.0)
        assert abs(found[marker].size_px - expected.size_px) < 1.0
    # At 2.2 m the large marker (top edge 1.83 m) has left the top of the view.
    assert not truth.marker("large").in_view
    assert "large" not in found


def test_marker_sizes_in_view_follow_the_pinhole() -> None:
    config = ScenarioConfig(bumps=(), frame_count=1)
    truth = Scenario(config).truth(0, detect=False)
    for marker in BOARD_MARKERS:
        expected = config.focal_px * marker.size_m / truth.camera_distance_m
        assert abs(truth.marker(marker.name).size_px - expected) < 0.03 * expected
