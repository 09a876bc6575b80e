"""VLP fixes for a simulated drive from the real camera pipeline: rendered frames through ``agent.vlp``.

:class:`PipelineFixes` is a :class:`agent.slam.simlog.FixSource`. Each time it is asked (10 times a
simulated second by default) it renders the frame whose readout has just ended (the rolling-shutter
renderer of ``drivers.sim``, the robot's true motion during the readout, the world's realistic errors:
principal point, LED survey, camera tilt), runs it through one :class:`~agent.vlp.pipeline.VlpPipeline`
that tracks the LEDs from frame to frame, as the robot's camera loop does, and hands the fix on with the
covariance the agent fuses (the solver's, plus ``[vlp] sigma_floor_*``). Degraded fixes (one LED, a
large residual) are left out, as SLAM anchors only on clean ones.

The pipeline gets the pose prior the agent would give it (an office repeats LED ids, which only a prior
tells apart): the last fix carried forward by the wheel odometry since, its uncertainty growing with the
distance rolled; before the first fix, the world's start pose (the agent's ``[fusion] initial_pose``
under ``[sim]``).

It lives with the commands because it joins two packages that do not import each other (the VLP
pipeline and the SLAM filter's simulated logs).
"""

from __future__ import annotations

import collections
import math

import numpy as np
import numpy.typing as npt

from agent.config import VlpConfig
from agent.sim_view import agent_view
from agent.slam.fix import PoseFix
from agent.slam.pose import between, compose
from agent.vlp.model import PosePrior, VlpFix
from agent.vlp.pipeline import VlpPipeline
from drivers.sim.render import RollingShutterRenderer
from drivers.sim.simulation import Simulation
from drivers.sim.world import World

__all__ = ["PipelineFixes"]

FloatArray = npt.NDArray[np.float64]

# The prior's spread: at an anchor (a fix, or the start pose), and growth per metre of odometry since.
_PRIOR_SIGMA_XY_M = 0.1
_PRIOR_SIGMA_XY_PER_M = 0.05
_PRIOR_SIGMA_YAW_RAD = math.radians(5.0)
_PRIOR_SIGMA_YAW_PER_M = math.radians(3.0)


class PipelineFixes:
    """Fixes from rendered frames through the VLP pipeline (see the module docstring)."""

    def __init__(
        self, world: World, *, rate_hz: float = 10.0, seed: int = 0, vlp: VlpConfig | None = None
    ) -> None:
        if not rate_hz > 0.0:
            raise ValueError(f"rate_hz must be positive, not {rate_hz}")
        vlp = vlp or VlpConfig()
        view = agent_view(world)
        self.rate_hz = rate_hz
        self.renderer = RollingShutterRenderer.for_world(world, seed=seed)
        self.pipeline = VlpPipeline(view.intrinsics, view.led_map, view.mount)
        self.floor = np.diag([vlp.sigma_floor_m**2, vlp.sigma_floor_m**2, vlp.sigma_floor_yaw_rad**2])
        self._rng = np.random.default_rng(seed)
        self._frame = np.empty((world.camera.output_height_px, world.camera.output_width_px), dtype=np.uint8)
        start = world.robot.start
        # (anchor pose in the world, odometry pose there; None: odometry's first pose, not seen yet).
        self._anchor: tuple[FloatArray, FloatArray | None] = (
            np.array([start.x_m, start.y_m, start.yaw_rad]),
            None,
        )
        self.frames = 0
        self.degraded = 0
        self.reasons: collections.Counter[str] = collections.Counter()

    def _prior(self, odometry: FloatArray) -> PosePrior:
        anchor, odometry_then = self._anchor
        if odometry_then is None:
            odometry_then = odometry.copy()
            self._anchor = (anchor, odometry_then)
        moved = between(odometry_then, odometry)
        x, y, yaw = compose(anchor, moved)
        rolled = math.hypot(float(moved[0]), float(moved[1]))
        return PosePrior(
            float(x),
            float(y),
            float(yaw),
            _PRIOR_SIGMA_XY_M + _PRIOR_SIGMA_XY_PER_M * rolled,
            _PRIOR_SIGMA_YAW_RAD + _PRIOR_SIGMA_YAW_PER_M * rolled,
        )

    def __call__(self, sim: Simulation, t_s: float, odometry: FloatArray) -> tuple[float, PoseFix, int] | str:
        self.frames += 1
        # The newest frame complete by t_s, its start a random part of a millisecond earlier (the camera
        # runs unsynchronised with the simulation's ticks and with the LEDs).
        t0 = t_s - self.renderer.readout_s - float(self._rng.uniform(0.0, 1e-3))
        rendered = self.renderer.render(sim.pose_at, t0, out=self._frame)
        result = self.pipeline.process(rendered.image, rendered.truth.t_mid_s, prior=self._prior(odometry))
        if not isinstance(result, VlpFix):
            self.reasons[result.reason] += 1
            return result.reason
        if result.degraded:
            self.degraded += 1
            reason = "degraded: " + ", ".join(result.flags)
            self.reasons[reason] += 1
            return reason
        self._anchor = (np.array([result.x_m, result.y_m, result.yaw_rad]), odometry.copy())
        covariance = np.array(result.covariance, dtype=np.float64) + self.floor
        fix = PoseFix(result.x_m, result.y_m, result.yaw_rad, covariance)
        return result.time_s, fix, len(result.ids)
