"""SE(2) poses as numpy arrays ``[..., 3] = (x_m, y_m, yaw_rad)``, vectorised over leading axes.

A pose ``a`` maps points from its local frame to the parent frame: ``p_parent = R(yaw_a) p_local + t_a``.
``compose(a, b)`` is ``a ⊕ b`` (b expressed in a's frame, result in a's parent frame) and
``between(a, b) = a⁻¹ ⊕ b`` is the motion from a to b seen from a, the quantity odometry reports.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


def wrap_angle(angle_rad: npt.ArrayLike) -> FloatArray:
    """Angles folded into [-pi, pi)."""
    a = np.asarray(angle_rad, dtype=np.float64)
    wrapped: FloatArray = (a + np.pi) % (2.0 * np.pi) - np.pi
    return wrapped


def compose(a: npt.ArrayLike, b: npt.ArrayLike) -> FloatArray:
    """a ⊕ b: x = x_a + cos(yaw_a) x_b - sin(yaw_a) y_b, y = y_a + sin(yaw_a) x_b + cos(yaw_a) y_b,
    yaw = yaw_a + yaw_b."""
    pa = np.asarray(a, dtype=np.float64)
    pb = np.asarray(b, dtype=np.float64)
    c, s = np.cos(pa[..., 2]), np.sin(pa[..., 2])
    x = pa[..., 0] + c * pb[..., 0] - s * pb[..., 1]
    y = pa[..., 1] + s * pb[..., 0] + c * pb[..., 1]
    return np.stack([x, y, wrap_angle(pa[..., 2] + pb[..., 2])], axis=-1)


def inverse(a: npt.ArrayLike) -> FloatArray:
    """a⁻¹: (-R(yaw)ᵀ t, -yaw)."""
    pa = np.asarray(a, dtype=np.float64)
    c, s = np.cos(pa[..., 2]), np.sin(pa[..., 2])
    x = -(c * pa[..., 0] + s * pa[..., 1])
    y = -(-s * pa[..., 0] + c * pa[..., 1])
    return np.stack([x, y, wrap_angle(-pa[..., 2])], axis=-1)


def between(a: npt.ArrayLike, b: npt.ArrayLike) -> FloatArray:
    """a⁻¹ ⊕ b: the relative pose of b in a's frame."""
    pa = np.asarray(a, dtype=np.float64)
    pb = np.asarray(b, dtype=np.float64)
    c, s = np.cos(pa[..., 2]), np.sin(pa[..., 2])
    dx = pb[..., 0] - pa[..., 0]
    dy = pb[..., 1] - pa[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(pb[..., 2] - pa[..., 2])], axis=-1)


def _transformed_xy(pose: npt.ArrayLike, points_xy: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """The parent-frame x and y (..., N) of points (..., N, 2) in the frames of poses (..., 3)."""
    p = np.asarray(pose, dtype=np.float64)
    q = np.asarray(points_xy, dtype=np.float64)
    c = np.cos(p[..., 2])[..., None]
    s = np.sin(p[..., 2])[..., None]
    x = p[..., 0][..., None] + c * q[..., 0] - s * q[..., 1]
    y = p[..., 1][..., None] + s * q[..., 0] + c * q[..., 1]
    return x, y


def transform_points(pose: npt.ArrayLike, points_xy: npt.ArrayLike) -> FloatArray:
    """Points (..., N, 2) in the pose's frame -> parent frame, for poses of shape (..., 3)."""
    return np.stack(_transformed_xy(pose, points_xy), axis=-1)


def transform_bounds(pose: npt.ArrayLike, points_xy: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """The (x, y) minimum and maximum of :func:`transform_points` (pose, points_xy) over all poses and
    points, bit for bit: x and y are computed as there but reduced apart, not stacked into (..., N, 2)
    pairs first (a min over the first axis of pairs runs an inner loop of two elements per row)."""
    x, y = _transformed_xy(pose, points_xy)
    return np.array([x.min(), y.min()]), np.array([x.max(), y.max()])
