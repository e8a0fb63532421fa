"""What the replay needs of each frame, computed offline from a rendered dataset.

For every frame: when it reaches the mediator (its exposure end, camera clock), the quality
the mediator would give it (the same ``frame_quality`` on the same gyro samples, q =
exp(-blur/b0)), and which markers the detector would recognize in it if it processed it (the
``all`` run's answer: ``detect_markers`` on the frame, scored against the truth as
``recognized_frames`` does). Detection costs tens of ms a frame, so its result is cached
beside the dataset (``<hash>.detections.json``); quality is cheap and depends on b0, so it is
recomputed.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

from services.lib.markers import detect_markers
from services.lib.quality import (
    CoverageError,
    Exposure,
    GyroSamples,
    QualityInputError,
    frame_quality,
)
from services.lib.sim import Dataset

from ._config import MARKER_NAMES, ExperimentError
from ._metrics import recognized_frames
from ._records import FrameDetections

_DETECTIONS_SUFFIX = ".detections.json"


@dataclass(frozen=True, slots=True)
class FrameOutcome:
    """One frame as the replay sees it.

    ``arrival_ns``: exposure end on the camera clock (when the camera can put it).
    ``quality``: the mediator's q, None when the gyro does not cover the exposure.
    ``recognized``: the markers the detector recognizes in it, were it processed.
    """

    frame_id: int
    arrival_ns: int
    blur_px: float | None
    quality: float | None
    recognized: frozenset[str]

    def value(self, marker: str | None = None) -> int:
        """Recognitions this frame is worth: of one marker (0/1) or of all (None)."""
        if marker is None:
            return len(self.recognized)
        return int(marker in self.recognized)


def frame_detections(dataset: Dataset) -> list[FrameDetections]:
    """``detect_markers`` on every frame, cached beside the dataset directory."""
    path = detections_path(dataset.root)
    if path.is_file():
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
            found = [
                FrameDetections(
                    int(d["frame_id"]),
                    int(d["processing_ns"]),
                    tuple((int(m[0]), float(m[1]), float(m[2])) for m in d["markers"]),
                )
                for d in data
            ]
        except (OSError, ValueError, KeyError, TypeError, IndexError) as exc:
            raise ExperimentError(f"{path} is unreadable ({exc!r}); delete it") from exc
        if len(found) == len(dataset):
            return found
    found = []
    for index in range(len(dataset)):
        markers = detect_markers(dataset.image(index))
        found.append(
            FrameDetections(
                frame_id=dataset.frames[index].frame_id,
                processing_ns=0,
                markers=tuple(
                    (
                        m.marker_id,
                        sum(c[0] for c in m.corners_px) / len(m.corners_px),
                        sum(c[1] for c in m.corners_px) / len(m.corners_px),
                    )
                    for m in markers
                ),
            )
        )
    partial = path.with_suffix(".partial")
    partial.write_text(json.dumps([asdict(d) for d in found]), encoding="utf-8")
    partial.rename(path)
    return found


def frame_outcomes(dataset: Dataset, b0_px: float) -> tuple[FrameOutcome, ...]:
    """Arrival, quality and recognizable markers of every frame of ``dataset``."""
    if dataset.truth is None:
        raise ExperimentError(f"dataset {dataset.root} has no truth; render it with the simulator")
    recognized = recognized_frames(frame_detections(dataset), dataset.truth)
    by_frame: dict[int, set[str]] = {}
    for name in MARKER_NAMES:
        for frame_id in recognized[name]:
            by_frame.setdefault(frame_id, set()).add(name)
    gyro = GyroSamples(dataset.gyro.t_ns, dataset.gyro.rate_rad_s)
    out = []
    for frame in dataset.frames:
        exposure = Exposure(frame.exposure_start_ns, frame.exposure_ns)
        blur: float | None
        q: float | None
        try:  # as the mediator scores it; one it cannot score has no quality
            blur, q = frame_quality(gyro, exposure, dataset.camera, b0_px)
        except (CoverageError, QualityInputError):
            blur, q = None, None
        out.append(
            FrameOutcome(
                frame_id=frame.frame_id,
                arrival_ns=frame.exposure_start_ns + frame.exposure_ns,
                blur_px=blur,
                quality=q,
                recognized=frozenset(by_frame.get(frame.frame_id, ())),
            )
        )
    return tuple(out)


def detections_path(dataset_root: Path) -> Path:
    """Where ``frame_detections`` caches a dataset's detections."""
    return dataset_root.parent / f"{dataset_root.name}{_DETECTIONS_SUFFIX}"
