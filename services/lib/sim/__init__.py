"""Bumpy-approach simulator: a robot drives at a marker board over a bumpy floor.

Camera frames, motion-blurred by the true camera motion, and gyro data that agree with each
other; ground truth per frame; and a dataset layout on disk that real recordings share
(``DATASET.md``). Live services use :class:`Scenario` directly; ``simulate`` writes a dataset
and ``read_dataset`` reads one back.
"""

from ._approaches import approach_cache_dir, cached_dataset, scenario_hash
from ._config import Bump, ScenarioConfig
from ._dataset import Dataset, DatasetError, DatasetWriter, read_dataset, write_report
from ._frame_cache import FrameCache
from ._records import FrameInfo, FrameTruth, GyroTrace, MarkerTruth
from ._report import BlurBin, MarkerReport, RecognitionReport, recognition_report
from ._scenario import Scenario
from ._simulate import RenderStopped, SimulationRun, simulate

__all__ = [
    "BlurBin",
    "Bump",
    "Dataset",
    "DatasetError",
    "DatasetWriter",
    "FrameCache",
    "FrameInfo",
    "FrameTruth",
    "GyroTrace",
    "MarkerReport",
    "MarkerTruth",
    "RecognitionReport",
    "RenderStopped",
    "Scenario",
    "ScenarioConfig",
    "SimulationRun",
    "approach_cache_dir",
    "cached_dataset",
    "read_dataset",
    "recognition_report",
    "scenario_hash",
    "simulate",
    "write_report",
]
