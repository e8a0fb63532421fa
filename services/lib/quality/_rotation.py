"""Vectorised integration of gyro rates into camera rotations.

The rates are taken as piecewise linear between samples, so the rotation vector gained over
any sub-interval is exact by the trapezoid rule, and an exposure boundary falling between two
samples is handled by interpolation, never by rounding to a sample.

Composing the per-interval rotations exactly needs a sequential product (a Python loop per
frame). Instead the rotation since the first knot is kept as one rotation vector, summed with
the second-order Baker-Campbell-Hausdorff term:

    theta_{k+1} = theta_k + delta_k + 1/2 theta_k x delta_k

with theta_k inside the cross product replaced by the plain running sum. This is exact
whenever the rotation axis is fixed (all analytic cases: constant yaw, pitch, roll, or a fixed
oblique axis, at any angle); when the axis wanders the error is third order in the total
angle, about |theta|^3 / 12 rad: 0.2 rad of shake (3.3 rad/s over 60 ms) gives <= 7e-4 rad,
0.4 px at f = 558 px on a blur of ~110 px.

Arrays are laid out component-first, (3, K), so each component is a contiguous row. Rates and
increments carry five rows, x y z x y (``DUPLICATED_ROWS``), so a cross product is two
products of slices instead of six of rows: with ~30 knots per frame, per-call numpy overhead,
not arithmetic, is what costs here (hence also ``a.dot(b)``, which skips the dispatch of
``np.dot``).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

Floats = npt.NDArray[np.float64]
Ints = npt.NDArray[np.int64]

DUPLICATED_ROWS = (0, 1, 2, 0, 1)
"""Rows of a rotation applied to rates so they come out as x y z x y."""

_ONES3 = np.ones(3)

# Keeps |theta| > 0 so sin(a)/a needs no branch; far below any real angle squared.
_TINY_ANGLE2 = 1e-300


def window_increments(t_ns: Ints, rates: Floats, start_ns: int, end_ns: int) -> Floats:
    """Rotation-vector increments over one window inside the samples.

    ``t_ns`` (M,) must start at or before ``start_ns`` and end at or after ``end_ns``, with
    every other sample strictly inside (the slice ``covering`` returns). ``rates`` (R, M),
    any number of rows. The knots are the window ends and the samples between them;
    returns d (R, M-1), the increment over each knot interval.
    """
    times = t_ns.tolist()
    t0, t1, t_before, t_last = times[0], times[1], times[-2], times[-1]
    # Fractions of the end points inside their sample intervals.
    f_start = (start_ns - t0) / (t1 - t0)
    f_end = (end_ns - t_before) / (t_last - t_before)
    right = (t_ns[1:] - t_ns[:-1]) * 5e-10
    left = right.copy()
    if right.size == 1:
        # Both ends inside one sample interval.
        length = (end_ns - start_ns) * 5e-10
        left[0] = (2.0 - f_start - f_end) * length
        right[0] = (f_start + f_end) * length
    else:
        # Trapezoids with the interpolated end rates, written as weights on the samples.
        first = (t1 - start_ns) * 5e-10
        last = (end_ns - t_before) * 5e-10
        left[0] = (1.0 - f_start) * first
        right[0] = (1.0 + f_start) * first
        left[-1] = (2.0 - f_end) * last
        right[-1] = f_end * last
    increments: Floats = rates[:, :-1] * left + rates[:, 1:] * right
    return increments


def knot_increments(t_ns: Ints, rates: Floats, knots: Ints) -> Floats:
    """Rotation-vector increments between sorted ``knots`` (K,) inside the samples.

    Every sample strictly inside the knots' span must itself be a knot, so each knot
    interval lies inside one sample interval. ``rates`` (R, M); returns (R, K-1).
    """
    seg = np.searchsorted(t_ns, knots[:-1], side="right") - 1
    t0 = t_ns[seg]
    step = (t_ns[seg + 1] - t0).astype(np.float64)
    fa = (knots[:-1] - t0) / step
    fb = (knots[1:] - t0) / step
    half_s = (knots[1:] - knots[:-1]) * 5e-10
    left: Floats = (2.0 - fa - fb) * half_s
    right: Floats = (fa + fb) * half_s
    return rates[:, seg] * left + rates[:, seg + 1] * right


def _strictly_upper(size: int) -> Floats:
    """(size, size + 1) ones above the diagonal: d @ it is a running sum led by a zero."""
    global _UPPER
    upper = _UPPER  # one read, so a concurrent grow cannot hand us a smaller array
    if upper.shape[0] < size:
        upper = _UPPER = np.triu(np.ones((2 * size, 2 * size + 1)), 1)
    return upper[:size, : size + 1]


_UPPER = np.triu(np.ones((128, 129)), 1)


def cumulative_rotation(d5: Floats) -> Floats:
    """Rotation vectors (3, K) at each knot since the first, from x y z x y increments (5, K-1).

    Running sums are products with a triangular matrix of ones: one BLAS call is cheaper
    here than cumsum plus the copies around it.
    """
    count = d5.shape[1]
    running: Floats = d5.dot(_strictly_upper(count))
    # BCH term: theta_{k+1} gains 1/2 sum_{j<=k} theta_j x d_j (theta_0 = 0 adds nothing).
    prev = running[:, 1:-1]
    nxt = d5[:, 1:]
    cross = prev[1:4] * nxt[2:5] - prev[2:5] * nxt[1:4]
    cross *= 0.5
    theta = running[:3]
    theta[:, 1:] += cross.dot(_strictly_upper(count - 1))
    return theta


def _terms(theta: Floats) -> tuple[Floats, Floats, Floats]:
    """cos|t|, sin|t|/|t| and (1 - cos|t|)/|t|^2 for Rodrigues' formula, branch-free."""
    angle2 = _ONES3.dot(theta * theta) + _TINY_ANGLE2
    angle = np.sqrt(angle2)
    cos = np.cos(angle)
    # 1 - cos loses relative precision for tiny angles, but the term it scales is then of
    # order |t|^2, so the absolute error of the rotation stays at rounding level.
    return cos, np.sin(angle) / angle, (1.0 - cos) / angle2


def inverse_rotation_matrices(theta: Floats) -> Floats:
    """Exp(-theta_k) as (K, 3, 3): maps a direction fixed at knot 0 into the frame at knot k."""
    cos, sinc, h = _terms(theta)
    ht = h * theta
    m = ht[:, None, :] * theta[None, :, :]
    st = sinc * theta
    m[0, 0] += cos
    m[1, 1] += cos
    m[2, 2] += cos
    m[0, 1] += st[2]
    m[1, 0] -= st[2]
    m[0, 2] -= st[1]
    m[2, 0] += st[1]
    m[1, 2] += st[0]
    m[2, 1] -= st[0]
    # Knot-first so np.matmul treats it as a stack of matrices (much faster than einsum).
    return np.ascontiguousarray(m.transpose(2, 0, 1))


def axis_projection(fx_px: float, fy_px: float) -> Floats:
    """The constant ``project_optical_axis`` needs for a camera, computed once per camera."""
    # Rows: x offset, y offset, depth; columns: the rows of ``terms`` below.
    return np.array(
        [
            [0.5 * fx_px, 0.0, 0.0, 0.0, -fx_px, 0.0, 0.0],
            [0.0, 0.5 * fy_px, 0.0, fy_px, 0.0, 0.0, 0.0],
            [0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 1.0],
        ]
    )


def project_optical_axis(theta: Floats, projection: Floats) -> tuple[Floats, Floats]:
    """Where the ray through the principal point at knot 0 is seen at each knot.

    Returns its image offsets from the principal point, (2, K) in pixels, and a depth (K,)
    whose sign is that of the ray's z (it is behind the camera when <= 0). ``projection``
    comes from ``axis_projection``. With the Gibbs vector g = tan(|t|/2) t/|t|,
    Exp(-theta) (0, 0, 1) is proportional to (2 (gx gz - gy), 2 (gy gz + gx),
    1 - gx^2 - gy^2 + gz^2): one trigonometric call instead of three. With h = 2 g that is
    (hx hz / 2 - hy, hy hz / 2 + hx, 1 - tan^2(|t|/2) + hz^2 / 2), one matrix product of
    ``projection`` with the stacked terms (hz h, h, 1 - tan^2).
    """
    half_angle = np.sqrt(_QUARTERS.dot(theta * theta) + _TINY_ANGLE2)
    tan = np.tan(half_angle)
    terms = np.empty((7, theta.shape[1]))
    h = np.multiply(theta, tan / half_angle, out=terms[3:6])
    np.multiply(h, h[2], out=terms[0:3])
    np.subtract(1.0, tan * tan, out=terms[6])
    image = projection.dot(terms)
    depth = image[2]
    return image[:2] / depth, depth


# |theta|^2 / 4 as a dot product.
_QUARTERS = np.full(3, 0.25)
