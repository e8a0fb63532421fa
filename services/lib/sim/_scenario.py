"""The scenario: one seeded approach, rendered on demand frame by frame.

This is the generator API the live camera and gyro services use (no disk involved); the
dataset writer drives the same object.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from services.lib.camera_model import CameraModel
from services.lib.markers import BOARD_MARKERS, detect_markers

from ._config import Bump, ScenarioConfig
from ._motion import Motion, gyro_trace
from ._records import FrameInfo, FrameTruth, GyroTrace, MarkerTruth
from ._render import Renderer
from ._scene import marker_corners_world

_NS = 1e-9


class Scenario:
    """A robot approaching the marker board over a bumpy floor, deterministic per seed.

    Motion and gyro data are computed at construction (cheap); textures on the first render.
    Frames can be rendered in any order and give the same bytes.
    """

    def __init__(self, config: ScenarioConfig | None = None) -> None:
        self.config = config if config is not None else ScenarioConfig()
        self.motion = Motion(self.config)
        self.renderer = Renderer(self.config, self.motion)

    @property
    def camera(self) -> CameraModel:
        """The camera description (intrinsics, gyro mounting and clock offset)."""
        return self.config.camera_model()

    @property
    def bumps(self) -> tuple[Bump, ...]:
        """The bumps the robot crosses (drawn from the seed unless configured)."""
        return self.motion.bumps

    @property
    def frame_count(self) -> int:
        """Number of frames in the approach."""
        return self.config.frame_count

    def frame_info(self, frame_id: int) -> FrameInfo:
        """Timing of one frame on the camera clock."""
        if not 0 <= frame_id < self.config.frame_count:
            raise IndexError(f"frame {frame_id} outside 0..{self.config.frame_count - 1}")
        return FrameInfo(frame_id, self.config.frame_start_ns(frame_id), self.config.exposure_ns)

    def render(self, frame_id: int) -> np.ndarray:
        """The mono8 frame (height x width uint8), motion-blurred and noisy."""
        self.frame_info(frame_id)
        return self.renderer.frame(frame_id)[0]

    def frames(
        self, start: int = 0, stop: int | None = None
    ) -> Iterator[tuple[FrameInfo, np.ndarray]]:
        """(FrameInfo, image) for frames start..stop-1, rendered as they are asked for."""
        stop = self.config.frame_count if stop is None else min(stop, self.config.frame_count)
        for frame_id in range(start, stop):
            yield self.frame_info(frame_id), self.render(frame_id)

    def gyro_samples(self) -> GyroTrace:
        """The whole gyro stream (gyro clock, gyro frame), covering every exposure."""
        t_ns, rate = gyro_trace(self.motion)
        return GyroTrace(t_ns, rate)

    def truth(self, frame_id: int, *, detect: bool = True) -> FrameTruth:
        """Ground truth of one frame.

        With ``detect`` it renders a blur-free version of the frame and decodes its markers
        (``detected_sharp``); without, only the geometry is computed (fast, no rendering)
        and ``detected_sharp`` is None.
        """
        self.frame_info(frame_id)
        detected: set[str | None] | None = None
        if detect:
            detected = {d.name for d in detect_markers(self.renderer.sharp_frame(frame_id))}
        return self._truth(frame_id, detected)

    def _truth(self, frame_id: int, detected_sharp: set[str | None] | None) -> FrameTruth:
        config, renderer = self.config, self.renderer
        start, exposure = renderer.frame_times_s(frame_id)
        line_s = config.line_readout_ns * _NS
        camera = self.camera
        centre_pixel = np.array([[camera.cx_px, camera.cy_px]])
        first_r, first_c = self.motion.camera_pose(np.array([start + camera.cy_px * line_s]))
        centre_point = renderer.scene_point(first_r[0], first_c[0], centre_pixel)
        corners = np.stack([marker_corners_world(config, m) for m in BOARD_MARKERS])
        points = np.vstack([centre_point, corners.mean(axis=1)])
        mid_r, mid_c = self.motion.camera_pose(np.array([start + exposure / 2]))
        mid_pix, _ = renderer.project(mid_r, mid_c, points)
        # Each point's exposure begins when its row does (same instant for a global shutter).
        rows = np.clip(mid_pix[0, :, 1], 0, config.height_px - 1)
        fractions = np.linspace(0.0, 1.0, config.truth_samples + 1)
        paths = []
        for point, row in zip(points, rows, strict=True):
            times = start + row * line_s + fractions * exposure
            r, c = self.motion.camera_pose(times)
            pix, _ = renderer.project(r, c, point[None])
            paths.append(float(np.linalg.norm(np.diff(pix[:, 0], axis=0), axis=1).sum()))
        corner_pix, corner_depth = renderer.project(mid_r, mid_c, corners.reshape(-1, 3))
        corner_pix = corner_pix.reshape(len(BOARD_MARKERS), 4, 2)
        corner_depth = corner_depth.reshape(len(BOARD_MARKERS), 4)
        markers = []
        for i, marker in enumerate(BOARD_MARKERS):
            quad = corner_pix[i]
            inside = (
                (corner_depth[i] > 0).all()
                and (quad[:, 0] >= 0).all() and (quad[:, 0] <= config.width_px - 1).all()
                and (quad[:, 1] >= 0).all() and (quad[:, 1] <= config.height_px - 1).all()
            )  # fmt: skip
            sides = np.linalg.norm(quad - np.roll(quad, 1, axis=0), axis=1)
            markers.append(
                MarkerTruth(
                    name=marker.name,
                    marker_id=marker.marker_id,
                    in_view=bool(inside),
                    size_px=float(sides.mean()),
                    blur_px=paths[i + 1],
                    centre_px=(float(mid_pix[0, i + 1, 0]), float(mid_pix[0, i + 1, 1])),
                    detected_sharp=(
                        None if detected_sharp is None else marker.name in detected_sharp
                    ),
                )
            )
        return FrameTruth(
            frame_id=frame_id,
            centre_blur_px=paths[0],
            camera_distance_m=-float(mid_c[0, 0]),
            substeps=renderer.substeps(frame_id)[0],
            markers=tuple(markers),
        )
