"""Motion and gyro: the gyro reads the same motion the renderer uses."""

from __future__ import annotations

import numpy as np

from services.lib.sim import Bump, Scenario, ScenarioConfig

NO_BUMPS = ScenarioConfig(bumps=(), frame_count=40)


def test_same_seed_same_bumps_and_gyro_different_seed_differs() -> None:
    a, b, c = (Scenario(ScenarioConfig(seed=s)) for s in (4, 4, 5))
    assert a.bumps == b.bumps != c.bumps
    assert np.array_equal(a.gyro_samples().rate_rad_s, b.gyro_samples().rate_rad_s)
    assert not np.array_equal(a.gyro_samples().rate_rad_s, c.gyro_samples().rate_rad_s)


def test_random_bumps_match_the_configured_statistics() -> None:
    config = ScenarioConfig(seed=2)
    bumps = Scenario(config).bumps
    spacing = np.diff([b.at_travel_m for b in bumps])
    assert 15 <= len(bumps) <= 35  # about 11.8 m of travel at 0.5 m mean spacing
    assert spacing.min() >= config.bump_length_max_m
    assert max(b.height_m for b in bumps) <= 0.01
    assert {b.track for b in bumps} == {"left", "right", "both"}


def test_gyro_covers_every_exposure_on_its_own_clock() -> None:
    scenario = Scenario(NO_BUMPS)
    gyro = scenario.gyro_samples()
    offset = scenario.camera.gyro_time_offset_ns
    assert gyro.rate_hz == 1000.0
    for frame_id in (0, NO_BUMPS.frame_count - 1):
        info = scenario.frame_info(frame_id)
        inside = gyro.between(
            info.exposure_start_ns + offset, info.exposure_start_ns + info.exposure_ns + offset
        )
        assert len(inside) == 60


def test_zero_bumps_give_noise_only_gyro_and_sharp_frames() -> None:
    config = NO_BUMPS.replace(gyro_noise_rad_s=0.002, gyro_bias_rad_s=0.005)
    scenario = Scenario(config)
    rates = scenario.gyro_samples().rate_rad_s
    bias = rates.mean(axis=0)
    assert np.all(np.abs(bias) < 4 * config.gyro_bias_rad_s)
    assert np.all(np.abs(rates - bias) < 6 * config.gyro_noise_rad_s)
    assert np.allclose((rates - bias).std(axis=0), config.gyro_noise_rad_s, rtol=0.1)
    blur = [scenario.truth(i, detect=False).centre_blur_px for i in range(config.frame_count)]
    # Only forward translation is left: a fraction of a pixel this far from the wall.
    assert max(blur) < 0.5


def test_gyro_is_the_camera_angular_velocity_in_the_gyro_frame() -> None:
    config = ScenarioConfig(seed=1, gyro_noise_rad_s=0.0, gyro_bias_rad_s=0.0)
    scenario = Scenario(config)
    gyro = scenario.gyro_samples()
    camera = scenario.camera
    pick = slice(2000, 12000, 37)
    true_s = (gyro.t_ns[pick] - camera.gyro_time_offset_ns) * 1e-9
    step = 1e-6
    r0, _ = scenario.motion.camera_pose(true_s)
    r1, _ = scenario.motion.camera_pose(true_s + step)
    # d/dt R_cw = -[w_c]x R_cw for a world-to-camera rotation.
    skew = -(r1 - r0) / step @ np.transpose(r0, (0, 2, 1))
    from_images = np.stack([skew[:, 2, 1], skew[:, 0, 2], skew[:, 1, 0]], axis=1)
    from_gyro = gyro.rate_rad_s[pick] @ camera.rotation_gyro_to_camera.T
    assert np.abs(from_gyro).max() > 0.1  # the bumps do shake the camera
    assert np.allclose(from_images, from_gyro, atol=1e-4)


def _gyro_blur_px(scenario: Scenario, frame_id: int) -> float:
    """The paper's estimate (Eq. 2): integrate the image-centre motion from the gyro."""
    camera = scenario.camera
    info = scenario.frame_info(frame_id)
    start = info.exposure_start_ns + camera.gyro_time_offset_ns
    samples = scenario.gyro_samples().between(start, start + info.exposure_ns)
    w = samples.rate_rad_s @ camera.rotation_gyro_to_camera.T
    return float(np.hypot(w[:, 0], w[:, 1]).sum() * 1e-3 * camera.fx_px)


def test_a_single_pitch_bump_blurs_the_frames_the_gyro_points_at() -> None:
    bump_frame = 8
    # Front wheels reach it at frame 8's exposure midpoint; both tracks, so pure pitch.
    bump = Bump(at_travel_m=(bump_frame + 0.45) / 15 * 0.54, height_m=0.01, length_m=0.1)
    config = ScenarioConfig(
        seed=0, frame_count=20, gyro_noise_rad_s=0.0, gyro_bias_rad_s=0.0, bumps=(bump,)
    )
    scenario = Scenario(config)
    truth = [scenario.truth(i, detect=False).centre_blur_px for i in range(config.frame_count)]
    gyro = [_gyro_blur_px(scenario, i) for i in range(config.frame_count)]
    worst = int(np.argmax(truth))
    # The wheels cross the bump in 0.19 s; the sprung body answers within one pitch period.
    enter_s = bump.at_travel_m / config.speed_m_s
    settled_s = enter_s + bump.length_m / config.speed_m_s + 1 / config.pitch_hz
    start_s = (scenario.frame_info(worst).exposure_start_ns - config.lead_in_ns) * 1e-9
    assert enter_s - 0.06 <= start_s <= settled_s, (worst, truth)
    assert int(np.argmax(gyro)) == worst
    assert truth[worst] > 3.0
    assert max(truth[:bump_frame]) < 0.5  # before the bump the camera is steady
    assert np.corrcoef(truth, gyro)[0, 1] > 0.95
    # And the rendered frames agree: the worst frame has lost its fine detail.
    rows = slice(0, 300)  # the wall, above the floor
    steady = scenario.render(bump_frame - 4)[rows].astype(np.float32)
    shaken = scenario.render(worst)[rows].astype(np.float32)
    detail = [float(np.abs(np.diff(img, axis=0)).mean()) for img in (steady, shaken)]
    assert detail[1] < 0.8 * detail[0], detail
