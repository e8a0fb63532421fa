"""Five Ctrl-C and five SIGTERM stops of ``launch`` reach its camera mid-render: each ends
with exit 0 and the camera's own totals (see test_clean_exit.py for the abort this guards
against: its twenty cameras are signalled directly, the race with the render itself; these
add the supervisor's path). A file of its own: ten launches one after another are the
longest test of tests/services/nodes, and the suite's workers share files (``--dist
loadfile``).
"""

from __future__ import annotations

import signal
import time
from pathlib import Path

import pytest

from tests.conftest import wait_until
from tests.helpers.timing import scaled
from tests.services.nodes.pipeline import Pipeline

# Stops that must reach a camera while it renders.
pytestmark = [pytest.mark.integration, pytest.mark.usefixtures("live_render")]


_CAMERA_ONLY = """\
version: 1
services:
  camera:
    args: {source: sim, seed: 1, loop: true}
"""


# launch's own line when a child did not stop within its grace after SIGTERM (a starved
# machine): that child's totals are missing, and its stop proved nothing.
_KILLED = "after SIGTERM: killed"
# Stops of that kind made again, at most: more means the camera rarely stops in time.
_KILLED_MAX = 10
# Stops counted (alternately SIGINT and SIGTERM): twenty took 75-115 s of a 2-core suite
# that is CPU-bound; the direct test signals twenty cameras.
STOPS = 10


def _ending(lines: list[str]) -> str | None:
    """How the camera under ``launch`` ended, once its last lines are out."""
    if any("frames stored" in line for line in lines):
        return "totals"
    if any(_KILLED in line for line in lines):
        return "killed"
    return None


@pytest.mark.slow
def test_ten_signals_stop_launches_of_a_rendering_camera_with_exit_0(tmp_path: Path) -> None:
    """Under ``launch`` the supervisor's SIGTERM reaches the camera mid-render: 5 Ctrl-C and
    5 SIGTERM stops of ``launch``, one after another (a process holding Nodes on several
    rendezvous ports would announce them all and join the rendezvous together)."""
    stops: list[float] = []
    killed = 0
    while len(stops) < STOPS:
        i = len(stops) + killed
        signum = (signal.SIGINT, signal.SIGTERM)[len(stops) % 2]
        (tmp_path / str(i)).mkdir()
        pipe = Pipeline(tmp_path / str(i), _CAMERA_ONLY)
        try:
            wait_until(lambda p=pipe: p.counter("camera/images") > 0, 90, "a stored frame")
            sent = time.monotonic()
            pipe.proc.send_signal(signum)
            code = pipe.proc.wait(timeout=scaled(20))
            took = time.monotonic() - sent
            # The camera ended its run itself: its totals are its last line. On a starved
            # machine it may miss launch's grace and be killed (launch says so): made again.
            try:
                ending = wait_until(lambda p=pipe: _ending(p.lines), 20, "the camera's end")
            except AssertionError:
                raise AssertionError(f"stop {i}: no camera totals\n{pipe.log()}") from None
            log = pipe.log()
            assert code == 0, f"stop {i} by {signum!r}: launch exited {code}\n{log}"
            assert "terminate called" not in log and "SIGABRT" not in log, log
            assert "died by signal" not in log and "error" not in log, log
            if ending == "killed":
                killed += 1
                assert killed <= _KILLED_MAX, f"the camera was killed in {killed} stops\n{log}"
            else:
                stops.append(took)
        finally:
            pipe.close()
    # As above: the bound catches a hang, not a slow machine.
    assert max(stops) < scaled(20), f"slowest launch stop took {max(stops):.1f} s"
