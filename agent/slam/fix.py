"""Absolute pose fixes (VLP) as measurements in a particle filter's weights.

A fix z = (x, y[, yaw]) with covariance R, taken when odometry read o_fix, weighs each particle i at a
later filter update (odometry o_t) by the Gaussian likelihood

    w_i *= N(z; x_i ⊕ (o_fix⁻¹ ⊕ o_t)⁻¹, R + Q)

i.e. the particle is moved back along the odometry to the fix's time (with its own heading, so a fix
without yaw is handled exactly) and Q, the motion model's covariance for that stretch, widens R. Q is
the model's spread without its floor (``OdometryNoise.spread``): a fix taken 2 cm before the scan is
widened by what 2 cm of odometry can err, not by the 5 mm floor that keeps one update's motion density
proper (with the floor, every fused office fix was claimed >= 5 mm per axis whatever it was: its
normalised error 1.25 against 3 expected; docs/slam.md, "VLP fixes: the carried covariance").
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


@dataclass(frozen=True)
class TimedFix:
    """A fix with the time it was taken and the odometry pose of the base at that time."""

    t_s: float
    fix: PoseFix
    odom_pose: FloatArray


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
        total += fix_log_likelihood(at_fix_time, fix, np.diag(noise.spread(moved) ** 2))
    return total


@dataclass(frozen=True)
class PoseMeasurement:
    """A Gaussian measurement of the current pose: ``mean`` (x, y, yaw) and ``information`` (3x3, inverse
    covariance; a zero yaw row and column for a position-only measurement)."""

    mean: FloatArray
    information: FloatArray

    def log_likelihood(self, poses: FloatArray) -> FloatArray:
        """-1/2 eᵀ I e for poses (..., 3), e = pose - mean with yaw wrapped."""
        err = np.asarray(poses, dtype=np.float64) - self.mean
        err[..., 2] = wrap_angle(err[..., 2])
        out: FloatArray = -0.5 * np.einsum("...i,ij,...j->...", err, self.information, err)
        return out


def fuse_fixes(
    fixes: list[tuple[PoseFix, FloatArray]], odom_now: FloatArray, noise: OdometryNoise, heading_rad: float
) -> PoseMeasurement:
    """The fixes [(fix, odometry at the fix)] carried forward by odometry to now, as one measurement of the
    current pose, so that a particle filter's proposal can use them (not only its weights).

    Each fix z is moved on by the odometry since, m = o_fix⁻¹ ⊕ o_now: z' = z ⊕ m (a fix without yaw uses
    ``heading_rad`` - m_yaw as its heading, the filter's own). Its covariance is the fix's carried
    through that composition, J R Jᵀ (J = d(z ⊕ m)/dz: the yaw error swings the motion's lever arm),
    plus the motion's own noise Q(m) rotated into the world (``OdometryNoise.spread``: no floor, so a
    fix taken at the scan's odometry is not widened at all). Fixes taken within one filter update share
    most of their odometry, so their errors are not independent: the fused covariance is
    (sum_i (J_i R_i J_iᵀ)⁻¹)⁻¹ + mean_i Q_i (the fixes' own noise averages down, the odometry's does not),
    around the information-weighted mean of the z'_i.
    """
    if not fixes:
        raise ValueError("no fixes to fuse")
    means = []
    fix_information = np.zeros((3, 3))
    weighted = np.zeros(3)
    odometry_cov = np.zeros((3, 3))
    reference_yaw: float | None = None
    for fix, odom_at_fix in fixes:
        moved = between(odom_at_fix, odom_now)
        has_yaw = fix.yaw_rad is not None
        yaw = float(fix.yaw_rad) if fix.yaw_rad is not None else float(heading_rad - moved[2])
        forwarded = compose(np.array([fix.x_m, fix.y_m, yaw]), moved)
        c, s = np.cos(yaw), np.sin(yaw)
        jac = np.array(
            [[1.0, 0.0, -s * moved[0] - c * moved[1]], [0.0, 1.0, c * moved[0] - s * moved[1]], [0, 0, 1]]
        )
        cov = np.asarray(fix.covariance, dtype=np.float64)
        if has_yaw:
            carried = jac @ cov @ jac.T
            info = np.linalg.inv(carried)
        else:
            info = np.zeros((3, 3))
            info[:2, :2] = np.linalg.inv(cov[:2, :2])
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        odometry_cov += rot @ np.diag(noise.spread(moved) ** 2) @ rot.T
        if reference_yaw is None:
            reference_yaw = float(forwarded[2])
        forwarded[2] = reference_yaw + float(wrap_angle(forwarded[2] - reference_yaw))
        means.append(forwarded)
        fix_information += info
        weighted += info @ forwarded
    yaw_known = fix_information[2, 2] > 0.0
    dims = 3 if yaw_known else 2
    fused_cov = np.linalg.inv(fix_information[:dims, :dims])
    mean = np.zeros(3)
    mean[:dims] = fused_cov @ weighted[:dims]
    if not yaw_known:
        mean[2] = means[-1][2]
    total_cov = fused_cov + (odometry_cov / len(fixes))[:dims, :dims]
    information = np.zeros((3, 3))
    information[:dims, :dims] = np.linalg.inv(total_cov)
    mean[2] = float(wrap_angle(mean[2]))
    return PoseMeasurement(mean, information)
