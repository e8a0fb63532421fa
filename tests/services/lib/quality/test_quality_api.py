"""The package's front door and the benchmark entry points."""

from __future__ import annotations

import json

import services.lib.quality as quality
from services.lib.quality import bench, bench_quality


def test_all_is_complete_and_sorted_like_ruff_sorts_it() -> None:
    names = quality.__all__
    constants = [n for n in names if n.isupper()]
    assert names == sorted(constants) + sorted(n for n in names if not n.isupper())
    for name in names:
        assert hasattr(quality, name), name


def test_bench_quality_reports_microseconds_per_mode() -> None:
    results = bench_quality(frames=3)
    assert set(results) >= {"center", "mean_grid", "max_grid", "roi_max", "rolling_center"}
    assert all(value > 0 for value in results.values())


def test_bench_main_prints_json(capsys) -> None:  # type: ignore[no-untyped-def]
    assert bench.main(["--frames", "2", "--json"]) == 0
    assert "center" in json.loads(capsys.readouterr().out)
