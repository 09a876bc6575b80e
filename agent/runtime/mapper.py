"""Laser scans + odometry -> a pose (and a map): the :class:`ScanMapper` protocol and its adapters.

The SLAM thread feeds every scan with the odometry pose at the scan's time and fuses the pose of each
*filter update* (between updates a filter only composes odometry, which the fusion has already);
absolute fixes (VLP) are passed in so that everything stays in the map frame of the LED survey.

* :class:`RbpfMapper` (``[slam] mode = "mapping"``) adapts ``agent.slam.rbpf.RbpfSlam``; it starts its map
  at the fused pose of the first scan, so the occupancy grid, the VLP fixes and the pose output share one
  frame. With ``mode = "continue"`` the filter starts from the saved map ``[slam] map`` (lifelong mapping):
  the saved map is in the same frame (it was made in it), the robot's start pose is the fused one
  (``fusion.initial_pose`` or the first VLP fixes), and the first filter update's search matches the first
  scan against the saved walls.
* :class:`MclMapper` (``mode = "localization"``) adapts ``agent.slam.mcl.MclLocalizer`` on a saved map
  (ROS map_server files, ``agent.slam.mapio``); its particles start from the fused pose once that is known.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import numpy.typing as npt

from agent.config_slam import MountConfig, SlamConfig, SlamMode
from agent.runtime.types import AbsoluteFix
from drivers.samples import Scan

if TYPE_CHECKING:
    from agent.slam.render import MapPath

__all__ = [
    "MapperStep",
    "MclMapper",
    "RbpfMapper",
    "ScanMapper",
    "front_end_filter",
    "front_end_log_odds",
    "front_end_noise",
    "front_end_proposal",
    "make_local_mapper",
    "prior_log_odds",
    "save_final_map",
    "save_map",
    "tidy_map_folder",
]

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
Pose = tuple[float, float, float]
# Filter updates of trajectory history the RBPF keeps (for the trajectory plot): bounded, so that a service
# running for days does not grow; at one update per 0.25 m that is the last 1.25 km.
_HISTORY_UPDATES = 5000


def front_end_proposal(config: SlamConfig, base: Any) -> Any:
    """``base`` (an ``agent.slam.proposal.ProposalConfig``) with the scan match's front end the ``[slam]``
    keys set (``along_surface_weight``, ``degenerate_noise_scale``, ``match_*`` (``match_gate_residual``:
    ``MatcherConfig.gate_on_residual``; ``match_min_translation_information``:
    ``MatcherConfig.min_translation_information``; ``match_medial_window_cells``:
    ``MatcherConfig.medial_window_cells``; ``match_iterations``: ``MatcherConfig.stages``' iterations),
    ``normal_radius_per_m``, ``normal_thickness_m``,
    ``failed_match_draw``,
    ``search_yaw_rad``). The agent's filters are built with it, and so is what ``vlp-agent eval slam`` runs
    for each source (``eval_slam.front_end``): what was measured is what runs."""
    import dataclasses

    matcher = dataclasses.replace(
        base.matcher,
        min_inliers=config.match_min_inliers,
        min_inlier_fraction=config.match_min_inlier_fraction,
        gate_on_residual=config.match_gate_residual,
        min_translation_information=config.match_min_translation_information,
        medial_window_cells=config.match_medial_window_cells,
        stages=_stages_with(base.matcher.stages, config.match_iterations),
    )
    return dataclasses.replace(
        base,
        matcher=matcher,
        along_surface_weight=config.along_surface_weight,
        normal_radius_per_m=config.normal_radius_per_m,
        normal_thickness_m=config.normal_thickness_m,
        degenerate_noise_scale=config.degenerate_noise_scale,
        keep_better_start=config.match_both_starts,
        failed_match_draw=config.failed_match_draw,
        search=None
        if base.search is None
        else dataclasses.replace(base.search, yaw_range_rad=config.search_yaw_rad),
    )


def _stages_with(
    stages: tuple[tuple[float, int], ...], iterations: tuple[int, ...]
) -> tuple[tuple[float, int], ...]:
    """The matcher's ``stages`` (bound, iterations) with the iterations ``[slam] match_iterations`` sets."""
    if len(stages) != len(iterations):
        raise ValueError(f"match_iterations names {len(iterations)} stages, the matcher has {len(stages)}")
    return tuple((bound, count) for (bound, _), count in zip(stages, iterations, strict=True))


def front_end_filter(config: SlamConfig, base_proposal: Any) -> dict[str, Any]:
    """The ``agent.slam.rbpf.RbpfConfig`` fields the ``[slam]`` front-end keys set: ``noise``,
    ``free_margin_m``, ``grid_phase_from_walls``, ``log_odds``, ``search_increment_rad``,
    ``search_below_inliers``, ``shared_field_updates``, ``reversal_ratio``, ``proposal``
    (``base_proposal`` with the match's keys, ``front_end_proposal``) and ``loop_closure`` (the default
    loop closure with ``loop_correction_odometry_sigmas``, ``loop_accept_graph_chi2``,
    ``loop_snap_forward_m`` and ``loop_final_scan_chain``).
    The agent's mapping filter and ``vlp-agent eval slam`` are both configured with it."""
    from agent.slam.loops import LoopClosureConfig
    from agent.slam.scan_chain import ScanChainConfig

    return {
        "loop_closure": LoopClosureConfig(
            correction_odometry_sigmas=config.loop_correction_odometry_sigmas,
            accept_graph_chi2=config.loop_accept_graph_chi2,
            snap_forward_m=config.loop_snap_forward_m,
            final_scan_chain=ScanChainConfig() if config.loop_final_scan_chain else None,
        ),
        "noise": front_end_noise(config),
        "free_margin_m": config.free_margin_m,
        "grid_phase_from_walls": config.grid_phase_from_walls,
        "log_odds": front_end_log_odds(config),
        "search_increment_rad": config.search_increment_rad,
        "search_below_inliers": config.search_below_inliers,
        "shared_field_updates": config.shared_field_updates,
        "reversal_ratio": config.reversal_ratio,
        "proposal": front_end_proposal(config, base_proposal),
    }


def front_end_log_odds(config: SlamConfig) -> Any:
    """The grid's inverse sensor model (``agent.slam.grid.LogOddsModel``) for ``[slam] miss_log_odds``."""
    from agent.slam.grid import LogOddsModel

    return LogOddsModel(miss=config.miss_log_odds)


def front_end_noise(config: SlamConfig) -> Any:
    """The filter's motion model (``agent.slam.motion.OdometryNoise``) for ``[slam] odometry_noise``:
    slam_gmapping's when the key is not set."""
    from agent.slam.motion import OdometryNoise

    if config.odometry_noise is None:
        return OdometryNoise()
    srr, srt, str_, stt = config.odometry_noise
    return OdometryNoise(srr, srt, str_, stt)


@dataclass(frozen=True, slots=True)
class MapperStep:
    """What one scan did: ``kind`` is the filter's word (``updated``, ``gated``, ``first``, ``rejected``,
    ``waiting``); ``fix`` is the pose to fuse (filter updates only); ``reason`` why a scan was turned away;
    ``stopped``: turned away (``rejected``) because the agent is stopping, so the filter never took it or
    left its update unfinished: no input of the run's filter (a replay does not feed it)."""

    kind: str
    fix: AbsoluteFix | None = None
    reason: str = ""
    matched: bool = True
    stopped: bool = False


class ScanMapper(Protocol):
    """Anything that builds a map from scans. Called from the SLAM thread only."""

    name: str

    def update(self, scan: Scan, odom_pose: Pose) -> MapperStep: ...

    def add_fix(self, fix: AbsoluteFix, odom_pose: Pose) -> None: ...

    def pose(self, odom_pose: Pose | None = None) -> Pose | None: ...

    def map_image(self) -> Any | None: ...

    def trajectory(self) -> FloatArray: ...

    def counters(self) -> dict[str, int]: ...

    def begin_stop(self) -> None:
        """The agent is stopping (from the thread that stops it, while the SLAM thread may be in an
        update; returns at once): a mapper that can leave a long update does so now. What is asked after
        (the final map) is still answered."""

    def finish(self) -> bool:
        """The final optimisation before the final map is taken (after the stop): True if it ran and the
        map and trajectory changed with it (``RbpfSlam.finish``; off with ``[slam]
        loop_final_scan_chain = false``)."""

    def close(self) -> None: ...


class RbpfMapper:
    """``agent.slam.rbpf.RbpfSlam`` behind :class:`ScanMapper`.

    ``start_pose(t_ns)``: the fused pose at a scan's time, where the map starts (None: not known well
    enough yet; the scan is skipped as ``waiting``). ``floor``: a lower bound on the pose covariance, since
    the particle spread alone is optimistic (the filter was fed the same VLP fixes the fusion has).
    """

    name = "slam"

    def __init__(
        self,
        config: SlamConfig,
        mount: MountConfig,
        start_pose: Callable[[int], Pose | None],
    ) -> None:
        from agent.slam import rbpf

        self._rbpf = rbpf
        self.config = config
        self.mount = (mount.x_m, mount.y_m, mount.yaw_rad)
        self.start_pose = start_pose
        self.slam: Any = None
        self.floor = np.diag([config.sigma_xy_m**2, config.sigma_xy_m**2, config.sigma_yaw_rad**2])
        self._counts: dict[str, int] = {}
        # Between the stages of an update the filter lets the hot path go first (Agent sets this).
        self.give_way: Callable[[], None] = lambda: None
        self.prior: tuple[FloatArray, tuple[float, float]] | None = None
        if config.mode is SlamMode.CONTINUE:
            if config.map is None:
                raise ValueError('mode = "continue" needs a map')
            from agent.slam import mapio
            from agent.slam.grid import LogOddsModel

            self.prior = prior_log_odds(mapio.load_map(config.map), LogOddsModel())
            log.info("continuing the saved map %s", config.map)

    def _count(self, what: str) -> None:
        self._counts[what] = self._counts.get(what, 0) + 1

    def _start(self, scan: Scan, pose: Pose) -> None:
        from agent.slam.grid import GridGeometry
        from agent.slam.scan import LaserGeometry

        rbpf = self._rbpf
        cfg = self.config
        geometry = LaserGeometry.from_scan(scan, self.mount)
        self.slam = rbpf.RbpfSlam(
            geometry,
            rbpf.RbpfConfig(
                particles=cfg.particles,
                **front_end_filter(cfg, rbpf.RbpfConfig().proposal),
                map_mode=rbpf.MapMode(cfg.map_mode),
                grid=GridGeometry(resolution_m=cfg.resolution_m),
                linear_update_m=cfg.linear_update_m,
                angular_update_rad=cfg.angular_update_rad,
                initial_pose=pose,
                history_limit=_HISTORY_UPDATES,
                seed=cfg.seed,
            ),
        )
        self.slam.give_way = self.give_way
        if self.prior is not None:
            self.slam.seed_map(self.prior[0].astype(np.float32), self.prior[1])
        log.info("SLAM map started at (%.3f, %.3f, %.1f deg)", pose[0], pose[1], math.degrees(pose[2]))

    def update(self, scan: Scan, odom_pose: Pose) -> MapperStep:
        from agent.slam.scan import ranges_from_scan

        if self.slam is None:
            start = self.start_pose(scan.host_time_ns)
            if start is None:
                self._count("waiting")
                return MapperStep("waiting", reason="no fused pose to start the map at yet")
            self._start(scan, start)
        rbpf = self._rbpf
        step = self.slam.process(scan.host_time_ns * 1e-9, ranges_from_scan(scan), np.asarray(odom_pose))
        kind = str(step.kind.value)
        self._count(kind)
        if step.kind is rbpf.StepKind.REJECTED:
            return MapperStep(kind, reason=str(step.rejection.value if step.rejection else "rejected"))
        if step.kind is not rbpf.StepKind.UPDATED:
            return MapperStep(kind)
        matched = step.matched > 0
        if not matched:
            self._count("unmatched_updates")
            return MapperStep(kind, matched=False)
        pose = step.pose
        cov = self._particle_covariance(pose) + self.floor
        fix = AbsoluteFix(
            scan.host_time_ns,
            float(pose[0]),
            float(pose[1]),
            float(pose[2]),
            cov,
            detail={"n_eff": step.n_eff, "matched": step.matched, "resampled": step.resampled},
        )
        return MapperStep(kind, fix)

    def _particle_covariance(self, best: FloatArray) -> FloatArray:
        """Weighted covariance of the particles around the best one (yaw differences wrapped)."""
        poses = self.slam.poses
        w = self.slam.weights
        d = poses - best[None, :]
        d[:, 2] = (d[:, 2] + math.pi) % (2.0 * math.pi) - math.pi
        cov: FloatArray = (w[:, None] * d).T @ d
        return cov

    def add_fix(self, fix: AbsoluteFix, odom_pose: Pose) -> None:
        if self.slam is None:
            return
        self.slam.add_fix(_pose_fix(fix), np.asarray(odom_pose))
        self._count("fixes")

    def pose(self, odom_pose: Pose | None = None) -> Pose | None:
        if self.slam is None:
            return None
        p = self.slam.pose(None if odom_pose is None else np.asarray(odom_pose))
        return float(p[0]), float(p[1]), float(p[2])

    def map_image(self) -> Any | None:
        """The best particle's map as an ``agent.slam.render.OccupancyImage`` (None before the first scan)."""
        if self.slam is None:
            return None
        from agent.slam.render import occupancy_image

        window = self.slam.map_window()
        if window is None:
            return None
        log_odds, origin = window
        return occupancy_image(log_odds, origin, self.config.resolution_m)

    def trajectory(self) -> FloatArray:
        if self.slam is None:
            return np.zeros((0, 3))
        _, poses, _ = self.slam.trajectory()
        out: FloatArray = np.asarray(poses, dtype=np.float64)
        return out

    def counters(self) -> dict[str, int]:
        out = dict(self._counts)
        if self.slam is not None:
            out["filter_updates"] = int(self.slam.stats.updates)
            out["resamples"] = int(self.slam.stats.resamples)
            out["fixes_applied"] = int(self.slam.stats.fixes_applied)
            out["map_bytes"] = int(self.slam.memory_bytes())
            out["loop_closures"] = int(self.slam.stats.loop_closures)
            out["loop_rebuilds"] = int(self.slam.stats.loop_rebuilds)
            out["loop_ms"] = round(self.slam.stats.loop_ms)
            # The final optimisation's steps measured scan to scan (-1: it has not run).
            out["final_scan_edges"] = int(self.slam.stats.final_scan_edges)
        return out

    def begin_stop(self) -> None:
        """Nothing to do: the SLAM thread's update runs to its end, and the agent's join waits for it."""

    def finish(self) -> bool:
        """The filter's final optimisation (``RbpfSlam.finish``): the pose graph with its chain measured scan
        to scan and every loop link, the history, particles and map put on it. Not without a loop link
        (nothing to gain), with ``loop_final_scan_chain = false``, or once the history was cut
        (``_HISTORY_UPDATES``). The filter may go on after it."""
        return self.slam is not None and bool(self.slam.finish())

    def close(self) -> None:
        """Nothing to release (the filter lives in this process)."""


def prior_log_odds(image: Any, model: Any) -> tuple[FloatArray, tuple[float, float]]:
    """A saved map (``OccupancyImage``) as log-odds to seed the filter with (rows = y) and the world xy of
    its first cell's corner: occupied cells at the model's upper limit, free at its lower one (a cell seen
    often enough to be saved as such), unknown 0. A rotated map (origin yaw != 0) is refused."""
    if abs(image.origin[2]) > 1e-9:
        raise ValueError(
            f"a saved map with a rotated origin (yaw {image.origin[2]:g} rad) cannot be continued"
        )
    p = (255.0 - image.pixels.astype(np.float64)) / 255.0
    log_odds = np.zeros(image.pixels.shape, dtype=np.float64)
    log_odds[p < image.free_thresh] = model.minimum
    log_odds[p > image.occupied_thresh] = model.maximum
    return np.ascontiguousarray(log_odds[::-1]), (float(image.origin[0]), float(image.origin[1]))


def _pose_fix(fix: AbsoluteFix) -> Any:
    from agent.slam.fix import PoseFix

    cov = np.asarray(fix.covariance[:2, :2] if fix.yaw_rad is None else fix.covariance, dtype=np.float64)
    return PoseFix(fix.x_m, fix.y_m, fix.yaw_rad, 0.5 * (cov + cov.T))


class MclMapper:
    """``agent.slam.mcl.MclLocalizer`` on a saved map behind :class:`ScanMapper`: localization only.

    The particles are drawn around the fused pose (``start_pose``) at the first scan after it is known;
    the pose of each filter update is fused like the SLAM pose, with the particle spread as its covariance.
    """

    name = "mcl"

    def __init__(
        self, config: SlamConfig, mount: MountConfig, start_pose: Callable[[int], Pose | None]
    ) -> None:
        from agent.slam import mapio, mcl, rbpf

        if config.map is None:
            raise ValueError("localization needs a map")
        self._mcl = mcl
        self._rbpf = rbpf
        self.config = config
        self.mount = (mount.x_m, mount.y_m, mount.yaw_rad)
        self.start_pose = start_pose
        self.occupancy = mapio.load_map(config.map)
        self.localizer: Any = None
        self.floor = np.diag([config.sigma_xy_m**2, config.sigma_xy_m**2, config.sigma_yaw_rad**2])
        self._counts: dict[str, int] = {}

    def _count(self, what: str) -> None:
        self._counts[what] = self._counts.get(what, 0) + 1

    def update(self, scan: Scan, odom_pose: Pose) -> MapperStep:
        from agent.slam.scan import LaserGeometry, ranges_from_scan

        mcl, rbpf = self._mcl, self._rbpf
        if self.localizer is None:
            self.localizer = mcl.MclLocalizer(
                LaserGeometry.from_scan(scan, self.mount),
                self.occupancy,
                mcl.MclConfig(
                    particles=max(self.config.particles, 30),
                    noise=front_end_noise(self.config),
                    proposal=front_end_proposal(self.config, mcl.MclConfig().proposal),
                    seed=self.config.seed,
                ),
            )
        if not self.localizer.initialized:
            start = self.start_pose(scan.host_time_ns)
            if start is None:
                self._count("waiting")
                return MapperStep("waiting", reason="no fused pose to start the particles from yet")
            cov = np.diag([0.1**2, 0.1**2, math.radians(5.0) ** 2])
            self.localizer.initialize(rbpf.PoseFix(*start, cov), np.asarray(odom_pose))
        step = self.localizer.process(scan.host_time_ns * 1e-9, ranges_from_scan(scan), np.asarray(odom_pose))
        kind = str(step.kind.value)
        self._count(kind)
        if step.kind is not rbpf.StepKind.UPDATED:
            reason = str(step.rejection.value) if step.rejection is not None else ""
            return MapperStep(kind, reason=reason)
        if step.matched <= 0:
            self._count("unmatched_updates")
            return MapperStep(kind, matched=False)
        pose = self.localizer.pose()
        d = self.localizer.poses - pose[None, :]
        d[:, 2] = (d[:, 2] + math.pi) % (2.0 * math.pi) - math.pi
        cov = (self.localizer.weights[:, None] * d).T @ d + self.floor
        fix = AbsoluteFix(scan.host_time_ns, float(pose[0]), float(pose[1]), float(pose[2]), cov)
        return MapperStep(kind, fix)

    def add_fix(self, fix: AbsoluteFix, odom_pose: Pose) -> None:
        if self.localizer is not None and self.localizer.initialized:
            self.localizer.add_fix(_pose_fix(fix), np.asarray(odom_pose))
            self._count("fixes")

    def pose(self, odom_pose: Pose | None = None) -> Pose | None:
        if self.localizer is None or not self.localizer.initialized:
            return None
        p = self.localizer.pose(None if odom_pose is None else np.asarray(odom_pose))
        return float(p[0]), float(p[1]), float(p[2])

    def map_image(self) -> Any | None:
        return self.occupancy

    def trajectory(self) -> FloatArray:
        return np.zeros((0, 3))

    def counters(self) -> dict[str, int]:
        out = dict(self._counts)
        if self.localizer is not None:
            out["filter_updates"] = int(self.localizer.stats.updates)
            out["fixes_applied"] = int(self.localizer.stats.fixes_applied)
        return out

    def begin_stop(self) -> None:
        """Nothing to do: the SLAM thread's update runs to its end, and the agent's join waits for it."""

    def finish(self) -> bool:
        """Nothing to optimise: the map is the saved one, localization only."""
        return False

    def close(self) -> None:
        """Nothing to release (the filter lives in this process)."""


def make_local_mapper(
    config: SlamConfig, mount: MountConfig, start_pose: Callable[[int], Pose | None]
) -> tuple[ScanMapper | None, str]:
    """The laser localizer for this config in this process (mapping or localization on a map), or None and
    the reason it is not available. ``agent.runtime.slam_factory.make_mapper`` picks between this and the
    child process (``config.process``); the child builds its filter with this."""
    if not config.enabled:
        return None, "disabled in the config"
    try:
        if config.mode is SlamMode.LOCALIZATION:
            return MclMapper(config, mount, start_pose), ""
        return RbpfMapper(config, mount, start_pose), ""
    except ImportError as exc:
        return None, f"the SLAM package is not usable: {exc}"
    except ValueError as exc:
        return None, str(exc)


def save_map(
    mapper: ScanMapper,
    directory: Path,
    name: str = "map",
    paths: Sequence[MapPath] | None = None,
    title: str = "",
) -> list[Path]:
    """Write the mapper's map as ROS map_server files (``name.yaml`` naming a new ``name.<stamp>.pgm``;
    the pair replaced is kept as ``name.prev.yaml``) and a picture of it for people (``name.png``:
    enlarged, with ``paths`` over it (default: the mapper's own trajectory), axes in metres, a legend and a
    scale bar), atomically. Nothing when there is no map (yet)."""
    # Nothing lost in either case: no map yet (a SLAM process that could not hand its map over has said so
    # itself). Asked before the map: at a stop, a SLAM process without one is not waited for.
    if mapper.counters().get("filter_updates", 0) == 0:
        log.info("no map saved to %s: no filter update yet", directory)
        return []
    image = mapper.map_image()
    if image is None:
        log.info("no map saved to %s: the mapper gave none", directory)
        return []
    from agent import figure
    from agent.slam import mapio
    from agent.slam.render import MapPath, map_picture

    if paths is None:
        paths = [MapPath("SLAM estimate", mapper.trajectory(), figure.SLAM)]
    files = mapio.save_map(image, directory / f"{name}.yaml", comment=f"vlp-agent {mapper.name}")
    picture = map_picture(image, paths, title or f"{name}.png: laser map ({mapper.name})")
    png = mapio.write_png(directory / f"{name}.png", picture)
    return [files.yaml, files.image, png]


def save_final_map(
    mapper: ScanMapper,
    directory: Path,
    name: str = "map",
    paths_for: Callable[[FloatArray], Sequence[MapPath]] | None = None,
    title: str = "",
) -> tuple[list[Path], bool]:
    """The map saved at a stop: first the filter's map as it stands (:func:`save_map`), then the final
    optimisation (:meth:`ScanMapper.finish`) and, where it ran, the optimised map saved over it, the
    filter's own kept beside it as ``name.prev.yaml``. Saving first loses nothing where the optimisation
    is cut short (a SLAM process still at it when the stop's grace runs out is killed, and the map saved
    first stays). ``paths_for``: the paths drawn over the picture for the mapper's trajectory (default:
    that trajectory alone). The files written last, and whether the optimisation ran."""

    def paths() -> Sequence[MapPath] | None:
        return None if paths_for is None else paths_for(mapper.trajectory())

    files = save_map(mapper, directory, name, paths(), title)
    if not files or not mapper.finish():
        return files, False
    # (A map that cannot be taken out after the optimisation leaves the first one on disk, as it was.)
    return save_map(mapper, directory, name, paths(), title) or files, True


def tidy_map_folder(directory: Path, name: str = "map") -> list[Path]:
    """At start: remove what a save killed half-way left in the map folder (see ``mapio.tidy_map_folder``)."""
    from agent.slam import mapio

    return mapio.tidy_map_folder(directory / f"{name}.yaml")
