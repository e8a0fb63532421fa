"""The mediator's own defences, without a network: frames, gyro batches, blur, flags."""

from __future__ import annotations

import argparse
import math

import numpy as np
import pytest

from middleware import ConfigError
from services.lib.camera_model import CameraModel
from services.lib.messages import FrameMeta
from services.lib.quality import BlurOptions, Exposure, GyroSamples
from services.nodes._mediator_inputs import JOIN_BELOW, MAX_GYRO_SAMPLES
from services.nodes.mediator import (
    SERVICE,
    BadFrame,
    GyroCache,
    MediatorConfig,
    blur_quality,
    check_frame,
    merge_batch,
)

MS = 1_000_000


def _camera(**hostile: object) -> CameraModel:
    camera = CameraModel(width_px=64, height_px=48, fx_px=50.0, fy_px=50.0, cx_px=32.0, cy_px=24.0)
    # A camera model that did not check its numbers (an older peer, a future field): the
    # mediator must not rely on the model or the schema having refused them.
    for name, value in hostile.items():
        object.__setattr__(camera, name, value)
    return camera


def _meta(
    *, width: int = 4, height: int = 2, exposure_ns: int = 10 * MS, encoding: str = "mono8",
    camera: CameraModel | None = None,
) -> FrameMeta:  # fmt: skip
    return FrameMeta(20 * MS, 7, Exposure(20 * MS, exposure_ns), encoding, width, height, camera)


def _samples(rates: tuple[float, float, float] = (0.1, 0.2, 0.3)) -> GyroSamples:
    t = np.arange(0, 100 * MS, MS, dtype=np.int64)
    return GyroSamples(t, np.tile(np.asarray(rates), (t.size, 1)))


@pytest.mark.parametrize(
    ("meta", "payload_bytes", "reason"),
    [
        (_meta(width=0), 0, "bad-size"),
        (_meta(height=-2), 8, "bad-size"),
        (_meta(exposure_ns=0), 8, "bad-exposure"),
        # Schema-valid, absurd: a frame a hostile camera sent (never "gyro missing").
        (_meta(exposure_ns=2**63 - 1), 8, "bad-exposure"),
        (
            FrameMeta(20 * MS, 7, Exposure(2**63 - 1, 10 * MS), "mono8", 4, 2, None),
            8,
            "bad-exposure",
        ),
        (FrameMeta(2**62, 7, Exposure(0, 10 * MS), "mono8", 4, 2, None), 8, "bad-exposure"),
        (_meta(encoding=" mono8 "), 8, "bad-encoding"),
        (_meta(encoding="yuv422"), 8, "bad-encoding"),
        (_meta(), 7, "bad-payload-size"),
        (_meta(encoding="bgr8"), 8, "bad-payload-size"),
        (_meta(encoding="bgra8"), 24, "bad-payload-size"),
        (_meta(encoding="mono16"), 8, "bad-payload-size"),
    ],
)
def test_a_frame_no_detector_could_use_is_a_bad_frame(
    meta: FrameMeta, payload_bytes: int, reason: str
) -> None:
    with pytest.raises(BadFrame) as caught:
        check_frame(meta, payload_bytes)
    assert caught.value.reason == reason


@pytest.mark.parametrize(
    "absurd",
    [
        {"line_readout_ns": 2**63 - 1},
        {"line_readout_ns": 30 * MS},  # 48 rows x 30 ms: 1.4 s to read one frame
        {"gyro_time_offset_ns": 2**63 - 1},
        {"gyro_time_offset_ns": -(2**63)},
    ],
)
def test_a_camera_description_with_absurd_timing_is_refused(absurd: dict[str, int]) -> None:
    base = {"width_px": 64, "height_px": 48, "fx_px": 50.0, "fy_px": 50.0}
    with pytest.raises(ConfigError):
        CameraModel(**base, cx_px=32.0, cy_px=24.0, **absurd)  # type: ignore[arg-type]


def test_a_sound_frame_passes_the_checks() -> None:
    check_frame(_meta(), 8)
    check_frame(_meta(encoding="bgr8"), 24)
    check_frame(_meta(encoding="bgra8"), 32)
    check_frame(_meta(encoding="rgba8"), 32)
    check_frame(_meta(encoding="mono16"), 16)


def test_regression_inf_fx_px_is_a_bad_frame_not_a_crash() -> None:
    # Issue 15: fx_px="INF" made the blur NaN and quality() raise out of step().
    meta = _meta(camera=_camera(fx_px=math.inf))
    with pytest.raises(BadFrame, match="blur of nan px") as caught:
        blur_quality(meta, _samples(), BlurOptions(), 5.0)
    assert caught.value.reason == "bad-blur"


def test_regression_nan_gyro_to_camera_is_a_bad_frame_not_a_crash() -> None:
    rotation = (math.nan, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    meta = _meta(camera=_camera(gyro_to_camera=rotation))
    with pytest.raises(BadFrame) as caught:
        blur_quality(meta, _samples(), BlurOptions(), 5.0)
    assert caught.value.reason == "bad-blur"


def test_a_sane_camera_gives_a_quality_in_the_unit_interval() -> None:
    blur_px, q = blur_quality(_meta(camera=_camera()), _samples(), BlurOptions(), 5.0)
    assert blur_px > 0.0 and 0.0 < q < 1.0
    assert q == pytest.approx(math.exp(-blur_px / 5.0))


def _batch(first_ms: int, count: int) -> GyroSamples:
    t = (np.arange(count, dtype=np.int64) + first_ms) * MS
    return GyroSamples(t, np.zeros((count, 3)))


def _times_ms(batches: list[GyroSamples]) -> list[int]:
    return [int(t) // MS for b in batches for t in b.t_ns]


def test_gyro_batches_in_order_are_kept() -> None:
    kept, outcome = merge_batch([_batch(0, 3)], _batch(3, 2), keep_ns=10**12)
    assert outcome is None and _times_ms(kept) == [0, 1, 2, 3, 4]


def test_an_overlapping_gyro_batch_keeps_only_its_new_samples() -> None:
    kept, outcome = merge_batch([_batch(0, 3)], _batch(1, 4), keep_ns=10**12)
    assert outcome == "overlap" and _times_ms(kept) == [0, 1, 2, 3, 4]


def test_a_late_or_repeated_gyro_batch_changes_nothing() -> None:
    before = [_batch(0, 3), _batch(3, 3)]
    for late in (_batch(0, 3), _batch(1, 2)):
        kept, outcome = merge_batch(before, late, keep_ns=10**12)
        assert outcome == "late-batch" and kept == before


def test_a_restarted_gyro_starts_the_cache_over() -> None:
    kept, outcome = merge_batch([_batch(20_000, 3)], _batch(0, 2), keep_ns=10**12)
    assert outcome == "restart" and _times_ms(kept) == [0, 1]


def test_samples_packed_densely_are_bounded_in_number_not_only_in_time() -> None:
    """A peer offering gyro/rates packs samples 1 ns apart: all within the 10 s kept, so
    time alone would keep every one (3.4 GB measured); the count is bounded too."""
    dense = GyroSamples(
        np.arange(MAX_GYRO_SAMPLES + 10, dtype=np.int64), np.zeros((MAX_GYRO_SAMPLES + 10, 3))
    )
    kept, outcome = merge_batch([], dense, keep_ns=10**10)
    assert outcome == "too-many-samples" and sum(len(b) for b in kept) == MAX_GYRO_SAMPLES
    assert int(kept[-1].t_ns[-1]) == MAX_GYRO_SAMPLES + 9  # the newest stay
    batches: list[GyroSamples] = []
    for i in range(5):
        start = i * (MAX_GYRO_SAMPLES // 2)
        half = GyroSamples(
            np.arange(start, start + MAX_GYRO_SAMPLES // 2, dtype=np.int64),
            np.zeros((MAX_GYRO_SAMPLES // 2, 3)),
        )
        batches, outcome = merge_batch(batches, half, keep_ns=10**10)
    assert sum(len(b) for b in batches) <= MAX_GYRO_SAMPLES and outcome == "too-many-samples"


def test_old_gyro_batches_are_forgotten() -> None:
    kept, _ = merge_batch([_batch(0, 2), _batch(2, 2)], _batch(100, 2), keep_ns=50 * MS)
    assert _times_ms(kept) == [100, 101]


def test_every_mediator_setting_has_a_flag() -> None:
    parser = argparse.ArgumentParser()
    SERVICE.add_arguments(parser)
    config = SERVICE.config_from_args(
        parser.parse_args(
            [
                *("--max-hold-ms", "40", "--policy", "replace", "--gyro-missing", "reject"),
                *("--blur-mode", "max", "--q-min", "0.2", "--b0", "7", "--gyro-wait-ms", "9"),
            ]
        )
    )
    assert (config.max_hold_ms, config.policy, config.gyro_missing.value) == (
        40,
        "replace",
        "reject",
    )
    assert (config.blur_mode.value, config.q_min, config.b0_px) == ("max", 0.2, 7.0)
    assert SERVICE.config_from_args(parser.parse_args([])) == MediatorConfig()


def test_gyro_cache_joins_in_order_samples_and_trims_overlapping_ones() -> None:
    cache = GyroCache()
    # One-sample elements taken together become one batch of the cache.
    cache.add_parts([_batch(0, 1), _batch(1, 1), _batch(2, 1)])
    assert [int(t) // MS for t in cache.window(0, 8 * MS).t_ns] == [0, 1, 2]
    assert len(cache._batches) == 1
    # A re-delivered and an overlapping part: the late one dropped, the overlap trimmed.
    cache.add_parts([_batch(5, 2), _batch(1, 1), _batch(6, 3)])
    assert [int(t) // MS for t in cache.window(0, 8 * MS).t_ns] == [0, 1, 2, 5, 6, 7, 8]
    assert cache.dropped["late-batch"] == 1 and cache.dropped["overlap"] == 1


def test_small_gyro_batches_are_kept_joined() -> None:
    # Issue 30: 10 s of one-sample batches at 1 kHz, each taken alone, were 10,000 batches
    # kept, each arrival and each frame's look-up scanning them all: 5-6 ms each.
    kept: list[GyroSamples] = []
    for i in range(20_000):
        kept, _ = merge_batch(kept, _batch(i, 1), keep_ns=10_000 * MS)
    samples = sum(len(b) for b in kept)
    assert 10_000 <= samples <= 10_000 + 2 * JOIN_BELOW  # 10 s, forgotten a batch at a time
    assert len(kept) <= 2 * samples // JOIN_BELOW + 1, len(kept)
    assert _times_ms(kept) == list(range(20_000 - samples, 20_000))  # in order, none lost
