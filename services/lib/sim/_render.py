"""Rendering: the exposure integral of the scene under the true camera motion, then the sensor.

A frame is the mean of sharp images at evenly spaced instants of the exposure (the midpoint
rule for the time integral), each warped by the exact pose at its instant, so the blur is the
one the trajectory implies, rotation and translation alike. The number of instants adapts
to the motion: consecutive warps move the wall by at most ``max_substep_px``. With a rolling
shutter each band of rows is rendered at its own instants. Then lens blur, shot and read
noise, and 8-bit quantisation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ._config import ScenarioConfig
from ._motion import Motion
from ._rng import Stream, rng_for
from ._scene import PlaneTexture, Scene, board_corners_world

_NS = 1e-9
# Samples of the probes' paths per exposure when choosing how many sub-steps to use.
_PROBE_SEGMENTS = 32
_PROBE_GRID = 5


@dataclass(frozen=True, slots=True)
class Levels:
    """The texture level of each plane for one frame."""

    wall: int
    board: int


def _warp(
    texture: np.ndarray, homography: np.ndarray, cols: tuple[int, int],
    rows: tuple[int, int], *, periodic: bool,
) -> np.ndarray:  # fmt: skip
    """Warp a texture into the image region cols x rows (half-open)."""
    shift = np.array([[1.0, 0.0, -cols[0]], [0.0, 1.0, -rows[0]], [0.0, 0.0, 1.0]])
    return cv2.warpPerspective(
        texture,
        shift @ homography,
        (cols[1] - cols[0], rows[1] - rows[0]),
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_WRAP if periodic else cv2.BORDER_CONSTANT,
        borderValue=0,
    )


class Renderer:
    """Renders frames of one scenario."""

    def __init__(self, config: ScenarioConfig, motion: Motion, scene: Scene | None = None) -> None:
        self.config = config
        self.motion = motion
        self._scene = scene
        camera = config.camera_model()
        self.camera_matrix = np.array(
            [[camera.fx_px, 0.0, camera.cx_px], [0.0, camera.fy_px, camera.cy_px], [0, 0, 1.0]]
        )
        self._board_corners = board_corners_world(config)

    @property
    def scene(self) -> Scene:
        """The textured scene, built on first use (geometry alone does not need it)."""
        if self._scene is None:
            self._scene = Scene.build(self.config)
        return self._scene

    # -- geometry --

    def project(
        self, r_cam_world: np.ndarray, centre: np.ndarray, points: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (n_poses, n_points, 2) and depths (n_poses, n_points) of world points."""
        rel = points[None, :, :] - centre[:, None, :]
        cam = np.einsum("pij,pnj->pni", r_cam_world, rel)
        depth = cam[..., 2]
        pix = np.einsum("ij,pnj->pni", self.camera_matrix, cam)
        return pix[..., :2] / pix[..., 2:3], depth

    def scene_point(self, r_cam_world: np.ndarray, centre: np.ndarray,
                    pixels: np.ndarray) -> np.ndarray:  # fmt: skip
        """World points seen at ``pixels`` (n, 2) from one pose: on the wall, or the floor
        where the floor hides the wall. NaN rows for rays that hit neither."""
        rays = np.column_stack([pixels, np.ones(len(pixels))]) @ np.linalg.inv(self.camera_matrix).T
        dirs = rays @ r_cam_world  # camera to world: R^T @ ray, row-wise
        with np.errstate(divide="ignore", invalid="ignore"):
            to_wall = -centre[0] / dirs[:, 0]
            to_floor = -centre[2] / dirs[:, 2]
        to_wall = np.where(to_wall > 0, to_wall, np.inf)
        to_floor = np.where(to_floor > 0, to_floor, np.inf)
        dist = np.minimum(to_wall, to_floor)
        points = centre[None, :] + dist[:, None] * dirs
        points[~np.isfinite(dist)] = np.nan
        return np.asarray(points)

    def frame_times_s(self, frame_id: int) -> tuple[float, float]:
        """Exposure start and length in seconds on the camera clock."""
        return self.config.frame_start_ns(frame_id) * _NS, self.config.exposure_ns * _NS

    def substeps(self, frame_id: int) -> tuple[int, int]:
        """(instants, row bands) for a frame: enough that consecutive warps differ by at
        most ``max_substep_px`` on the wall, capped at ``max_substeps``."""
        config = self.config
        start, exposure = self.frame_times_s(frame_id)
        readout = config.line_readout_ns * (config.height_px - 1) * _NS
        r_mid, c_mid = self.motion.camera_pose(np.array([start + (exposure + readout) / 2]))
        grid = np.stack(
            np.meshgrid(
                np.linspace(0, config.width_px - 1, _PROBE_GRID),
                np.linspace(0, config.height_px - 1, _PROBE_GRID),
            ),
            axis=-1,
        ).reshape(-1, 2)
        points = self.scene_point(r_mid[0], c_mid[0], grid)
        # The floor is smooth by design (floor_feature_m), so only wall probes set the step.
        points = points[np.isfinite(points).all(axis=1) & (np.abs(points[:, 0]) < 1e-9)]
        points = np.vstack([points, self._board_corners])
        span = exposure + readout
        times = start + np.linspace(0.0, span, _PROBE_SEGMENTS + 1)
        r, c = self.motion.camera_pose(times)
        pix, _ = self.project(r, c, points)
        step = np.linalg.norm(np.diff(pix, axis=0), axis=-1).max()
        speed_px_s = float(step) * _PROBE_SEGMENTS / span
        cap = config.max_substeps
        instants = min(cap, max(1, math.ceil(speed_px_s * exposure / config.max_substep_px)))
        bands = min(cap, max(1, math.ceil(speed_px_s * readout / config.max_substep_px)))
        return instants, bands

    def levels(self, centre: np.ndarray) -> Levels:
        """Texture levels for a camera at ``centre``: texels about one pixel's footprint."""
        footprint_m = max(-float(centre[0]), 1e-3) / self.config.focal_px
        return Levels(
            wall=self.scene.wall.level_for(footprint_m),
            board=self.scene.board.level_for(footprint_m),
        )

    # -- images --

    def radiance(
        self, r_cam_world: np.ndarray, centre: np.ndarray, rows: tuple[int, int], levels: Levels
    ) -> np.ndarray:
        """Sharp scene radiance (reflectance) in image rows ``rows`` for one pose."""
        width = self.config.width_px
        r0, r1 = rows
        k = self.camera_matrix
        wall, floor, board = self.scene.wall, self.scene.floor, self.scene.board
        h_wall = wall.image_from_texture(levels.wall, k, r_cam_world, centre)
        h_floor = floor.image_from_texture(0, k, r_cam_world, centre)
        line = self._wall_floor_line(r_cam_world, centre)
        if line[1] < 0:
            # Wall above the line (the normal case): wall rows, floor rows, a band of both.
            v_edges = -(line[0] * np.array([0.0, width - 1]) + line[2]) / line[1]
            margin = 0.5 / abs(line[1])
            band0 = int(np.clip(math.floor(v_edges.min() - margin), r0, r1))
            band1 = int(np.clip(math.ceil(v_edges.max() + margin) + 1, r0, r1))
        else:
            band0, band1 = r0, r1
        out = np.empty((r1 - r0, width), dtype=np.float32)
        if band1 > r0:
            out[: band1 - r0] = _warp(
                wall.levels[levels.wall], h_wall, (0, width), (r0, band1), periodic=True
            )
        if r1 > band0:
            below = _warp(floor.levels[0], h_floor, (0, width), (band0, r1), periodic=True)
            wall_part = out[band0 - r0 : band1 - r0]
            v = np.arange(band0, band1, dtype=np.float32)[:, None]
            u = np.arange(width, dtype=np.float32)[None, :]
            mask = np.clip(0.5 + line[0] * u + line[1] * v + line[2], 0.0, 1.0)
            out[band0 - r0 : band1 - r0] = below[: band1 - band0] + mask * (
                wall_part - below[: band1 - band0]
            )
            out[band1 - r0 :] = below[band1 - band0 :]
        self._paint_board(out, board, levels.board, r_cam_world, centre, rows)
        return out

    def _wall_floor_line(self, r_cam_world: np.ndarray, centre: np.ndarray) -> np.ndarray:
        """Image line where wall meets floor, as (a, b, c) with a*u + b*v + c the signed pixel
        distance, positive on the wall side."""
        k = self.camera_matrix
        point = k @ r_cam_world @ (np.zeros(3) - centre)
        direction = k @ r_cam_world @ np.array([0.0, 1.0, 0.0])
        line = np.cross(point, direction)
        line = line / np.hypot(line[0], line[1])
        above = k @ r_cam_world @ (np.array([0.0, centre[1], 1.0]) - centre)
        if line @ (above / above[2]) < 0:
            line = -line
        return np.asarray(line)

    def _paint_board(self, out: np.ndarray, board: PlaneTexture, level: int,
                     r_cam_world: np.ndarray, centre: np.ndarray,
                     rows: tuple[int, int]) -> None:  # fmt: skip
        pix, depth = self.project(r_cam_world[None], centre[None], self._board_corners)
        if (depth <= 0).any():
            return  # never the case in this scenario: the board stays in front
        c0 = max(0, math.floor(pix[0, :, 0].min()) - 2)
        c1 = min(self.config.width_px, math.ceil(pix[0, :, 0].max()) + 3)
        b0 = max(rows[0], math.floor(pix[0, :, 1].min()) - 2)
        b1 = min(rows[1], math.ceil(pix[0, :, 1].max()) + 3)
        if c1 <= c0 or b1 <= b0:
            return
        h = board.image_from_texture(level, self.camera_matrix, r_cam_world, centre)
        assert board.alpha is not None
        value = _warp(board.levels[level], h, (c0, c1), (b0, b1), periodic=False)
        alpha = _warp(board.alpha[level], h, (c0, c1), (b0, b1), periodic=False)
        region = out[b0 - rows[0] : b1 - rows[0], c0:c1]
        region *= 1.0 - alpha
        region += value

    def exposure_radiance(self, frame_id: int) -> tuple[np.ndarray, int]:
        """Mean radiance over the frame's exposure, and the number of instants used."""
        config = self.config
        start, exposure = self.frame_times_s(frame_id)
        instants, bands = self.substeps(frame_id)
        line_s = config.line_readout_ns * _NS
        edges = np.linspace(0, config.height_px, bands + 1).round().astype(int)
        offsets = (np.arange(instants) + 0.5) / instants * exposure
        row_mid = (edges[:-1] + edges[1:] - 1) / 2
        times = start + offsets[:, None] + row_mid[None, :] * line_s
        r, c = self.motion.camera_pose(times.ravel())
        levels = self.levels(self.motion.camera_pose(np.array([start + exposure / 2]))[1][0])
        total = np.zeros((config.height_px, config.width_px), dtype=np.float32)
        for i in range(instants * bands):
            b = i % bands
            rows = (int(edges[b]), int(edges[b + 1]))
            total[rows[0] : rows[1]] += self.radiance(r[i], c[i], rows, levels)
        total /= instants
        return total, instants

    def sharp_radiance(self, t_s: float) -> np.ndarray:
        """The scene at one instant, no motion blur."""
        r, c = self.motion.camera_pose(np.array([t_s]))
        return self.radiance(r[0], c[0], (0, self.config.height_px), self.levels(c[0]))

    def sensor(self, radiance: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Lens blur, shot and read noise, gain and 8-bit quantisation: the mono8 image."""
        config = self.config
        if config.optics_blur_px > 0:
            radiance = cv2.GaussianBlur(radiance, (0, 0), config.optics_blur_px)
        electrons = np.maximum(radiance, 0.0) * np.float32(config.white_signal_e)
        # Shot noise (Poisson, Gaussian at these counts) and read noise add in variance.
        sigma = np.sqrt(electrons + np.float32(config.read_noise_e**2))
        electrons += sigma * rng.standard_normal(electrons.shape, dtype=np.float32)
        gain = np.float32((255.0 - config.black_level_dn) / config.full_scale_e)
        dn = np.rint(electrons * gain + np.float32(config.black_level_dn))
        return np.asarray(np.clip(dn, 0, 255), dtype=np.uint8)

    def frame(self, frame_id: int) -> tuple[np.ndarray, int]:
        """The mono8 frame and the number of instants its exposure was rendered with."""
        radiance, instants = self.exposure_radiance(frame_id)
        image = self.sensor(radiance, rng_for(self.config.seed, Stream.FRAME_NOISE, frame_id))
        return image, instants

    def sharp_frame(self, frame_id: int) -> np.ndarray:
        """The same frame without motion blur: the pose at exposure midpoint, own noise."""
        start, exposure = self.frame_times_s(frame_id)
        radiance = self.sharp_radiance(start + exposure / 2)
        return self.sensor(radiance, rng_for(self.config.seed, Stream.SHARP_NOISE, frame_id))
