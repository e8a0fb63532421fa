"""The ``quality`` scenario's timing of every blur mode, on a few frames."""

from __future__ import annotations

import pytest

from services.evidence.bench._quality import time_blur_modes


def test_every_blur_mode_is_timed_in_microseconds_per_frame() -> None:
    results = time_blur_modes(frames=3, repeat=1)
    assert set(results) == {
        "center",
        "point",
        "mean_grid",
        "max_grid",
        "roi_max",
        "rolling_center",
        "rolling_max_grid",
    }
    assert all(value > 0 for value in results.values())


def test_timing_no_frames_is_refused() -> None:
    with pytest.raises(ValueError, match="frames and repeat must be >= 1"):
        time_blur_modes(frames=0)
