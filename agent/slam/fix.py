"""Absolute pose fixes (VLP) as measurements in a particle filter's weights.

A fix z = (x, y[, yaw]) with covariance R, taken when odometry read o_fix, weighs each particle i at a
later filter update (odometry o_t) by the Gaussian likelihood

    w_i *= N(z; x_i ⊕ (o_fix⁻¹ ⊕ o_t)⁻¹, R + Q)

i.e. the particle is moved back along the odometry to the fix's time (with its own heading, so a fix
without yaw is handled exactly) and Q, the motion model's covariance for that stretch, widens R.
Because the fixes are in the building's LED frame, particles that drift away from it lose weight: the
map is built in that frame and the drift stays bounded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from agent.slam.motion import OdometryNoise
from agent.slam.pose import between, compose, inverse, wrap_angle

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class PoseFix:
    """An absolute pose measurement of the robot base in the map frame: x, y, optionally yaw, with its
    covariance (2x2 for x, y; 3x3 with yaw; metres and radians)."""

    x_m: float
    y_m: float
    yaw_rad: float | None
    covariance: FloatArray

    def __post_init__(self) -> None:
        n = 2 if self.yaw_rad is None else 3
        cov = np.asarray(self.covariance, dtype=np.float64)
        if cov.shape != (n, n):
            raise ValueError(f"covariance must be {n}x{n} for this fix, got {cov.shape}")
        if not np.allclose(cov, cov.T) or np.any(np.linalg.eigvalsh(cov) <= 0.0):
            raise ValueError("covariance must be symmetric positive definite")

    @property
    def dimension(self) -> int:
        return 2 if self.yaw_rad is None else 3


def fix_log_likelihood(
    poses: FloatArray, fix: PoseFix, extra_covariance: FloatArray | None = None
) -> FloatArray:
    """log N(z; x_i, R + Q) up to a constant for poses (P, 3): -1/2 eᵀ (R + Q)⁻¹ e, e = z - x_i (yaw
    wrapped). ``extra_covariance`` (3x3) is Q; only its x, y block is used for a fix without yaw."""
    n = fix.dimension
    if n == 2:
        err = np.array([fix.x_m, fix.y_m])[None, :] - poses[:, :2]
    else:
        err = np.array([fix.x_m, fix.y_m, fix.yaw_rad])[None, :] - poses
        err[:, 2] = wrap_angle(err[:, 2])
    cov = np.asarray(fix.covariance, dtype=np.float64)
    if extra_covariance is not None:
        cov = cov + extra_covariance[:n, :n]
    out: FloatArray = -0.5 * np.einsum("pi,ij,pj->p", err, np.linalg.inv(cov), err)
    return out


def pending_fixes_log_likelihood(
    poses: FloatArray, fixes: list[tuple[PoseFix, FloatArray]], odom_now: FloatArray, noise: OdometryNoise
) -> FloatArray:
    """Sum of the log-likelihoods of fixes [(fix, odometry at the fix)] for particles at ``poses`` now."""
    total = np.zeros(poses.shape[0])
    for fix, odom_at_fix in fixes:
        moved = between(odom_at_fix, odom_now)
        at_fix_time = compose(poses, inverse(moved)[None, :])
        total += fix_log_likelihood(at_fix_time, fix, np.diag(noise.sigmas(moved) ** 2))
    return total
