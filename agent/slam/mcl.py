"""Localization only, on a saved map: Monte Carlo localization (Dellaert, Fox, Burgard, Thrun 1999) with
the same improved proposal as the SLAM filter, against one fixed distance field.

It is the RBPF with the map frozen: per update each particle is moved by odometry, scan-matched and
sampled around the match (``agent.slam.proposal``; pending absolute fixes, ``agent.slam.fix``, join that
proposal as they do in the SLAM filter), weighted, and resampled when N_eff drops. Sweeps are de-skewed
and pose jumps in the odometry dropped, as in the SLAM filter. Nothing is written to the map, so the
field is computed once, for the whole map, when the localizer is made.

Global initialization is from an absolute fix (VLP): the particles are drawn from the fix's Gaussian;
when the fix has no heading, headings are spread evenly over the circle and scan matching picks the ones
that fit. Until then scans are not used.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from agent.slam.fix import PoseFix, fuse_fixes, pending_fixes_log_likelihood
from agent.slam.grid import prepare_scan
from agent.slam.matcher import DistanceField
from agent.slam.motion import OdometryNoise, sample_motion
from agent.slam.pose import between, compose, inverse, wrap_angle
from agent.slam.proposal import ProposalConfig, improved_proposal, scan_normals
from agent.slam.rbpf import (
    FilterStats,
    StepKind,
    StepResult,
    sweep_offsets,
    systematic_resample,
    voxel_indices,
)
from agent.slam.render import OccupancyImage
from agent.slam.scan import LaserGeometry, Rejection, ScanGate

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MclConfig:
    """Localization runs denser updates than mapping (0.1 m / 0.1 rad: it is cheap, nothing is
    integrated) and no correlative search by default (particles may be far apart after a global start)."""

    particles: int = 100
    noise: OdometryNoise = field(default_factory=OdometryNoise)
    proposal: ProposalConfig = field(default_factory=lambda: ProposalConfig(search=None))
    linear_update_m: float = 0.1
    angular_update_rad: float = 0.1
    resample_threshold: float = 0.5
    min_range_m: float = 0.1
    max_usable_range_m: float = 5.5
    match_voxel_m: float = 0.1
    max_match_points: int = 200
    seed: int = 0


class MclLocalizer:
    """Particles on a fixed occupancy map (a map_server image)."""

    def __init__(
        self, laser: LaserGeometry, occupancy: OccupancyImage, config: MclConfig | None = None
    ) -> None:
        self.laser = laser
        self.config = config or MclConfig()
        cfg = self.config
        if occupancy.origin[2] != 0.0:
            raise ValueError("maps with a rotated origin are not supported")
        self.rng = np.random.default_rng(cfg.seed)
        self.gate = ScanGate(laser)
        # map_server images have row 0 at the top; the field wants row 0 at the lowest y.
        obstacles = occupancy.occupied_mask()[::-1]
        cap = max(max(stage[0] for stage in cfg.proposal.matcher.stages), cfg.proposal.outlier_m)
        # No ``known`` cells here, unlike the SLAM filter: a saved map is whole, so an endpoint off it is
        # evidence against the pose (an outlier), not the edge of a map still being built; scored as
        # "unknown" it would let particles walk off the map (a heading turned round in a corridor did).
        self.field = DistanceField.from_obstacles(
            np.ascontiguousarray(obstacles)[None, :, :],
            (occupancy.origin[0], occupancy.origin[1]),
            occupancy.resolution_m,
            cap + occupancy.resolution_m,
        )
        self.resolution_m = occupancy.resolution_m
        self.poses: FloatArray = np.zeros((cfg.particles, 3))
        self.log_weights: FloatArray = np.zeros(cfg.particles)
        self.initialized = False
        self._force_update = False
        self._update_odom: FloatArray | None = None
        self._last_odom: FloatArray | None = None  # odometry of the last accepted scan (de-skewing)
        self._pending_fixes: list[tuple[PoseFix, FloatArray]] = []
        self.stats = FilterStats()

    @property
    def weights(self) -> FloatArray:
        w = np.exp(self.log_weights - self.log_weights.max())
        normalised: FloatArray = w / w.sum()
        return normalised

    def initialize(self, fix: PoseFix, odom_pose: FloatArray) -> None:
        """Global initialization: particles drawn from the fix (x, y ~ N(z, R); yaw from the fix, or
        evenly over the circle when it has none)."""
        n = self.config.particles
        cov = np.asarray(fix.covariance, dtype=np.float64)
        xy = self.rng.multivariate_normal([fix.x_m, fix.y_m], cov[:2, :2], size=n)
        if fix.yaw_rad is None:
            yaw = (np.arange(n) + self.rng.random()) * (2.0 * math.pi / n) - math.pi
        else:
            yaw = fix.yaw_rad + self.rng.standard_normal(n) * math.sqrt(cov[2, 2])
        self.poses = np.column_stack([xy, wrap_angle(yaw)])
        self.log_weights = np.zeros(n)
        self._update_odom = np.asarray(odom_pose, dtype=np.float64).copy()
        self._force_update = True
        self.initialized = True

    def add_fix(self, fix: PoseFix, odom_pose: FloatArray) -> None:
        """Queue a fix taken when odometry read ``odom_pose``; it weighs the particles at the next update."""
        self._pending_fixes.append((fix, np.asarray(odom_pose, dtype=np.float64).copy()))

    def pose(self, odom_pose: FloatArray | None = None) -> FloatArray:
        """Weighted mean pose (circular mean for yaw), moved on by odometry since the last update."""
        w = self.weights
        mean = np.array(
            [
                w @ self.poses[:, 0],
                w @ self.poses[:, 1],
                math.atan2(w @ np.sin(self.poses[:, 2]), w @ np.cos(self.poses[:, 2])),
            ]
        )
        if odom_pose is None or self._update_odom is None:
            return mean
        return compose(mean, between(self._update_odom, odom_pose))

    def spread_m(self) -> float:
        """Weighted RMS distance of the particles from the mean position."""
        w = self.weights
        mean = self.pose()
        d2 = (self.poses[:, 0] - mean[0]) ** 2 + (self.poses[:, 1] - mean[1]) ** 2
        return float(math.sqrt(w @ d2))

    def process(self, t_s: float, ranges_m: FloatArray, odom_pose: FloatArray) -> StepResult:
        cfg = self.config
        self.stats.scans += 1
        odom = np.asarray(odom_pose, dtype=np.float64)
        rejection = self.gate.check(t_s, np.asarray(ranges_m), odom)
        if not self.initialized:
            return StepResult(StepKind.UNINITIALIZED, np.full(3, np.nan), rejection)
        assert self._update_odom is not None
        if rejection is not None:
            if rejection is Rejection.POSE_JUMP and self._last_odom is not None:
                # As the SLAM filter: keep the motion up to the last good scan, drop the jump itself.
                travelled = between(self._update_odom, self._last_odom)
                self._update_odom = compose(odom, inverse(travelled))
                self._last_odom = odom
            return StepResult(StepKind.REJECTED, self.pose(self._last_odom), rejection)
        beam_offsets = None
        if self._last_odom is not None and self.gate.previous_t_s is not None:
            beam_offsets = sweep_offsets(
                self.laser, t_s - self.gate.previous_t_s, between(self._last_odom, odom)
            )
        self._last_odom = odom
        increment = between(self._update_odom, odom)
        if (
            not self._force_update
            and math.hypot(increment[0], increment[1]) < cfg.linear_update_m
            and abs(increment[2]) < cfg.angular_update_rad
        ):
            return StepResult(StepKind.GATED, self.pose(odom))
        self._force_update = False
        scan = prepare_scan(
            ranges_m,
            self.laser.angles_rad,
            self.laser.mount,
            max(self.laser.min_range_m, cfg.min_range_m),
            self.laser.no_return_m,
            cfg.max_usable_range_m,
            self.resolution_m / 2.0,
            beam_offsets,
        )
        kept = voxel_indices(scan.hit_xy, cfg.match_voxel_m, cfg.max_match_points)
        points = scan.hit_xy[kept]
        normals = None if cfg.proposal.along_surface_weight == 1.0 else scan_normals(scan, kept, cfg.proposal)
        window_index = np.zeros(cfg.particles, dtype=np.int64)
        fixes_weighted = False
        if points.shape[0] < cfg.proposal.matcher.min_inliers:
            self.poses = sample_motion(self.poses, increment, cfg.noise, self.rng)
            matched = np.zeros(cfg.particles, dtype=bool)
        else:
            measurement = None
            if self._pending_fixes:
                # The fixes join the proposal, as in the SLAM filter (agent.slam.proposal).
                heading = float(compose(self.pose(), increment)[2])
                measurement = fuse_fixes(self._pending_fixes, odom, cfg.noise, heading)
                fixes_weighted = True
            result = improved_proposal(
                self.field,
                window_index,
                points,
                self.poses,
                increment,
                cfg.noise,
                cfg.proposal,
                self.rng,
                self.log_weights,
                normals,
                measurement,
            )
            self.poses = result.poses
            self.log_weights = self.log_weights + result.log_eta
            matched = result.matched
        self.stats.match_failures += int(np.count_nonzero(~matched))
        if self._pending_fixes:
            if not fixes_weighted:
                self.log_weights = self.log_weights + pending_fixes_log_likelihood(
                    self.poses, self._pending_fixes, odom, cfg.noise
                )
            self.stats.fixes_applied += len(self._pending_fixes)
            self._pending_fixes.clear()
        self.log_weights -= self.log_weights.max()
        w = self.weights
        n_eff = float(1.0 / np.sum(w * w))
        self.stats.n_eff.append(n_eff)
        resampled = n_eff < cfg.resample_threshold * cfg.particles
        if resampled:
            parents: IntArray = systematic_resample(w, self.rng)
            self.poses = self.poses[parents]
            self.log_weights = np.zeros(cfg.particles)
            self.stats.resamples += 1
        self._update_odom = odom
        self.stats.updates += 1
        return StepResult(
            StepKind.UPDATED, self.pose(), None, n_eff, resampled, int(np.count_nonzero(matched))
        )
