"""The mediator's configuration: each setting written once, with its flag and help
(``services.lib.settings``)."""

from __future__ import annotations

import argparse
from dataclasses import dataclass

from services.lib.argtypes import non_negative_float, positive_float, positive_int, unit_float
from services.lib.decisions import DEFAULT_POLICY, POLICIES, GyroMissing
from services.lib.quality import DEFAULT_B0_PX, BlurMode
from services.lib.settings import add_flags, from_args, setting


@dataclass(frozen=True, slots=True)
class MediatorConfig:
    """Everything the mediator can be told (one flag per field)."""

    name: str = setting("mediator", "service name")
    camera: str = setting("camera/images", "frames to filter (SERVICE/BUFFER)")
    gyro: str = setting("gyro/rates", "gyro batches (SERVICE/BUFFER)")
    camera_queue: int = setting(
        8, "notification queue on the camera (deep: never stall it)", parse=positive_int
    )
    b0_px: float = setting(
        DEFAULT_B0_PX,
        "blur scale b0 in pixels: q = exp(-blur/b0)",
        parse=positive_float,
        aliases=("--b0",),
    )
    q_min: float = setting(0.0, "minimum quality", parse=unit_float)
    policy: str = setting(
        DEFAULT_POLICY,
        "paper: q > load; replace: hold the sharpest frames, one per free slot",
        choices=sorted(POLICIES),
    )
    gyro_missing: GyroMissing = setting(
        GyroMissing.DEFAULT, "frames without gyro coverage: idle = accept only when idle"
    )
    gyro_wait_ms: float = setting(
        150.0,
        "how long a frame waits for gyro coverage after it arrived",
        parse=non_negative_float,
    )
    blur_mode: BlurMode = setting(
        BlurMode.DEFAULT,
        "where blur is measured (paper: center)",
        choices=[m.value for m in BlurMode if m is not BlurMode.POINT],
    )
    max_hold_ms: float = setting(
        250.0, "longest a frame may be held for the detector", parse=non_negative_float
    )
    horizon_s: float = setting(
        10.0, "frames stamped further ahead of our clock are skipped", parse=positive_float
    )
    max_clock_offset: float = setting(
        0.5,
        "camera-gyro clock offset allowed, as a fraction of the exposure",
        parse=positive_float,
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The mediator's flags (``framegate run mediator --help``): one per config field."""
    add_flags(parser, MediatorConfig)


def config_from_args(args: argparse.Namespace) -> MediatorConfig:
    """The config the parsed flags describe."""
    config: MediatorConfig = from_args(MediatorConfig, args)
    return config
