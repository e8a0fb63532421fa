"""The dataset layout on disk (see DATASET.md): a writer and a lazy reader.

Nothing here is specific to the simulator except the optional ``scenario.json`` and
``truth.json``; a recording from a real robot uses the same files without them.
"""

from __future__ import annotations

import contextlib
import csv
import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2
import numpy as np

from middleware import FramegateError, SchemaError
from services.lib.camera_model import CameraModel

from ._config import ScenarioConfig
from ._records import FrameInfo, FrameTruth, GyroTrace

CAMERA_FILE = "camera.xml"
FRAMES_FILE = "frames.csv"
FRAMES_DIR = "frames"
GYRO_FILE = "gyro.csv"
SCENARIO_FILE = "scenario.json"
TRUTH_FILE = "truth.json"
REPORT_FILE = "report.json"

_FRAME_COLUMNS = ["frame_id", "exposure_start_ns", "exposure_ns", "file"]
_GYRO_COLUMNS = ["t_ns", "x_rad_s", "y_rad_s", "z_rad_s"]
# Huffman-only deflate: noisy camera images gain nothing from LZ matching, and it is twice
# as fast as the default while the files come out smaller.
_PNG_PARAMS = [
    cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY,
]  # fmt: skip
_OUR_FILES = (CAMERA_FILE, FRAMES_FILE, GYRO_FILE, SCENARIO_FILE, TRUTH_FILE, REPORT_FILE)


class DatasetError(FramegateError):
    """A dataset directory is missing a file, or a file is malformed."""


@dataclass(frozen=True, slots=True)
class Dataset:
    """A dataset read from disk; images load lazily by index (``dataset.image(i)``).

    ``truth`` and ``scenario`` are None for a recording that has none.
    """

    root: Path
    camera: CameraModel
    frames: tuple[FrameInfo, ...]
    frame_files: tuple[str, ...]
    gyro: GyroTrace
    truth: tuple[FrameTruth, ...] | None
    scenario: ScenarioConfig | None

    def __len__(self) -> int:
        return len(self.frames)

    def image_path(self, index: int) -> Path:
        """Path of the index-th frame's image."""
        return self.root / self.frame_files[index]

    def image(self, index: int) -> np.ndarray:
        """The index-th frame as a mono8 array (height x width)."""
        path = self.image_path(index)
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise DatasetError(f"cannot read frame image {path}")
        expected = (self.camera.height_px, self.camera.width_px)
        if image.dtype != np.uint8 or image.shape != expected:
            raise DatasetError(
                f"{path} is {image.dtype} {image.shape}, expected mono8 {expected} from camera.xml"
            )
        return np.asarray(image)


def read_dataset(root: str | Path) -> Dataset:
    """Read a dataset directory: camera.xml, frames.csv, gyro.csv, and if present
    truth.json and scenario.json."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"no dataset directory at {root}")
    try:
        camera = CameraModel.from_xml(_need(root, CAMERA_FILE).read_bytes())
    except (SchemaError, ValueError) as exc:
        raise DatasetError(f"{root / CAMERA_FILE}: {exc}") from exc
    frames, files = _read_frames(_need(root, FRAMES_FILE))
    gyro = _read_gyro(_need(root, GYRO_FILE))
    truth = None
    if (root / TRUTH_FILE).is_file():
        data = _read_json(root / TRUTH_FILE)
        try:
            truth = tuple(FrameTruth.from_dict(item) for item in data["frames"])
        except (KeyError, TypeError, ValueError) as exc:
            raise DatasetError(f"{root / TRUTH_FILE}: malformed truth ({exc!r})") from exc
        if len(truth) != len(frames):
            raise DatasetError(
                f"{root / TRUTH_FILE}: {len(truth)} frames, but {FRAMES_FILE} lists {len(frames)}"
            )
    scenario = None
    if (root / SCENARIO_FILE).is_file():
        data = _read_json(root / SCENARIO_FILE)
        if not isinstance(data, dict):
            raise DatasetError(f"{root / SCENARIO_FILE}: not a JSON object of parameters")
        try:
            scenario = ScenarioConfig.from_dict(data)
        except (TypeError, ValueError) as exc:
            raise DatasetError(f"{root / SCENARIO_FILE}: {exc}") from exc
    return Dataset(root, camera, frames, files, gyro, truth, scenario)


# Shipped beside this module (package data), so the path is right in any installation.
LAYOUT_DOC = Path(__file__).with_name("DATASET.md")


def _need(root: Path, name: str) -> Path:
    path = root / name
    if not path.is_file():
        raise DatasetError(
            f"dataset {root} has no {name}: not a dataset as `framegate simulate` writes it; "
            f"the layout is in {LAYOUT_DOC}"
        )
    return path


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path}: not readable JSON ({exc})") from exc


def _read_frames(path: Path) -> tuple[tuple[FrameInfo, ...], tuple[str, ...]]:
    frames, files = [], []
    line = 1
    try:
        with path.open(newline="", encoding="utf-8") as handle:
            reader = csv.DictReader(handle)
            if reader.fieldnames != _FRAME_COLUMNS:
                raise DatasetError(f"{path}: header must be {','.join(_FRAME_COLUMNS)}")
            for line, row in enumerate(reader, start=2):
                try:
                    frames.append(
                        FrameInfo(
                            int(row["frame_id"]),
                            int(row["exposure_start_ns"]),
                            int(row["exposure_ns"]),
                        )
                    )
                except (TypeError, ValueError) as exc:
                    raise DatasetError(f"{path}:{line}: {exc}") from exc
                if not row["file"] or None in row:  # a short row, or one with extra fields
                    raise DatasetError(f"{path}:{line}: needs the {len(_FRAME_COLUMNS)} columns")
                files.append(row["file"])
    except (UnicodeDecodeError, csv.Error) as exc:
        raise DatasetError(f"{path}:{line + 1}: not UTF-8 CSV ({exc})") from exc
    return tuple(frames), tuple(files)


def _read_gyro(path: Path) -> GyroTrace:
    with path.open(encoding="utf-8") as handle:
        header = handle.readline().strip().split(",")
    if header != _GYRO_COLUMNS:
        raise DatasetError(f"{path}: header must be {','.join(_GYRO_COLUMNS)}")
    try:
        # Timestamps parsed as integers: Unix-epoch ns do not fit a float exactly.
        t_ns = np.loadtxt(path, delimiter=",", skiprows=1, usecols=0, dtype=np.int64, ndmin=1)
        rate = np.loadtxt(path, delimiter=",", skiprows=1, usecols=(1, 2, 3), ndmin=2)
        return GyroTrace(t_ns, rate)
    except ValueError as exc:
        raise DatasetError(f"{path}: {exc}") from exc


class DatasetWriter:
    """Writes a dataset directory; use as a context manager.

    Frames go to disk as they are added; ``frames.csv`` and ``truth.json`` are written on
    close. ``overwrite`` clears a previous dataset in the directory; other files there are
    refused rather than deleted. Left by an exception (a Ctrl-C included), it removes what
    it wrote: a half-written directory would be neither a dataset nor empty.
    """

    def __init__(
        self, root: str | Path, camera: CameraModel, *, exposure_ns: int | None = None,
        frame_period_ns: int | None = None, scenario: ScenarioConfig | None = None,
        overwrite: bool = False,
    ) -> None:  # fmt: skip
        self.root = Path(root)
        self._created = not self.root.exists()
        _prepare(self.root, overwrite)
        (self.root / FRAMES_DIR).mkdir()
        xml = camera.to_xml(0, exposure_ns=exposure_ns, frame_period_ns=frame_period_ns)
        (self.root / CAMERA_FILE).write_bytes(xml + b"\n")
        if scenario is not None:
            _write_json(self.root / SCENARIO_FILE, scenario.to_dict())
        self._camera = camera
        self._frames: list[tuple[FrameInfo, str]] = []
        self._truth: list[FrameTruth] = []
        self._extra_truth: dict[str, Any] = {}

    def add_frame(self, info: FrameInfo, image: np.ndarray) -> None:
        """Write one frame's image (mono8, the camera's size) as a lossless PNG."""
        expected = (self._camera.height_px, self._camera.width_px)
        if image.dtype != np.uint8 or image.shape != expected:
            raise DatasetError(f"frame {info.frame_id} is {image.dtype} {image.shape}, "
                               f"expected mono8 {expected}")  # fmt: skip
        name = f"{FRAMES_DIR}/{info.frame_id:06d}.png"
        if not cv2.imwrite(str(self.root / name), image, _PNG_PARAMS):
            raise DatasetError(f"could not write {self.root / name}")
        self._frames.append((info, name))

    def add_truth(self, truth: FrameTruth) -> None:
        """Record one frame's ground truth (written to truth.json on close)."""
        self._truth.append(truth)

    def set_truth_extra(self, **fields: Any) -> None:
        """Scenario-wide truth for truth.json next to the frames (e.g. the bumps)."""
        self._extra_truth.update(fields)

    def write_gyro(self, gyro: GyroTrace) -> None:
        """Write the gyro stream (gyro clock, gyro frame) as gyro.csv."""
        with (self.root / GYRO_FILE).open("w", encoding="utf-8", newline="\n") as handle:
            handle.write(",".join(_GYRO_COLUMNS) + "\n")
            # %.17g round-trips a float64 exactly.
            for t, (x, y, z) in zip(gyro.t_ns.tolist(), gyro.rate_rad_s.tolist(), strict=True):
                handle.write(f"{t},{x:.17g},{y:.17g},{z:.17g}\n")

    def close(self) -> None:
        """Write frames.csv (and truth.json if any truth was added)."""
        with (self.root / FRAMES_FILE).open("w", encoding="utf-8", newline="") as handle:
            writer = csv.writer(handle, lineterminator="\n")
            writer.writerow(_FRAME_COLUMNS)
            for info, name in self._frames:
                writer.writerow([info.frame_id, info.exposure_start_ns, info.exposure_ns, name])
        if self._truth:
            frames = [t.to_dict() for t in self._truth]
            _write_json(self.root / TRUTH_FILE, {**self._extra_truth, "frames": frames})

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:  # fmt: skip
        if exc_type is None:
            self.close()
        else:
            self.discard()

    def discard(self) -> None:
        """Remove what this writer wrote (and the directory, if it made it)."""
        for name in (*_OUR_FILES, FRAMES_DIR):
            path = self.root / name
            if path.is_dir():
                shutil.rmtree(path, ignore_errors=True)
            elif path.exists():
                path.unlink(missing_ok=True)
        if self._created:
            with contextlib.suppress(OSError):  # not empty: someone else's files stay
                self.root.rmdir()


def write_report(root: str | Path, report: dict[str, Any]) -> Path:
    """Write report.json into a dataset directory."""
    path = Path(root) / REPORT_FILE
    _write_json(path, report)
    return path


def _write_json(path: Path, data: Any) -> None:
    path.write_text(json.dumps(data, indent=1, sort_keys=False) + "\n", encoding="utf-8")


def _prepare(root: Path, overwrite: bool) -> None:
    if root.exists() and not root.is_dir():
        raise DatasetError(f"{root} exists and is not a directory")
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # a parent that is a file, a read-only or missing mount
        raise DatasetError(f"cannot create dataset directory {root}: {exc.strerror}") from exc
    present = {p.name for p in root.iterdir()}
    ours = present & {*_OUR_FILES, FRAMES_DIR}
    others = present - ours
    if ours and not overwrite:
        raise DatasetError(
            f"{root} already holds a dataset; replace it with --force (from Python: overwrite=True)"
        )
    if others:
        raise DatasetError(
            f"{root} holds files that are not part of a dataset ({', '.join(sorted(others)[:3])}); "
            "choose an empty or new directory"
        )
    for name in ours:
        path = root / name
        if path.is_dir():
            shutil.rmtree(path)
        else:
            path.unlink()
