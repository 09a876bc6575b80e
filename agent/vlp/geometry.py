"""From image pixels to level rays: undistortion, and the camera's tilt taken out (tilt compensation).

A pixel (u, v) becomes normalised camera coordinates (x, y) = ((u - cx) / fx, (v - cy) / fy), undistorted
with OpenCV's model when the camera has distortion. The ray m = (x, y, 1) in the camera frame is turned into
the camera's *level* frame (z vertical, x and y turned by the camera yaw only) by R_level; an LED at height h
above the lens then lies at horizontal offset h * (m_x / m_z, m_y / m_z) in that frame. With no tilt this is
exactly the model of ``reference/vlp.md`` §1.5 that the renderer draws: u = cx + f (d . x_c) / h.

Rotations: R_world_camera = Rz(psi_base) Ry(pitch_b) Rx(roll_b) Rz(yaw_m) Ry(pitch_m) Rx(roll_m), base tilt
(IMU) and mount tilt (calibration), so R_level = Rz(-yaw_m) Ry(pitch_b) Rx(roll_b) Rz(yaw_m) Ry(pitch_m)
Rx(roll_m) and the camera's level yaw is psi_base + yaw_m.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt

from agent.vlp.model import CameraIntrinsics, CameraMount, Tilt

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "lens_offset_level",
    "level_plane_coordinates",
    "level_plane_points",
    "level_rotation",
    "normalised_coordinates",
]

_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-12)


def _rx(a: float) -> FloatArray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(a: float) -> FloatArray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rz(a: float) -> FloatArray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def level_rotation(mount: CameraMount, tilt: Tilt | None = None) -> FloatArray:
    """R_level = Rz(-yaw_m) Ry(pitch_b) Rx(roll_b) Rz(yaw_m) Ry(pitch_m) Rx(roll_m) (3x3)."""
    r_mount = _ry(mount.pitch_rad) @ _rx(mount.roll_rad)
    if tilt is None or (tilt.roll_rad == 0.0 and tilt.pitch_rad == 0.0):
        return r_mount
    r_base = _ry(tilt.pitch_rad) @ _rx(tilt.roll_rad)
    result: FloatArray = _rz(-mount.yaw_rad) @ r_base @ _rz(mount.yaw_rad) @ r_mount
    return result


def lens_offset_level(mount: CameraMount, tilt: Tilt | None = None) -> FloatArray:
    """The lens relative to the base origin in the base's level frame (x along the base yaw), metres:
    Ry(pitch_b) Rx(roll_b) (x_m, y_m, z_m). A tilted base moves the lens sideways by z_m sin(tilt)."""
    offset = np.array([mount.x_m, mount.y_m, mount.z_m])
    if tilt is None:
        return offset
    result: FloatArray = _ry(tilt.pitch_rad) @ _rx(tilt.roll_rad) @ offset
    return result


def normalised_coordinates(uv_px: FloatArray, intrinsics: CameraIntrinsics) -> FloatArray:
    """Undistorted normalised camera coordinates (x, y) of output pixels ``uv_px`` (shape (n, 2))."""
    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    xy = np.empty_like(uv)
    xy[:, 0] = (uv[:, 0] - intrinsics.cx_px) / intrinsics.fx_px
    xy[:, 1] = (uv[:, 1] - intrinsics.cy_px) / intrinsics.fy_px
    if any(k != 0.0 for k in intrinsics.distortion) and len(xy):
        eye = np.eye(3)
        dist = np.asarray(intrinsics.distortion, dtype=np.float64)
        # K = I: the points are already normalised; the result stays normalised (R = P = I).
        out = cv2.undistortPointsIter(xy.reshape(-1, 1, 2), eye, dist, eye, eye, _UNDISTORT_CRITERIA)
        xy = np.asarray(out, dtype=np.float64).reshape(-1, 2)
    return xy


def level_plane_coordinates(xy: FloatArray, r_level: FloatArray) -> FloatArray:
    """q = (m'_x / m'_z, m'_y / m'_z) with m' = R_level (x, y, 1): a point at height h above the lens and
    horizontal offset d (in the camera's level yaw frame) has q = d / h."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    m = r_level[:, 0:1].T * xy[:, 0:1] + r_level[:, 1:2].T * xy[:, 1:2] + r_level[:, 2]
    q: FloatArray = m[:, :2] / m[:, 2:3]
    return q


def level_plane_points(
    uv_px: list[tuple[float, float]], intrinsics: CameraIntrinsics, r_level: FloatArray
) -> list[tuple[float, float]]:
    """``level_plane_coordinates(normalised_coordinates(uv_px))`` for a few points, as plain floats.

    Without distortion each point is x = (u - cx) / fx, y = (v - cy) / fy, m = R_level (x, y, 1),
    q = (m_x / m_z, m_y / m_z): a dozen float operations, done here without building arrays (the same
    operations in the same order, so the same numbers). With distortion the undistortion goes through
    OpenCV as in :func:`normalised_coordinates`.
    """
    if not uv_px:
        return []
    if any(k != 0.0 for k in intrinsics.distortion):
        q = level_plane_coordinates(normalised_coordinates(np.array(uv_px), intrinsics), r_level)
        return [(a, b) for a, b in q.tolist()]
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = r_level.tolist()
    cx, cy, fx, fy = intrinsics.cx_px, intrinsics.cy_px, intrinsics.fx_px, intrinsics.fy_px
    out = []
    for u, v in uv_px:
        x = (u - cx) / fx
        y = (v - cy) / fy
        mz = r20 * x + r21 * y + r22
        out.append(((r00 * x + r01 * y + r02) / mz, (r10 * x + r11 * y + r12) / mz))
    return out
