"""Motion blur from gyro rates: the paper's centre estimate (eq. 2) and what goes beyond it.

A world direction is fixed to a pixel's ray at the start of that pixel's exposure and
followed through the camera rotation accumulated so far; its pinhole projection traces the
blur path, whose length in pixels (the sum of segment lengths, eq. 2) is the blur. Knots are
the exposure ends and every gyro sample between them. Translation is ignored, as in the paper
(§4.2), and so is lens distortion.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import numpy.typing as npt

from services.lib.camera_model import CameraModel

from ._coverage import covering
from ._errors import QualityInputError
from ._exposure import Exposure
from ._gyro import GyroSamples
from ._rotation import (
    DUPLICATED_ROWS,
    axis_projection,
    cumulative_rotation,
    inverse_rotation_matrices,
    knot_increments,
    project_optical_axis,
    window_increments,
)

Floats = npt.NDArray[np.float64]

# A tracked ray whose depth falls to this has turned ~90 degrees away during the exposure;
# its projection is meaningless and the blur is reported as infinite.
_MIN_DEPTH = 1e-6


class BlurMode(enum.Enum):
    """Where blur is measured. DEFAULT is the paper's choice, the image centre."""

    CENTER = "center"
    """The principal point (cx, cy): roll contributes nothing there (paper §4.2)."""
    POINT = "point"
    """One pixel, ``BlurOptions.point_px``; roll matters off-centre."""
    MEAN = "mean"
    """Mean blur over a grid of pixels (the frame, or ``BlurOptions.roi``)."""
    MAX = "max"
    """Largest blur over that grid: the worst-blurred place decides."""
    DEFAULT = "center"


@dataclass(frozen=True, slots=True)
class Roi:
    """A rectangle of the image in pixels, e.g. where a marker was last seen."""

    x_px: float
    y_px: float
    width_px: float
    height_px: float

    def __post_init__(self) -> None:
        if not (self.width_px > 0 and self.height_px > 0):
            raise QualityInputError(
                f"ROI needs a positive size, got {self.width_px} x {self.height_px} px"
            )


@dataclass(frozen=True, slots=True)
class BlurOptions:
    """How ``estimate_blur`` measures. The defaults are the paper's estimate.

    ``grid`` is (columns, rows) of the MEAN/MAX grid, whose points are cell centres over
    ``roi`` (None: the whole frame). ``rolling_shutter`` shifts each pixel's exposure by
    row * ``CameraModel.line_readout_ns``. ``max_gap_ns`` is the longest allowed spacing
    of gyro samples inside an exposure (None: two nominal periods).
    """

    mode: BlurMode = BlurMode.DEFAULT
    point_px: tuple[float, float] | None = None
    roi: Roi | None = None
    grid: tuple[int, int] = (16, 12)
    rolling_shutter: bool = False
    max_gap_ns: int | None = None

    def __post_init__(self) -> None:
        if self.mode is BlurMode.POINT and self.point_px is None:
            raise QualityInputError("BlurMode.POINT needs point_px=(x_px, y_px)")
        if len(self.grid) != 2 or min(self.grid) < 1:
            raise QualityInputError(f"grid must be (columns, rows), each >= 1, got {self.grid}")
        if self.max_gap_ns is not None and self.max_gap_ns <= 0:
            raise QualityInputError(f"max_gap_ns must be positive or None, got {self.max_gap_ns}")


@dataclass(frozen=True, slots=True)
class BlurEstimate:
    """Blur of one frame.

    ``blur_px`` is the path length (eq. 2) summarised per the mode; ``dx_px``/``dy_px`` the
    net displacement (x right, y down) of the same point (MEAN: averaged over the grid), so a
    back-and-forth shake has a long path and a small net. ``direction_rad`` is the axis of
    the dominant motion, in [0, pi) from +x towards +y, and ``anisotropy`` in [0, 1] how
    line-like the path is (1: one straight direction, 0: none dominates). ``x_px``/``y_px``
    is where it was measured (MAX: the worst grid point; MEAN: the grid's centre).
    """

    blur_px: float
    dx_px: float
    dy_px: float
    direction_rad: float
    anisotropy: float
    x_px: float
    y_px: float
    mode: BlurMode


DEFAULT_OPTIONS = BlurOptions()


@dataclass(frozen=True, slots=True, eq=False)
class _Plan:
    """Everything about a (camera, options) pair that does not change from frame to frame."""

    points_px: Floats  # (2, P)
    rays: Floats  # (3, P): (x, y, 1) in normalised camera coordinates
    row_offsets_ns: npt.NDArray[np.int64]  # (P,)
    rolling: bool
    centre_only: bool
    anchor_px: tuple[float, float]  # reported position for MEAN
    rotation5: Floats  # gyro-to-camera rows x y z x y, see DUPLICATED_ROWS
    focal_px: Floats  # (2, 1): fx, fy as a column
    projection: Floats  # the constant of project_optical_axis
    mode: BlurMode


@lru_cache(maxsize=64)
def _plan(camera: CameraModel, options: BlurOptions) -> _Plan:
    mode = options.mode
    if mode is BlurMode.CENTER:
        xs, ys = np.array([camera.cx_px]), np.array([camera.cy_px])
        anchor = (camera.cx_px, camera.cy_px)
    elif mode is BlurMode.POINT:
        assert options.point_px is not None  # checked by BlurOptions
        xs, ys = np.array([options.point_px[0]]), np.array([options.point_px[1]])
        anchor = options.point_px
    else:
        roi = options.roi or Roi(0.0, 0.0, float(camera.width_px), float(camera.height_px))
        cols, rows = options.grid
        gx = roi.x_px + (np.arange(cols) + 0.5) * (roi.width_px / cols)
        gy = roi.y_px + (np.arange(rows) + 0.5) * (roi.height_px / rows)
        mesh_x, mesh_y = np.meshgrid(gx, gy)
        xs, ys = mesh_x.ravel(), mesh_y.ravel()
        anchor = (roi.x_px + roi.width_px / 2, roi.y_px + roi.height_px / 2)
    rays = np.stack(
        [(xs - camera.cx_px) / camera.fx_px, (ys - camera.cy_px) / camera.fy_px, np.ones_like(xs)]
    )
    rolling = options.rolling_shutter and camera.line_readout_ns > 0
    offsets = np.rint(ys * camera.line_readout_ns).astype(np.int64)
    return _Plan(
        points_px=np.stack([xs, ys]),
        rays=rays,
        row_offsets_ns=offsets if rolling else np.zeros(xs.size, np.int64),
        rolling=rolling,
        centre_only=mode is BlurMode.CENTER and not rolling,
        anchor_px=(float(anchor[0]), float(anchor[1])),
        rotation5=camera.rotation_gyro_to_camera[list(DUPLICATED_ROWS)],
        focal_px=np.array([[camera.fx_px], [camera.fy_px]]),
        projection=axis_projection(camera.fx_px, camera.fy_px),
        mode=mode,
    )


# The mediator passes the same camera and options for every frame: an identity check is
# cheaper than hashing both for the cache. One tuple, replaced whole, so threads are safe.
_LAST_PLAN: tuple[CameraModel, BlurOptions, _Plan] | None = None


def _plan_for(camera: CameraModel, options: BlurOptions) -> _Plan:
    global _LAST_PLAN
    last = _LAST_PLAN
    if last is not None and last[0] is camera and last[1] is options:
        return last[2]
    plan = _plan(camera, options)
    _LAST_PLAN = (camera, options, plan)
    return plan


def estimate_blur(
    gyro: GyroSamples,
    exposure: Exposure,
    camera: CameraModel,
    options: BlurOptions = DEFAULT_OPTIONS,
) -> BlurEstimate:
    """Blur of a frame exposed over ``exposure`` (camera clock) from ``gyro`` samples.

    Raises CoverageError when the samples do not cover the exposure shifted to the gyro
    clock by ``camera.gyro_time_offset_ns``. ``blur_px`` is inf if the camera turned
    about 90 degrees or more during the exposure.
    """
    plan = _plan_for(camera, options)
    offset_ns = camera.gyro_time_offset_ns
    start_ns = exposure.start_ns + offset_ns
    duration_ns = exposure.duration_ns
    if plan.rolling:
        starts = start_ns + plan.row_offsets_ns
        first, last = int(starts.min()), int(starts.max()) + duration_ns
    else:
        first, last = start_ns, start_ns + duration_ns
    span = covering(gyro, first, last, options.max_gap_ns, exposure, offset_ns)
    if duration_ns == 0:
        x_px, y_px = plan.anchor_px if plan.mode is BlurMode.MEAN else plan.points_px[:, 0]
        return _estimate(0.0, 0.0, 0.0, _NO_MOTION, float(x_px), float(y_px), plan.mode)
    t_ns = gyro.t_ns[span]
    # Rates in the camera frame, component-first: (5, M), rows x y z x y.
    rates5 = plan.rotation5.dot(gyro.rates_rad_s[span].T)
    if plan.rolling:
        return _rolling(t_ns, rates5, starts, duration_ns, plan)
    theta = cumulative_rotation(window_increments(t_ns, rates5, first, last))
    if plan.centre_only:
        return _centre(*project_optical_axis(theta, plan.projection), plan)
    return _points(np.matmul(inverse_rotation_matrices(theta), plan.rays), plan, None, None)


_NO_MOTION = np.zeros((2, 2))


def _centre(offsets_px: Floats, depth: Floats, plan: _Plan) -> BlurEstimate:
    """The paper's estimate: length of the optical axis' path (2, K) in the image, eq. 2."""
    x_px, y_px = plan.anchor_px
    # Python's min over a short list beats a numpy reduction's fixed cost.
    if min(depth.tolist()) <= _MIN_DEPTH:
        return _estimate(math.inf, math.nan, math.nan, _NO_MOTION, x_px, y_px, plan.mode)
    steps = offsets_px[:, 1:] - offsets_px[:, :-1]
    blur = float(sum(np.hypot(steps[0], steps[1]).tolist()))
    # Knot 0 is the principal point itself, so the last offset is the net displacement.
    dx_px, dy_px = offsets_px[:, -1].tolist()
    return _estimate(blur, dx_px, dy_px, steps.dot(steps.T), x_px, y_px, plan.mode)


def _rolling(
    t_ns: npt.NDArray[np.int64],
    rates5: Floats,
    starts_ns: npt.NDArray[np.int64],
    duration_ns: int,
    plan: _Plan,
) -> BlurEstimate:
    """Every point over its own row's window; knots are all window ends and samples."""
    ends_ns = starts_ns + duration_ns
    knots = np.unique(np.concatenate([t_ns[1:-1], starts_ns, ends_ns]))
    theta = cumulative_rotation(knot_increments(t_ns, rates5, knots))
    inverse = inverse_rotation_matrices(theta)
    first = np.searchsorted(knots, starts_ns)
    last = np.searchsorted(knots, ends_ns)
    # Each pixel's ray at its own exposure start, expressed at knot 0: Exp(theta) = inverse^T.
    world = (inverse[first] * plan.rays.T[:, :, None]).sum(axis=1)  # (P, 3)
    return _points(np.matmul(inverse, world.T), plan, first, last)


def _points(
    rays: Floats,
    plan: _Plan,
    first: npt.NDArray[np.intp] | None,
    last: npt.NDArray[np.intp] | None,
) -> BlurEstimate:
    """Paths of tracked rays (K, 3, P), each between its own knots (None: all of them)."""
    depth = rays[:, 2, :]
    image = rays[:, :2, :] / depth[:, None, :]  # (K, 2, P)
    steps = (image[1:] - image[:-1]) * plan.focal_px
    if first is None or last is None:
        inside = np.ones(depth.shape, dtype=bool)
        net = (image[-1] - image[0]) * plan.focal_px
    else:
        knot = np.arange(depth.shape[0])[:, None]
        inside = (knot >= first) & (knot <= last)
        # where, not a product: outside a pixel's window a turned ray may project to inf.
        steps = np.where((inside[1:] & inside[:-1])[:, None, :], steps, 0.0)
        points = np.arange(depth.shape[1])
        net = (image[last, :, points] - image[first, :, points]).T * plan.focal_px
    blur = np.sqrt((steps * steps).sum(axis=1)).sum(axis=0)
    turned = ((depth <= _MIN_DEPTH) & inside).any(axis=0)
    if bool(turned.any()):
        blur[turned] = math.inf
        net[:, turned] = math.nan
    if plan.mode is BlurMode.MEAN:
        mean_net = net.mean(axis=1)
        x_px, y_px = plan.anchor_px
        moments = np.tensordot(steps, steps, axes=([0, 2], [0, 2]))
        return _estimate(
            float(blur.mean()),
            float(mean_net[0]),
            float(mean_net[1]),
            moments,
            x_px,
            y_px,
            plan.mode,
        )
    # POINT has one point; MAX reports its worst one.
    index = int(np.argmax(blur))
    one = steps[:, :, index]
    return _estimate(
        float(blur[index]),
        float(net[0, index]),
        float(net[1, index]),
        one.T @ one,
        float(plan.points_px[0, index]),
        float(plan.points_px[1, index]),
        plan.mode,
    )


def _estimate(
    blur_px: float,
    dx_px: float,
    dy_px: float,
    moments: Floats,
    x_px: float,
    y_px: float,
    mode: BlurMode,
) -> BlurEstimate:
    """Assemble the result; direction and anisotropy from the 2x2 second moments of steps."""
    (xx, xy), (_, yy) = moments.tolist()
    energy = xx + yy
    if energy > 0.0 and math.isfinite(blur_px):
        direction = 0.5 * math.atan2(2.0 * xy, xx - yy)
        if direction < 0.0:
            direction += math.pi
        if direction >= math.pi:
            # -1e-17 + pi rounds to pi: that axis is the x axis.
            direction = 0.0
        anisotropy = min(math.hypot(xx - yy, 2.0 * xy) / energy, 1.0)
    else:
        direction, anisotropy = 0.0, 0.0
    return BlurEstimate(blur_px, dx_px, dy_px, direction, anisotropy, x_px, y_px, mode)
