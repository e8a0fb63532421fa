"""The dataset on disk: deterministic, complete, and read back as written."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from middleware import validate_metadata
from services.lib.sim import (
    DatasetError,
    FrameInfo,
    Scenario,
    ScenarioConfig,
    read_dataset,
    simulate,
)

SmallConfig = Callable[..., ScenarioConfig]


def _hashes(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def test_same_seed_writes_byte_identical_datasets(
    tmp_path: Path, small_config: SmallConfig
) -> None:
    config = small_config(seed=11)
    simulate(config, tmp_path / "a", progress=False, workers=1)
    simulate(config, tmp_path / "b", progress=False, workers=2)
    a, b = _hashes(tmp_path / "a"), _hashes(tmp_path / "b")
    assert len(a) == 4 + 5  # four frames, five files
    assert a == b


def test_different_seeds_write_different_datasets(
    tmp_path: Path, small_config: SmallConfig
) -> None:
    simulate(small_config(seed=1), tmp_path / "a", progress=False)
    simulate(small_config(seed=2), tmp_path / "b", progress=False)
    a, b = _hashes(tmp_path / "a"), _hashes(tmp_path / "b")
    for name in ("gyro.csv", "truth.json", "scenario.json", "frames/000000.png"):
        assert a[name] != b[name], name


def test_dataset_round_trips_through_the_reader(tmp_path: Path, small_config: SmallConfig) -> None:
    config = small_config(seed=5)
    simulate(config, tmp_path, progress=False)
    dataset = read_dataset(tmp_path)
    scenario = Scenario(config)

    validate_metadata((tmp_path / "camera.xml").read_bytes(), kind="camera")
    assert dataset.camera == scenario.camera
    assert dataset.scenario == config
    assert dataset.frames == tuple(scenario.frame_info(i) for i in range(4))
    assert dataset.frames[1] == FrameInfo(1, 566_666_667, 60_000_000)
    assert len(dataset) == 4
    for index in range(4):
        assert np.array_equal(dataset.image(index), scenario.render(index))
    gyro = scenario.gyro_samples()
    assert dataset.gyro.t_ns.dtype == np.int64
    assert np.array_equal(dataset.gyro.t_ns, gyro.t_ns)
    assert np.array_equal(dataset.gyro.rate_rad_s, gyro.rate_rad_s)  # exact, not approx
    assert dataset.truth == tuple(scenario.truth(i) for i in range(4))


def test_reader_reads_a_recording_without_truth(tmp_path: Path, small_config: SmallConfig) -> None:
    simulate(small_config(), tmp_path, progress=False)
    (tmp_path / "truth.json").unlink()
    (tmp_path / "scenario.json").unlink()
    dataset = read_dataset(tmp_path)
    assert dataset.truth is None and dataset.scenario is None
    assert dataset.image(3).shape == (192, 256)


def test_reader_names_the_missing_file(tmp_path: Path, small_config: SmallConfig) -> None:
    simulate(small_config(), tmp_path, progress=False)
    (tmp_path / "gyro.csv").unlink()
    with pytest.raises(DatasetError, match=r"no gyro\.csv"):
        read_dataset(tmp_path)


def _short_row(root: Path) -> None:
    lines = (root / "frames.csv").read_text().splitlines()
    lines[2] = lines[2].rsplit(",", 1)[0]
    (root / "frames.csv").write_text("\n".join(lines) + "\n")


def _latin1(root: Path) -> None:
    (root / "frames.csv").write_bytes((root / "frames.csv").read_bytes() + b"9,\xe9,1,x\n")


def _short_truth(root: Path) -> None:
    truth = json.loads((root / "truth.json").read_text())
    truth["frames"] = truth["frames"][:-1]
    (root / "truth.json").write_text(json.dumps(truth))


@pytest.mark.parametrize(
    ("damage", "match"),
    [
        (_short_row, r"frames\.csv:3: needs the 4 columns"),
        (_latin1, r"frames\.csv:\d+: not UTF-8 CSV"),
        (_short_truth, r"truth\.json: \d+ frames, but frames\.csv lists"),
        (lambda root: (root / "scenario.json").write_text("[1]"), "not a JSON object"),
    ],
    ids=["short row", "latin-1", "truth shorter", "scenario a list"],
)
def test_a_damaged_dataset_is_one_dataset_error(
    tmp_path: Path, small_config: SmallConfig, damage: Any, match: str
) -> None:
    simulate(small_config(), tmp_path, progress=False)
    damage(tmp_path)
    with pytest.raises(DatasetError, match=match):
        read_dataset(tmp_path)


def test_writer_refuses_to_clobber_without_overwrite(
    tmp_path: Path, small_config: SmallConfig
) -> None:
    simulate(small_config(frame_count=2), tmp_path, progress=False)
    with pytest.raises(DatasetError, match="already holds a dataset"):
        simulate(small_config(frame_count=2), tmp_path, progress=False)
    simulate(small_config(frame_count=1), tmp_path, progress=False, overwrite=True)
    assert len(read_dataset(tmp_path)) == 1
    assert not (tmp_path / "frames" / "000001.png").exists()
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(DatasetError, match=r"notes\.txt"):
        simulate(small_config(), tmp_path, progress=False, overwrite=True)


def test_an_interrupted_simulation_leaves_no_half_dataset(
    tmp_path: Path, small_config: SmallConfig, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A Ctrl-C while frames are written: the directory it made is gone, one that existed
    (empty) stays, empty; a rerun needs no --force."""
    from services.lib.sim import _simulate

    calls = {"n": 0}
    real = _simulate._write_next

    def interrupted(*args: object, **kwargs: object) -> None:
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        real(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(_simulate, "_write_next", interrupted)
    fresh = tmp_path / "new"
    with pytest.raises(KeyboardInterrupt):
        simulate(small_config(frame_count=4), fresh, progress=False, workers=1)
    assert not fresh.exists()
    mine = tmp_path / "mine"
    mine.mkdir()
    calls["n"] = 0
    with pytest.raises(KeyboardInterrupt):
        simulate(small_config(frame_count=4), mine, progress=False, workers=1)
    assert mine.is_dir() and not list(mine.iterdir())
    monkeypatch.setattr(_simulate, "_write_next", real)
    simulate(small_config(frame_count=1), fresh, progress=False)
    assert len(read_dataset(fresh)) == 1


def test_the_render_bar_writes_nothing_into_a_log(
    tmp_path: Path, small_config: SmallConfig, capfd: pytest.CaptureFixture[str]
) -> None:
    # A demo or launch redirected to a file got hundreds of \r updates of the render bar.
    simulate(small_config(frame_count=3), tmp_path, progress=True)
    assert "\r" not in capfd.readouterr().err
