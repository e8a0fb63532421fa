"""The mediator's configuration: one field per setting, one flag per field."""

from __future__ import annotations

import argparse
from dataclasses import dataclass

from services.lib.decisions import DEFAULT_POLICY, POLICIES, GyroMissing
from services.lib.quality import DEFAULT_B0_PX, BlurMode


@dataclass(frozen=True, slots=True)
class MediatorConfig:
    """Everything the mediator can be told (one flag per field)."""

    name: str = "mediator"
    camera: str = "camera/images"
    gyro: str = "gyro/rates"
    camera_queue: int = 8
    b0_px: float = DEFAULT_B0_PX
    q_min: float = 0.0
    policy: str = DEFAULT_POLICY
    gyro_missing: GyroMissing = GyroMissing.DEFAULT
    gyro_wait_ms: float = 150.0
    blur_mode: BlurMode = BlurMode.DEFAULT
    max_hold_ms: float = 250.0
    horizon_s: float = 10.0
    max_clock_offset: float = 0.5


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The mediator's flags (``framegate run mediator --help``): one per config field."""
    from services.lib.argtypes import non_negative_float, positive_float, positive_int, unit_float

    d = MediatorConfig()
    parser.add_argument("--name", default=d.name, help="service name (default %(default)s)")
    parser.add_argument("--camera", default=d.camera, help="frames to filter (SERVICE/BUFFER)")
    parser.add_argument("--gyro", default=d.gyro, help="gyro batches (SERVICE/BUFFER)")
    parser.add_argument(
        "--camera-queue",
        type=positive_int,
        default=d.camera_queue,
        help="notification queue on the camera (deep: never stall it)",
    )
    parser.add_argument(
        "--b0",
        type=positive_float,
        default=d.b0_px,
        dest="b0_px",
        help="blur scale b0 in pixels: q = exp(-blur/b0) (default %(default)s)",
    )
    parser.add_argument("--q-min", type=unit_float, default=d.q_min, help="minimum quality")
    parser.add_argument(
        "--policy",
        choices=sorted(POLICIES),
        default=d.policy,
        help="paper: q > load; replace: hold the sharpest frames, one per free slot",
    )
    parser.add_argument(
        "--gyro-missing",
        choices=[g.value for g in GyroMissing],
        default=d.gyro_missing.value,
        help="frames without gyro coverage: idle = accept only when idle",
    )
    parser.add_argument(
        "--gyro-wait-ms",
        type=non_negative_float,
        default=d.gyro_wait_ms,
        help="how long to wait for gyro coverage after exposure end",
    )
    parser.add_argument(
        "--blur-mode",
        choices=[m.value for m in BlurMode if m is not BlurMode.POINT],
        default=d.blur_mode.value,
        help="where blur is measured (paper: center)",
    )
    parser.add_argument(
        "--max-hold-ms",
        type=non_negative_float,
        default=d.max_hold_ms,
        help="longest a frame may be held for the detector (default %(default)s)",
    )
    parser.add_argument(
        "--horizon-s",
        type=positive_float,
        default=d.horizon_s,
        help="frames stamped further ahead of our clock are skipped (default %(default)s)",
    )
    parser.add_argument(
        "--max-clock-offset",
        type=positive_float,
        default=d.max_clock_offset,
        help="camera-gyro clock offset allowed, as a fraction of the exposure (default "
        "%(default)s)",
    )


def config_from_args(args: argparse.Namespace) -> MediatorConfig:
    """The config the parsed flags describe."""
    return MediatorConfig(
        name=args.name,
        camera=args.camera,
        gyro=args.gyro,
        camera_queue=args.camera_queue,
        b0_px=args.b0_px,
        q_min=args.q_min,
        policy=args.policy,
        gyro_missing=GyroMissing(args.gyro_missing),
        gyro_wait_ms=args.gyro_wait_ms,
        blur_mode=BlurMode(args.blur_mode),
        max_hold_ms=args.max_hold_ms,
        horizon_s=args.horizon_s,
        max_clock_offset=args.max_clock_offset,
    )
