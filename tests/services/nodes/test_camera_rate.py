"""A source that cannot keep its rate says so: late skips counted, one warning with why."""

from __future__ import annotations

import logging

import pytest

from services.nodes.camera import KEEP_UP_SHARE, RateWatch

PERIOD_NS = 66_666_667
LOG = logging.getLogger("test-camera-rate")


def _watch_with_one_frame() -> RateWatch:
    watch = RateWatch(PERIOD_NS, 1.0)
    watch.loaded(30_000_000)  # one frame made, in 30 ms
    return watch


def test_a_source_below_90_percent_warns_once_with_its_render_time(
    caplog: pytest.LogCaptureFixture,
) -> None:
    watch = _watch_with_one_frame()
    with caplog.at_level(logging.WARNING, logger=LOG.name):
        for i in range(200):
            if i % 2:
                watch.made(LOG)
            else:
                watch.late(LOG)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1, warnings
    assert "cannot keep its rate" in warnings[0]
    assert "ms per frame" in warnings[0] and "CPU" in warnings[0]
    assert "of 15.0 frames/s" in warnings[0]
    assert watch.late_total == 100


def test_a_source_that_keeps_its_rate_stays_quiet(caplog: pytest.LogCaptureFixture) -> None:
    watch = _watch_with_one_frame()
    with caplog.at_level(logging.WARNING, logger=LOG.name):
        for i in range(200):
            if i % 20 == 0:  # 95 % made
                watch.late(LOG)
            else:
                watch.made(LOG)
    assert not [r for r in caplog.records if r.levelno == logging.WARNING]
    assert KEEP_UP_SHARE == 0.9


def test_late_frames_before_the_first_one_made_do_not_count() -> None:
    watch = RateWatch(PERIOD_NS, 1.0)
    for _ in range(100):  # the first render takes seconds by nature
        watch.late(LOG)
    assert watch.late_total == 100
    assert not watch.warned
