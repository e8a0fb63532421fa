"""table.md from a fixed results mapping."""

from __future__ import annotations

from typing import Any

from services.evidence.experiment import aggregate_markers, format_table, seed_markers


def _seed(
    seed: int, all_: int, unc: int, filt: int, beyond: int, oracle: int | None = None
) -> dict[str, Any]:
    counts = {
        "all": {"large": all_, "medium": all_ + 20, "small": 90},
        "uncontrolled": {"large": unc, "medium": unc, "small": 0},
        "filtered": {"large": filt, "medium": filt + 10, "small": 5},
        "beyond": {"large": beyond, "medium": beyond, "small": 6},
    }
    if oracle is not None:
        counts["oracle"] = {"large": oracle, "medium": oracle, "small": 10}
    run = {
        "processed": 200, "dropped_at_camera": 119, "skipped_late": 0, "forwarded": None,
        "drained": True,
    }  # fmt: skip
    return {
        "seed": seed,
        "frames": 319,
        "markers": seed_markers(counts),
        "runs": {
            "all": {**run, "processed": 319, "dropped_at_camera": 0},
            "uncontrolled": run,
            "filtered": {**run, "dropped_at_camera": 0, "forwarded": 198},
        },
    }


def _results(*seeds: dict[str, Any]) -> dict[str, Any]:
    return {
        "config": {"queue": 2, "service_factor": 1.6, "b0_px": 5.0},
        "seeds": list(seeds),
        "markers": aggregate_markers(list(seeds)),
        "quality_vs_blur": {"pearson": 0.9712, "spearman": 0.9534, "frames": 638},
    }


def test_table_puts_our_mean_and_interval_beside_the_quoted_paper() -> None:
    text = format_table(_results(_seed(1, 240, 150, 156, 160), _seed(2, 250, 160, 168, 170)))
    lines = text.splitlines()
    ours = next(line for line in lines if line.startswith("| large | framegate |"))
    # Means of (240, 250) etc.; t(0.975, 1) = 12.706 times std / sqrt(2) = 5 -> 63.5.
    assert ours.startswith("| large | framegate | 245.0 ± 63.5 | 155.0 ± 63.5 | 162.0 ± 76.2 |")
    improvement = (600 / 150 + 800 / 160) / 2
    assert f"| +{improvement:.1f} ± " in ours
    assert "| large | paper (quoted) | 246 | 154 | 161 | +4.5 | - | - | - |" in lines
    assert "| medium | paper (quoted) | 272 | 159 | 178 | +11.9 | - | - | - |" in lines
    assert "| small | paper (quoted) | 99 | 62 | 71 | +14.5 | - | - | - |" in lines
    assert "over 2 seeds (Student's t, 1 degrees of freedom)" in text
    assert "quoted verbatim" in text


def test_table_lists_every_seed_and_what_each_run_did() -> None:
    text = format_table(_results(_seed(1, 240, 150, 156, 160), _seed(2, 250, 160, 168, 170)))
    assert "| 1 | large | 240 | 150 | 156 | +4.0 | 160 | +6.7 |" in text
    assert "| 2 | small | 90 | 0 | 5 | - | 6 | - |" in text
    assert "| 1 | 319 / 0 / 0 | 200 / 119 / 0 | 200 / 0 / 0 (fwd 198) | - |" in text
    assert "Pearson r = 0.971, Spearman ρ = 0.953" in text
    assert "638 frames" in text


def test_table_of_one_seed_says_there_is_no_interval() -> None:
    text = format_table(_results(_seed(7, 240, 150, 156, 160)))
    assert "one seed, so no confidence interval" in text
    assert "| large | framegate | 240.0 | 150.0 | 156.0 | +4.0 | 160.0 | +6.7 | +2.6 |" in text


def test_table_names_runs_that_could_not_keep_real_time() -> None:
    seed = _seed(3, 240, 150, 156, 160)
    seed["runs"]["filtered"] = {**seed["runs"]["filtered"], "skipped_late": 16}
    seed["runs"]["uncontrolled"] = {**seed["runs"]["uncontrolled"], "drained": False}
    text = format_table(_results(seed, _seed(4, 250, 160, 168, 170)))
    assert (
        "Disturbed runs (the machine could not keep real time; compare with care): "
        "seed 3 uncontrolled (detector did not drain), seed 3 filtered (16 frames late)."
    ) in text


def test_table_says_when_every_run_kept_real_time() -> None:
    results = _results(_seed(1, 240, 150, 156, 160))
    results["machine"] = {"cpus": 2, "load_avg_before": [0.7, 1.9, 3.9], "load_avg_after": [0.9]}
    text = format_table(results)
    assert "Every run kept real time" in text
    assert "Machine: 2 CPUs, 1-minute load average 0.70 before and 0.90 after" in text


def test_table_shows_the_oracle_and_each_runs_share_of_its_gain() -> None:
    text = format_table(
        _results(_seed(1, 240, 150, 156, 160, oracle=170), _seed(2, 250, 160, 168, 170, 180))
    )
    assert "## The gain as a share of the possible" in text
    # Oracle 175 on the mean; filtered captured 6/20 and 8/20 of the gain (35 %), beyond
    # 10/20 both times (50 %, no spread).
    assert (
        "| large | 155.0 ± 63.5 | 175.0 ± 63.5 | 162.0 ± 76.2 | 35 ± 64 | 165.0 ± 63.5 | 50 ± 0 |"
        in text
    )


def test_table_without_an_oracle_has_no_share_section() -> None:
    text = format_table(_results(_seed(1, 240, 150, 156, 160)))
    assert "share of the possible" not in text
