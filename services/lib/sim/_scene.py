"""The scene: a textured wall (plane X = 0), a floor (Z = 0) and the marker board on the wall.

Each surface is a plane with a texture of reflectances, so a camera pose maps it to the
image by an exact homography. Textures come as mip levels (level k has texels 2**k times
larger, low-passed by ``pyrDown``) so a far wall is sampled without aliasing; wall and floor
are periodic, which makes them endless without storing an endless image.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from services.lib.markers import (
    BOARD_HEIGHT_M,
    BOARD_MARKERS,
    BOARD_REFLECTANCE,
    BOARD_WIDTH_M,
    MARKER_BLACK_REFLECTANCE,
    BoardMarker,
    marker_bits,
)

from . import _scene_cache
from ._config import ScenarioConfig
from ._rng import Stream, rng_for

# Enough zero-alpha margin around the board that five pyrDown levels never see its border.
_BOARD_PAD = 64
_WRAP_PAD = 8
_MIN_LEVEL_TEXELS = 64


@dataclass(frozen=True, slots=True)
class PlaneTexture:
    """Texture levels on a world plane.

    The centre of level-0 texel (u, v) is the world point ``origin + u*axis_u + v*axis_v``
    (axes already scaled by the texel size); level k's texel j sits at level-0 coordinate
    ``2**k * j``, which is where ``pyrDown`` centres it. ``alpha`` levels (premultiplied
    ``levels``) mark where a non-periodic texture exists.
    """

    levels: tuple[np.ndarray, ...]
    alpha: tuple[np.ndarray, ...] | None
    texel_m: float
    origin: np.ndarray
    axis_u: np.ndarray
    axis_v: np.ndarray
    periodic: bool

    def image_from_texture(self, level: int, camera_matrix: np.ndarray,
                           r_cam_world: np.ndarray, centre: np.ndarray) -> np.ndarray:  # fmt: skip
        """Homography from level-``level`` texel coordinates to image pixels."""
        scale = float(2**level)
        plane = np.column_stack([self.axis_u * scale, self.axis_v * scale, self.origin - centre])
        return np.asarray(camera_matrix @ r_cam_world @ plane)

    def level_for(self, footprint_m: float) -> int:
        """The coarsest level whose texels are no larger than one pixel's footprint."""
        if footprint_m <= self.texel_m:
            return 0
        level = int(np.floor(np.log2(footprint_m / self.texel_m)))
        return min(level, len(self.levels) - 1)


def _even(texels: float) -> int:
    """A texel count rounded to even, at least 2, so every pyramid level tiles the period."""
    return max(2, 2 * round(texels / 2))


def _wrap_pyramid(base: np.ndarray) -> tuple[np.ndarray, ...]:
    levels = [base]
    # Halving must keep whole periods, so only even sizes go down a level.
    while min(levels[-1].shape) // 2 >= _MIN_LEVEL_TEXELS and not any(
        n % 2 for n in levels[-1].shape
    ):
        padded = np.pad(levels[-1], _WRAP_PAD, mode="wrap")
        half = _WRAP_PAD // 2
        levels.append(np.ascontiguousarray(cv2.pyrDown(padded)[half:-half, half:-half]))
    return tuple(levels)


def _pyramid(base: np.ndarray, count: int) -> tuple[np.ndarray, ...]:
    levels = [base]
    for _ in range(count - 1):
        levels.append(cv2.pyrDown(levels[-1]))
    return tuple(levels)


def _periodic_noise(
    rng: np.random.Generator, shape: tuple[int, int], texel_m: float, feature_m: float
) -> np.ndarray:
    """Zero-mean, unit-std periodic noise with a 1/f amplitude spectrum above ``feature_m``."""
    white = rng.standard_normal(shape, dtype=np.float32)
    fy = np.fft.fftfreq(shape[0], d=texel_m)[:, None]
    fx = np.fft.rfftfreq(shape[1], d=texel_m)[None, :]
    freq = np.hypot(fx, fy)
    freq[0, 0] = np.inf  # no DC: the mean is set separately
    # 1/f amplitude like natural images; a Gaussian roll-off removes detail finer than feature_m.
    spectrum = np.fft.rfft2(white) / freq * np.exp(-((freq * feature_m) ** 2))
    noise = np.fft.irfft2(spectrum, s=shape)
    return np.asarray(noise / noise.std(), dtype=np.float32)


def _wall_shape(config: ScenarioConfig) -> tuple[int, int]:
    return (_even(config.wall_height_m / config.wall_texel_m),
            _even(config.wall_period_m / config.wall_texel_m))  # fmt: skip


def _wall_texture(config: ScenarioConfig, rng: np.random.Generator) -> np.ndarray:
    shape = _wall_shape(config)
    noise = _periodic_noise(rng, shape, config.wall_texel_m, 2 * config.wall_texel_m)
    texture = config.wall_reflectance + config.wall_contrast * noise
    # Posters and panels: straight, sharp edges, where motion blur shows most. Axis-aligned, so
    # their exact box-filtered coverage is separable; indices wrap to keep the wall periodic.
    for _ in range(int(0.75 * config.wall_period_m * config.wall_height_m)):
        w, h = rng.uniform(0.08, 0.9, 2) / config.wall_texel_m
        x, y = rng.uniform(0, 1, 2) * shape[::-1]
        level = config.wall_reflectance + float(rng.uniform(-2.5, 2.5)) * config.wall_contrast
        cols = np.arange(int(np.floor(x - 0.5)), int(np.ceil(x + w + 0.5)))
        rows = np.arange(int(np.floor(y - 0.5)), int(np.ceil(y + h + 0.5)))
        across = _coverage(np.array([x, x + w]) - cols[0], len(cols))[0]
        down = _coverage(np.array([y, y + h]) - rows[0], len(rows))[0]
        cover = np.outer(down, across)
        region = np.ix_(rows % shape[0], cols % shape[1])
        inside = level + 0.5 * (texture[region] - config.wall_reflectance)
        texture[region] = (1 - cover) * texture[region] + cover * inside
    return np.clip(texture, 0.03, 0.97).astype(np.float32)


def _wall(config: ScenarioConfig, texture: np.ndarray) -> PlaneTexture:
    return PlaneTexture(
        levels=_wrap_pyramid(texture),
        alpha=None,
        texel_m=config.wall_texel_m,
        origin=np.array([0.0, config.wall_period_m / 2, config.wall_height_m]),
        axis_u=np.array([0.0, -config.wall_texel_m, 0.0]),
        axis_v=np.array([0.0, 0.0, -config.wall_texel_m]),
        periodic=True,
    )


def _floor_shape(config: ScenarioConfig) -> tuple[int, int]:
    size = _even(config.floor_period_m / config.floor_texel_m)
    return (size, size)


def _floor_texture(config: ScenarioConfig, rng: np.random.Generator) -> np.ndarray:
    noise = _periodic_noise(rng, _floor_shape(config), config.floor_texel_m, config.floor_feature_m)
    texture = np.clip(config.floor_reflectance + config.floor_contrast * noise, 0.02, 0.98)
    return texture.astype(np.float32)


def _floor(config: ScenarioConfig, texture: np.ndarray) -> PlaneTexture:
    return PlaneTexture(
        levels=(texture,),
        alpha=None,
        texel_m=config.floor_texel_m,
        origin=np.zeros(3),
        axis_u=np.array([0.0, -config.floor_texel_m, 0.0]),
        axis_v=np.array([-config.floor_texel_m, 0.0, 0.0]),
        periodic=True,
    )


def _coverage(edges: np.ndarray, count: int) -> np.ndarray:
    """(len(edges) - 1, count): how much of texel j (spanning [j-0.5, j+0.5]) each interval
    between consecutive ``edges`` (in texel coordinates) covers."""
    centres = np.arange(count)[None, :]
    lo = np.maximum(edges[:-1, None], centres - 0.5)
    hi = np.minimum(edges[1:, None], centres + 0.5)
    return np.asarray(np.clip(hi - lo, 0.0, None))


def _board(config: ScenarioConfig) -> PlaneTexture:
    texel = config.board_texel_m
    width, height = round(BOARD_WIDTH_M / texel), round(BOARD_HEIGHT_M / texel)
    value = np.zeros((height + 2 * _BOARD_PAD, width + 2 * _BOARD_PAD), dtype=np.float32)
    alpha = np.zeros_like(value)
    inner = np.s_[_BOARD_PAD : _BOARD_PAD + height, _BOARD_PAD : _BOARD_PAD + width]
    value[inner] = BOARD_REFLECTANCE
    alpha[inner] = 1.0
    for marker in BOARD_MARKERS:
        # Box-filtered exactly: each texel gets the area-weighted mean of the cells it overlaps.
        side = marker.size_m / texel
        left = _BOARD_PAD - 0.5 + (marker.centre_x_m - marker.size_m / 2) / texel
        top = _BOARD_PAD - 0.5 + (BOARD_HEIGHT_M - marker.centre_y_m - marker.size_m / 2) / texel
        cols = np.arange(int(np.floor(left)), int(np.ceil(left + side)) + 1)
        rows = np.arange(int(np.floor(top)), int(np.ceil(top + side)) + 1)
        cell_edges = side / 6 * np.arange(7)
        across = _coverage(left - cols[0] + cell_edges, len(cols))
        down = _coverage(top - rows[0] + cell_edges, len(rows))
        cells = np.where(marker_bits(marker.marker_id), BOARD_REFLECTANCE, MARKER_BLACK_REFLECTANCE)
        covered = down.T @ np.ones((6, 6)) @ across
        region = np.s_[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
        value[region] = down.T @ cells @ across + (1 - covered) * value[region]
    levels = 1 + max(0, int(np.log2(min(value.shape) / _MIN_LEVEL_TEXELS)))
    levels = min(levels, int(np.log2(_BOARD_PAD)))
    left_y = config.board_lateral_m + BOARD_WIDTH_M / 2
    top_z = config.board_bottom_m + BOARD_HEIGHT_M
    return PlaneTexture(
        levels=_pyramid(value, levels),  # premultiplied: alpha is 1 wherever value is set
        alpha=_pyramid(alpha, levels),
        texel_m=texel,
        origin=np.array(
            [0.0, left_y - (0.5 - _BOARD_PAD) * texel, top_z - (0.5 - _BOARD_PAD) * texel]
        ),
        axis_u=np.array([0.0, -texel, 0.0]),
        axis_v=np.array([0.0, 0.0, -texel]),
        periodic=False,
    )


@dataclass(frozen=True, slots=True)
class Scene:
    """The three textured planes of one scenario."""

    wall: PlaneTexture
    floor: PlaneTexture
    board: PlaneTexture

    @classmethod
    def build(cls, config: ScenarioConfig) -> Scene:
        """Textures for this configuration (drawn from the seed's texture stream, or read
        back from the scene cache, which holds exactly what the stream draws)."""
        shapes = {"wall": _wall_shape(config), "floor": _floor_shape(config)}
        textures = _scene_cache.load(config, "scene", shapes, np.float32)
        if textures is None:
            rng = rng_for(config.seed, Stream.TEXTURE)
            textures = {"wall": _wall_texture(config, rng), "floor": _floor_texture(config, rng)}
            _scene_cache.save(config, "scene", textures)
        return cls(
            wall=_wall(config, textures["wall"]),
            floor=_floor(config, textures["floor"]),
            board=_board(config),
        )


def marker_corners_world(config: ScenarioConfig, marker: BoardMarker) -> np.ndarray:
    """(4, 3) world corners of a board marker: top-left, top-right, bottom-right, bottom-left
    as seen facing the board (ArUco's corner order)."""
    left_y = config.board_lateral_m + BOARD_WIDTH_M / 2
    centre_y = left_y - marker.centre_x_m
    centre_z = config.board_bottom_m + marker.centre_y_m
    half = marker.size_m / 2
    offsets = np.array([[half, half], [-half, half], [-half, -half], [half, -half]])
    return np.column_stack([np.zeros(4), centre_y + offsets[:, 0], centre_z + offsets[:, 1]])


def board_corners_world(config: ScenarioConfig) -> np.ndarray:
    """(4, 3) world corners of the whole board."""
    left_y = config.board_lateral_m + BOARD_WIDTH_M / 2
    right_y = left_y - BOARD_WIDTH_M
    bottom, top = config.board_bottom_m, config.board_bottom_m + BOARD_HEIGHT_M
    return np.array(
        [[0, left_y, top], [0, right_y, top], [0, right_y, bottom], [0, left_y, bottom]]
    )
