"""Soak: the whole pipeline at full speed for minutes, watching memory and lost elements.

Camera and gyro (simulator), mediator and a detector with no emulated load (it takes the
next frame as soon as it is done) run as separate processes on a private loopback
rendezvous port, started like ``framegate demo``. The simulated camera produces as fast as
it can render (frames it is too late for are skipped, as a real camera would); ``rate``
speeds up the scenario clock of camera and gyro.

Measured:
- resident memory (RSS) of every service process every ``sample_s``; growth after the
  warm-up, from the mean of the first three samples to the mean of the last three
  (goal: <= 5 %);
- accepted elements lost (goal: 0), audited every ``check_s`` while everything runs:
  every camera frame older than the newest decision (or than 30 s) has a decision;
  every frame the
  mediator accepted that is still within mediator/images' retention is there and
  byte-identical (payload and metadata) to the camera's copy; nothing is in
  mediator/images that the mediator did not accept; every accepted frame older than the
  newest detection has a detection; decisions and detections stored are all queryable;
- refusals and drops, from the producers' own counters (``info``, never the logs):
  camera/images and gyro/rates refused by flow control, frames the camera skipped late,
  subscriptions refused, the mediator's decisions by reason;
- stalls (goal: none): a stage whose input keeps coming while its output stands still for
  30 s; the timeline of counters and queue fills and the services' logs go into the report.
"""

from __future__ import annotations

from ._audit import EXCUSED_REASONS, Audit
from ._report import format_report
from ._run import MemorySeries, SoakConfig, find_stalls, rss_bytes, run_soak, soak_deployment

__all__ = [
    "EXCUSED_REASONS",
    "Audit",
    "MemorySeries",
    "SoakConfig",
    "find_stalls",
    "format_report",
    "rss_bytes",
    "run_soak",
    "soak_deployment",
]
