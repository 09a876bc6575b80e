"""GMapping's odometry motion model (``gridfastslam/motionmodel.cpp``, ``drawFromMotion``).

The odometry increment u = (dx, dy, dyaw) = odom_{t-1}⁻¹ ⊕ odom_t is perturbed per axis with standard
deviations that grow with the motion:

    sigma_x   = srr |dx| + str |dyaw| + 0.3 srr |dy|
    sigma_y   = srr |dy| + str |dyaw| + 0.3 srr |dx|
    sigma_yaw = stt |dyaw| + srt sqrt(dx^2 + dy^2)

so, as in GMapping's code, ``srt`` scales rotation noise per metre travelled and ``str`` translation noise
per radian turned. The new pose is x_{t-1} ⊕ (u + noise). A small floor keeps the density proper when the
robot has barely moved. :meth:`OdometryNoise.spread` is the same without the floor: the odometry's own
error over a stretch, which is zero over no motion (``agent.slam.fix`` carries a VLP fix forward by it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from agent.slam.pose import between, compose, wrap_angle

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class OdometryNoise:
    """GMapping's names and ROS defaults (slam_gmapping: srr 0.1, srt 0.2, str 0.1, stt 0.2)."""

    srr: float = 0.1
    srt: float = 0.2
    str: float = 0.1
    stt: float = 0.2
    floor_m: float = 0.005
    floor_rad: float = 0.002

    def sigmas(self, increment: FloatArray) -> FloatArray:
        """(sigma_x_m, sigma_y_m, sigma_yaw_rad) for an increment (..., 3): :meth:`spread`, floored."""
        floor = np.array([self.floor_m, self.floor_m, self.floor_rad])
        sigmas: FloatArray = np.maximum(self.spread(increment), floor)
        return sigmas

    def spread(self, increment: FloatArray) -> FloatArray:
        """:meth:`sigmas` without the floor (..., 3): zero for no motion. The floor is for one filter
        update's motion density; the error odometry adds in carrying a measurement over a stretch (a VLP
        fix taken a few centimetres before the scan) has none."""
        dx, dy, dyaw = np.abs(increment[..., 0]), np.abs(increment[..., 1]), np.abs(increment[..., 2])
        sx = self.srr * dx + self.str * dyaw + 0.3 * self.srr * dy
        sy = self.srr * dy + self.str * dyaw + 0.3 * self.srr * dx
        syaw = self.stt * dyaw + self.srt * np.hypot(dx, dy)
        return np.stack([sx, sy, syaw], axis=-1)


def sample_motion(
    poses: FloatArray, increment: FloatArray, noise: OdometryNoise, rng: np.random.Generator
) -> FloatArray:
    """x_t = x_{t-1} ⊕ (u + e), e ~ N(0, diag(sigma(u)^2)), one draw per pose (P, 3)."""
    sig = noise.sigmas(increment)
    noisy = increment[None, :] + rng.standard_normal((poses.shape[0], 3)) * sig[None, :]
    return compose(poses, noisy)


def motion_log_density(
    previous: FloatArray, candidates: FloatArray, increment: FloatArray, noise: OdometryNoise
) -> FloatArray:
    """log p(x_t | x_{t-1}, u) up to a constant for candidates (P, K, 3) from previous poses (P, 3):
    -1/2 sum_k ((x_{t-1}⁻¹ ⊕ x_t - u)_k / sigma_k)^2."""
    rel = between(previous[:, None, :], candidates)
    err = rel - increment[None, None, :]
    err[..., 2] = wrap_angle(err[..., 2])
    sig = noise.sigmas(increment)
    out: FloatArray = -0.5 * np.sum((err / sig) ** 2, axis=-1)
    return out
