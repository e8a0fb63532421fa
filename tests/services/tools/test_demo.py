"""The demo's status line, summary, policies, pipeline and approach cache; one short live run."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import psutil
import pytest

from middleware import BufferInfo, ConfigError, NetworkConfig, Node, Retention
from services.cli import build_parser
from services.lib.decisions import POLICIES
from services.lib.sim import ScenarioConfig, cached_dataset, scenario_hash
from services.nodes.sources import SourceSpec, open_frame_source
from services.tools.demo import (
    STATUS_COLUMNS,
    STATUS_LEGEND,
    UNCONTROLLED,
    DemoConfig,
    Status,
    demo_deployment,
    gain_pct,
    print_summary,
    status_line,
)
from tests.conftest import REPO, child_env, free_port, wait_until
from tests.helpers.timing import scaled


def test_status_line_fits_100_columns_even_with_large_counts() -> None:
    counts = Status().counts()
    counts.update(frames=99_999, camera_hz=15.0, late=9_999, accepted=99_999, rejected=99_999)
    line = status_line(counts, {"detector": 99_999, UNCONTROLLED: 9_999}, 999.9)
    assert len(line) <= STATUS_COLUMNS == 100
    assert line.endswith("| found 99999 vs  9999 +900%")
    assert all(len(legend) <= 100 for legend in STATUS_LEGEND.splitlines())


def test_status_line_shows_late_skips_load_and_the_gain() -> None:
    counts = Status().counts()
    counts.update(frames=300, camera_hz=14.9, late=7, accepted=120, rejected=180, load=0.5)
    line = status_line(counts, {"detector": 33, UNCONTROLLED: 30}, 20.0)
    assert "   7 late" in line and "120 fwd   180 left load 0.50" in line
    assert line.endswith("found    33 vs    30  +10%")
    assert status_line(counts, {}, 1.0).endswith("  n/a")


def test_a_service_that_answers_late_keeps_its_last_counts_on_the_line() -> None:
    """A camera stopped for a moment (or starved on a busy machine) misses a reading: its
    frames stay as last seen, they do not fall to 0 (and "left" with them)."""
    camera = BufferInfo(
        "camera", "images", "frame", Retention(), 10, 0, 1, 2, 15.0, 57, 3, 0,
        skipped={"late": 4},
    )  # fmt: skip
    mediator = BufferInfo(
        "mediator", "images", "frame", Retention(), 10, 0, 1, 2, 5.0, 35, 0, 0
    )  # fmt: skip
    known = Status()
    known.update(Status({"camera/images": camera, "mediator/images": mediator}))
    known.update(Status({"mediator/images": replace(mediator, puts=36)}))  # camera late
    counts = known.counts()
    assert (counts["frames"], counts["late"], counts["accepted"]) == (57, 4, 36)
    assert counts["rejected"] == 57 - 36


def test_gain_is_relative_to_the_uncontrolled_detector() -> None:
    assert gain_pct(12, 10) == pytest.approx(20.0)
    assert gain_pct(9, 10) == pytest.approx(-10.0)
    assert gain_pct(5, 0) is None


def test_policy_flag_offers_every_policy() -> None:
    parser = build_parser("demo")
    for name in POLICIES:
        args = parser.parse_args(["demo", "--policy", name])
        assert args.policy == name
    assert {"adaptive", "paper"} <= set(POLICIES)
    with pytest.raises(ConfigError, match="--policy 'nope'"):
        DemoConfig(policy="nope")


def test_the_uncontrolled_detector_observes_the_camera_at_the_same_speed() -> None:
    services = {s.name: s for s in demo_deployment(DemoConfig(service_factor=2.0)).services}
    raw, filtered = services[UNCONTROLLED].args, services["detector"].args
    assert services[UNCONTROLLED].type == "detector"
    assert raw[raw.index("--input") + 1] == "camera/images" and "--observe" in raw
    assert filtered[filtered.index("--input") + 1] == "mediator/images"
    for flag in ("--queue", "--service-factor"):
        assert raw[raw.index(flag) + 1] == filtered[filtered.index(flag) + 1]


def test_summary_lists_each_marker_filtered_against_uncontrolled(
    capsys: pytest.CaptureFixture[str],
) -> None:
    counts = Status().counts()
    counts.update(frames=600, late=3, accepted=330, rejected=270, load=0.5)
    print_summary(
        {
            **counts,
            "duration_s": 46.2,
            "source": "prerendered",
            "floor": "rough",
            "policy": "paper",
            "markers": {"large": {"filtered": 287, "uncontrolled": 275}},
            "recognitions_filtered": 287,
            "recognitions_uncontrolled": 275,
        }
    )
    out = capsys.readouterr().out
    assert "policy paper" in out and "330 forwarded, 270 left out" in out
    assert "  large                287           275     +4%" in out
    assert "  total                287           275     +4%" in out


def test_an_approach_is_rendered_once_and_then_read_from_the_cache(tmp_path: Path) -> None:
    scenario = ScenarioConfig(seed=5).replace(frame_count=2)
    first = cached_dataset(scenario, tmp_path, progress=False)
    assert first.root == tmp_path / scenario_hash(scenario) and len(first) == 2
    stamp = first.image_path(0).stat().st_mtime_ns
    again = cached_dataset(scenario, tmp_path, progress=False)
    assert again.image_path(0).stat().st_mtime_ns == stamp  # not rendered again
    assert [p.name for p in tmp_path.iterdir()] == [scenario_hash(scenario)]  # no partials


def test_a_damaged_prerendered_cache_is_one_clear_error(tmp_path: Path) -> None:
    spec = SourceSpec(kind="prerendered", path=str(tmp_path), seed=4, floor="rough")
    (tmp_path / scenario_hash(spec.scenario())).mkdir()  # an empty, damaged entry
    with pytest.raises(ConfigError, match=r"unreadable .*delete it"):
        open_frame_source(spec)


@pytest.mark.parametrize(
    ("source", "frames", "late", "expected"),
    [
        ("sim", 124, 129, "it kept 49 % of its frames (below 90 %):\n              rendering live"),
        (
            "prerendered",
            500,
            100,
            "it kept 83 % of its frames (below 90 %):\n              the machine",
        ),
        ("prerendered", 593, 28, None),
        # 89.5 %: below 90 %, and never printed as 90 % beside "(below 90 %)".
        ("prerendered", 564, 66, "it kept 89 % of its frames (below 90 %)"),
    ],
)
def test_summary_says_why_when_the_camera_did_not_keep_its_rate(
    capsys: pytest.CaptureFixture[str], source: str, frames: int, late: int, expected: str | None
) -> None:
    counts = Status().counts()
    counts.update(frames=frames, late=late)
    print_summary(
        {
            **counts,
            "duration_s": 20.3,
            "source": source,
            "floor": "rough",
            "policy": "paper",
            "markers": {},
            "recognitions_filtered": 0,
            "recognitions_uncontrolled": 0,
        }
    )
    out = capsys.readouterr().out
    if expected is None:
        assert "it kept" not in out, out
    else:
        assert expected in out, out


DEMO = [sys.executable, "-m", "services.cli", "demo"]


def _live_demo(port: int, duration_s: int) -> subprocess.CompletedProcess[str]:
    """``framegate demo --source sim`` on its own rendezvous port, run to its end."""
    env = child_env()
    env["FRAMEGATE_LOCAL_PORT"] = str(port)
    return subprocess.run(
        [*DEMO, "--source", "sim", "--duration", str(duration_s)],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=scaled(120),
        check=False,
    )


@pytest.mark.integration
def test_a_short_live_demo_prints_status_lines_and_the_side_by_side_summary() -> None:
    result = _live_demo(free_port(), 8)
    assert result.returncode == 0 and "Traceback" not in result.stderr, result
    lines = result.stdout.splitlines()
    status = [line for line in lines if " late | med " in line]
    assert status and all(len(line) <= STATUS_COLUMNS for line in status), result.stdout
    assert "(sim camera, rough floor, policy paper)" in result.stdout
    table = lines[next(i for i, line in enumerate(lines) if line.split()[:1] == ["recognitions"]) :]
    assert table[0].split() == ["recognitions", "filtered", "uncontrolled", "gain"], table
    assert table[-1].split()[0] == "total", table


@pytest.mark.integration
def test_a_demo_beside_a_live_pipeline_on_its_rendezvous_refuses_in_one_line() -> None:
    port = free_port()
    with Node("camera", NetworkConfig(local_port=port)) as other:  # another pipeline's camera
        other.offer("images", kind="frame")
        result = _live_demo(port, 5)
    assert result.returncode == 1, result
    assert result.stderr.startswith("error: service 'camera' is live already (pid "), result
    assert len(result.stderr.splitlines()) == 1
    # The advice names another rendezvous than the one in use (it named 7447 + 1 always).
    assert f"(FRAMEGATE_LOCAL_PORT={port + 1} framegate demo)" in result.stderr, result
    assert " late | med " not in result.stdout  # it read no other pipeline's numbers


@pytest.mark.integration
def test_demo_json_prints_only_the_summary_on_stdout() -> None:
    env = child_env()
    env["FRAMEGATE_LOCAL_PORT"] = str(free_port())
    result = subprocess.run(
        [sys.executable, "-m", "services.cli", "demo", "--source", "sim", "--duration", "5",
         "--json"],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=scaled(120), check=False,
    )  # fmt: skip
    assert result.returncode == 0, result
    summary = json.loads(result.stdout)  # no status line mixed in
    assert summary["source"] == "sim" and "gain_pct" in summary and "markers" in summary
    assert " late | med " in result.stderr  # the status lines went to stderr


def _child(parent: psutil.Process, *argv: str) -> psutil.Process | None:
    """The descendant of ``parent`` whose command line holds ``argv`` in a row, if any."""
    for child in parent.children(recursive=True):
        try:
            cmdline = child.cmdline()
        except psutil.Error:
            continue
        if any(cmdline[i : i + len(argv)] == list(argv) for i in range(len(cmdline))):
            return child
    return None


@pytest.mark.integration
def test_demo_names_a_child_that_died_by_a_signal_and_exits_1() -> None:
    env = child_env()
    env["FRAMEGATE_LOCAL_PORT"] = str(free_port())
    demo = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "demo", "--source", "sim", "--duration", "3"],
        cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        parent = psutil.Process(demo.pid)
        detector = wait_until(
            lambda: _child(parent, "run", "detector", "--name", "detector"), 60, "the detector"
        )
        detector.rlimit(psutil.RLIMIT_CORE, (0, 0))  # an abort, without a core file
        detector.send_signal(signal.SIGABRT)
        _out, err = demo.communicate(timeout=scaled(60))
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.communicate()
    assert demo.returncode == 1, (demo.returncode, err)
    errors = [line for line in err.splitlines() if line.startswith("error: ")]
    assert errors == ["error: detector died by signal SIGABRT (6)"], err


@pytest.mark.integration
def test_a_demo_told_to_connect_where_nothing_listens_says_so_in_one_line() -> None:
    # FRAMEGATE_CONNECT left set for a robot (or a --connect) replaces the rendezvous: the
    # demo's services could never meet, and it ran its whole duration showing zeros, exit 0.
    env = child_env()
    env["FRAMEGATE_LOCAL_PORT"] = str(free_port())
    env["FRAMEGATE_CONNECT"] = f"tcp/127.0.0.1:{free_port()}"
    result = subprocess.run(
        [*DEMO, "--source", "sim", "--duration", "5"],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=scaled(60), check=False,
    )  # fmt: skip
    assert result.returncode == 1, result
    assert result.stderr.startswith(f"error: cannot reach {env['FRAMEGATE_CONNECT']} ("), result
    assert len(result.stderr.splitlines()) == 1, result.stderr
    assert " late | med " not in result.stdout  # nothing was started
