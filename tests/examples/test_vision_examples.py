"""The vision examples run as a user runs them: the handler alone, its deploy file, and the
cheap-vs-expensive measurement against real processes."""

from __future__ import annotations

import signal
import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import REPO, child_env, start_python
from tests.helpers.timing import scaled


def _run(*argv: str, timeout_s: float) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, *argv],
        capture_output=True,
        text=True,
        cwd=REPO,
        env=child_env(),
        timeout=scaled(timeout_s),
    )


def test_the_template_example_finds_its_marker_and_says_what_it_costs() -> None:
    result = _run("examples/vision_template.py", "--frames", "2", timeout_s=120)
    assert result.returncode == 0, result
    assert "ms per frame" in result.stdout and "found marker 0" in result.stdout, result


def test_the_vision_deploy_file_checks() -> None:
    result = _run("-m", "services.cli", "launch", "examples/vision.yaml", "--check", timeout_s=120)
    assert result.returncode == 0, result
    assert "examples.vision_template:find_marker" in result.stdout, result


@pytest.mark.integration
@pytest.mark.slow
def test_the_compare_example_measures_both_handlers_from_one_camera() -> None:
    result = _run("examples/vision_compare.py", "--seconds", "4", "--warmup-s", "1", timeout_s=300)
    assert result.returncode == 0, result
    lines = result.stdout.splitlines()
    header = next(i for i, line in enumerate(lines) if line.startswith("handler"))
    rows = {line.split()[0]: line.split()[1:] for line in lines[header + 1 :]}
    assert sorted(rows) == ["cheap", "expensive"], result.stdout
    for values in rows.values():
        assert len(values) == 5 and values[-1].endswith("%"), result.stdout


@pytest.mark.integration
@pytest.mark.parametrize(
    ("argv", "started"),
    [
        (["examples/vision_template.py", "--frames", "1000000"], "timing find_marker"),
        (["examples/vision_compare.py", "--seconds", "3600"], "started the pipeline"),
    ],
)
def test_a_vision_example_stops_on_ctrl_c_with_exit_0_and_no_traceback(
    argv: list[str], started: str
) -> None:
    """As offer.py, query.py and subscribe.py do (these printed a KeyboardInterrupt
    traceback and exited -2)."""
    proc = start_python(argv)
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()  # it is inside main(): Ctrl-C there is the case
        assert started in first, first
        proc.send_signal(signal.SIGINT)
        _out, err = proc.communicate(timeout=scaled(60))
        assert proc.returncode == 0, err
        assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["examples/vision_template.py", "--frames", "0"], "argument --frames: must be an integer >= 1"),  # noqa: E501
        (["examples/vision_compare.py", "--seconds", "0"], "argument --seconds: must be a number of seconds > 0"),  # noqa: E501
        (["examples/vision_compare.py", "--seconds", "-5"], "argument --seconds: must be a number of seconds > 0"),  # noqa: E501
        (["examples/vision_compare.py", "--warmup-s", "nan"], "argument --warmup-s: must be a number of seconds >= 0"),  # noqa: E501
    ],
)  # fmt: skip
def test_a_vision_example_refuses_a_flag_value_it_cannot_use_as_parsed(
    argv: list[str], expected: str
) -> None:
    # --frames 0 divided by zero; --seconds -5 started the whole pipeline, then raised in
    # time.sleep; --seconds 0 printed rates divided by a few microseconds.
    result = _run(*argv, timeout_s=60)
    assert result.returncode == 2, result  # argparse's own usage error
    assert "Traceback" not in result.stderr and expected in result.stderr, result
    assert "started the pipeline" not in result.stdout, result


def test_the_template_example_finds_its_marker_in_a_bgra8_frame() -> None:
    from examples.vision_template import TEMPLATES, find_marker
    from services.lib.quality import Exposure
    from services.lib.vision import FrameMeta

    side, template = TEMPLATES[2]
    gray = np.full((240, 320), 170, np.uint8)
    gray[50 : 50 + side, 80 : 80 + side] = template
    bgra = np.dstack([gray, gray, gray, np.zeros_like(gray)])
    [box] = find_marker(bgra, FrameMeta(0, 0, Exposure(0, 1), "bgra8", 320, 240, None))
    assert box.label == 0 and box.corners_px[0][0] == pytest.approx(80 + side / 8, abs=1)
