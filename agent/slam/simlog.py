"""Laser logs with ground truth from the simulated world: the robot drives the world's route on a fake clock.

:func:`simulate_log` runs a :class:`~drivers.sim.simulation.Simulation` as fast as it goes (no ptys, no
threads: a fake clock advanced in 10 ms ticks), steering along ``world.route`` with the
:class:`~drivers.sim.route.RouteFollower` autopilot from the true pose, and records what the robot would
have logged:

* **Scans** of the world's :class:`~drivers.sim.world.LaserModel` (a URG-04LX by default): each beam is
  cast at its own time of the sweep (``Simulation.laser_ranges_m`` at the pose of the moment; beams are
  cast in chunks small enough that the laser turns < 0.1 deg and moves < 3 mm within one), with the
  model's Gaussian range noise and dropout, rounded to millimetres, out-of-range readings as "no return"
  (0). A scan's timestamp is its last beam, as for the BreezySLAM logs.
* **Wheel odometry** as the robot's own would be, from the simulated wheel angles through a
  :class:`WheelErrorModel`: wheels whose real radii differ from the nominal one, an effective track wider
  than the nominal one (turns are over-counted), random slip growing with the distance rolled, and
  4096-tick encoders, integrated at 100 Hz with the wheel radius and track the robot's odometry uses:
  the nominal ones, or those ``vlp-agent calibrate wheels`` finds for these wheels
  (:func:`wheel_calibration_runs` simulates its manoeuvres; ``calibration.wheels.fit_wheels`` fits them).
  The odometry with the nominal geometry is kept beside it (``SimulatedRun.nominal_odometry``). The
  simulation's truth is untouched.
* **VLP fixes** from a :class:`FixSource`, asked at its rate: the camera pipeline itself on rendered
  frames (``agent.commands.eval_slam`` plugs ``agent.vlp`` and the rolling-shutter renderer in here; this
  package does not import them), or a :class:`VlpFixModel`, a stand-in for it: at 10 Hz, when at least
  two ceiling LEDs project inside the upward camera's sensor at the true pose, the fix is the true base
  pose plus the mean survey error of the LEDs in view (the agent's LED map is the world's, bent by
  ``[errors] led_survey_error_m``) plus Gaussian noise (5 mm per axis, 0.3 deg). Each fix is paired with
  the odometry pose at the fix's own time (interpolated over the last ticks: a camera fix refers to the
  middle of its frame's exposure, before the moment it is asked for).
* **Ground truth**: the true base pose at every scan's timestamp (as the log records' reference pose).

No files, no printing; the randomness is seeded.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

from agent.slam.fix import PoseFix, TimedFix
from agent.slam.logs import LogFormat, LogRecord, SlamLog
from agent.slam.motion import OdometryNoise
from agent.slam.pose import between, compose
from agent.slam.scan import LaserGeometry
from drivers.sim.route import RouteFollower
from drivers.sim.simulation import Simulation
from drivers.sim.world import LaserModel, Led, Pose2D, World
from drivers.sim.worldfile import survey

FloatArray = npt.NDArray[np.float64]

TICK_S = 0.01  # odometry sampling and the fake clock's step
AUTOPILOT_EVERY = 5  # ticks between autopilot commands (20 Hz, as ``vlp-agent sim``)
MAX_CHUNK_YAW_RAD = math.radians(0.1)
MAX_CHUNK_MOVE_M = 0.003


@dataclass(frozen=True)
class WheelErrorModel:
    """How the robot's wheel odometry differs from its true motion.

    ``left_scale`` / ``right_scale``: distance the odometry counts per metre a wheel really rolls (real
    radius against the nominal one). ``track_scale``: the effective track (where the tyres' contact
    patches turn the robot) over the nominal one the odometry divides by; > 1 over-counts turns.
    ``slip_m_per_sqrt_m``: random slip per wheel, a random walk whose standard deviation grows with the
    square root of the distance the wheel rolled. ``ticks_per_turn``: encoder resolution (XL430: 4096)."""

    left_scale: float = 1.006
    right_scale: float = 1.004
    track_scale: float = 1.01
    slip_m_per_sqrt_m: float = 0.002
    ticks_per_turn: int = 4096

    def counted_rad(
        self, rolled_rad: float, scale: float, radius_m: float, rng: np.random.Generator
    ) -> float:
        """What one wheel's encoder counts (rad, before quantization) while it really rolls ``rolled_rad``."""
        slip_m = self.slip_m_per_sqrt_m * math.sqrt(abs(rolled_rad) * radius_m) * rng.standard_normal()
        return rolled_rad * scale + slip_m / radius_m


@dataclass(frozen=True)
class WheelGeometry:
    """The wheel radius and track a robot's odometry computes with."""

    radius_m: float
    track_m: float


def nominal_geometry(world: World, errors: WheelErrorModel) -> WheelGeometry:
    """The design's geometry, which an uncalibrated robot uses: the world's wheel radius (the encoders'
    scale errors stand for the real radii's difference from it) and the effective track over
    ``track_scale``."""
    return WheelGeometry(world.robot.wheel_radius_m, world.robot.track_m / errors.track_scale)


def wheel_calibration_runs(
    world: World,
    errors: WheelErrorModel,
    rng: np.random.Generator,
    distance_m: float = 1.0,
    turns: float = 2.0,
) -> list[tuple[str, float, float, float]]:
    """The manoeuvres of ``vlp-agent calibrate wheels`` done with these wheels, as that step records them:
    ``(kind, left encoder angle rad, right encoder angle rad, measured)`` for a straight run of
    ``distance_m`` forward and one back, and ``turns`` turns in place one way and then the other (the
    step's defaults). The encoders count through the error model (scale and slip) what the wheels really
    roll; the tape measure reads the true distance to the millimetre, the true turn to a tenth of a degree
    (the step's own simulation does the same). Fit them with ``calibration.wheels.fit_wheels``."""
    r, track = world.robot.wheel_radius_m, world.robot.track_m
    runs: list[tuple[str, float, float, float]] = []
    for sign in (1.0, -1.0):
        rolled = sign * distance_m / r
        left = errors.counted_rad(rolled, errors.left_scale, r, rng)
        right = errors.counted_rad(rolled, errors.right_scale, r, rng)
        runs.append(("straight", left, right, round(distance_m, 3)))
    for sign in (1.0, -1.0):
        turned = sign * turns * 2.0 * math.pi
        rolled = turned * track / 2.0 / r  # the right wheel forward for a counter-clockwise turn
        left = errors.counted_rad(-rolled, errors.left_scale, r, rng)
        right = errors.counted_rad(rolled, errors.right_scale, r, rng)
        runs.append(("turn", left, right, math.radians(round(math.degrees(turned), 1))))
    return runs


# The filter's motion model for the simulated robot (GMapping's srr, srt, str, stt). Its odometry
# (WheelErrorModel's defaults) errs by 0.5 % in distance, 0.2 % between the wheels (0.7 deg per metre)
# and 1 % in turns, plus slip; these are three to ten times that. GMapping's defaults (0.1 0.2 0.1 0.2:
# 10 % of the distance, 11 deg per metre) are for a robot whose odometry nobody has looked at: on the
# simulated office they let the particles wander along corridors, where the scans say little about the
# distance driven (docs/slam.md).
MOTION_NOISE = OdometryNoise(0.03, 0.05, 0.03, 0.05)


@dataclass(frozen=True)
class VlpFixModel:
    """Simulated VLP fixes: rate, noise, and the minimum LEDs in the camera's view."""

    rate_hz: float = 10.0
    sigma_xy_m: float = 0.005
    sigma_yaw_rad: float = math.radians(0.3)
    min_leds: int = 2

    def covariance(self) -> FloatArray:
        return np.diag([self.sigma_xy_m**2, self.sigma_xy_m**2, self.sigma_yaw_rad**2])


class FixSource(Protocol):
    """Where a simulated drive's VLP fixes come from. Called ``rate_hz`` times a simulated second with the
    simulation (advanced to ``t_s``) and the robot's odometry pose then (its own frame, as the robot knows
    it); returns (the fix's own time, the fix, LEDs it used), or a reason why there is none."""

    rate_hz: float

    def __call__(
        self, sim: Simulation, t_s: float, odometry: FloatArray
    ) -> tuple[float, PoseFix, int] | str: ...


class _ModelledFixes:
    """A :class:`VlpFixModel` as a :class:`FixSource`: the true pose, the survey error, Gaussian noise."""

    def __init__(self, world: World, model: VlpFixModel, rng: np.random.Generator) -> None:
        self.world = world
        self.model = model
        self.rate_hz = model.rate_hz
        self.rng = rng
        # The agent's LED map is the world's bent by the survey error; a fix inherits the mean error of
        # the LEDs it was solved from (``survey`` is aligned with ``world.leds``; an LED missing from the
        # map adds no survey error).
        self.survey_error_m = np.array(
            [
                (0.0, 0.0) if s is None else (s.x_m - t.x_m, s.y_m - t.y_m)
                for t, s in zip(world.leds, survey(world), strict=True)
            ]
        ).reshape(-1, 2)

    def __call__(self, sim: Simulation, t_s: float, odometry: FloatArray) -> tuple[float, PoseFix, int] | str:
        truth = sim.pose()
        visible = leds_in_view(self.world, truth, self.world.leds)
        if len(visible) < self.model.min_leds:
            return f"fewer than {self.model.min_leds} LEDs in view"
        bias = self.survey_error_m[visible].mean(axis=0)
        m = self.model
        noise = self.rng.standard_normal(3) * np.array([m.sigma_xy_m, m.sigma_xy_m, m.sigma_yaw_rad])
        yaw = math.atan2(math.sin(truth.yaw_rad + noise[2]), math.cos(truth.yaw_rad + noise[2]))
        fix = PoseFix(truth.x_m + bias[0] + noise[0], truth.y_m + bias[1] + noise[1], yaw, m.covariance())
        return t_s, fix, len(visible)


class _OdometryHistory:
    """The odometry pose over the last ``span`` ticks, interpolated at a past time."""

    def __init__(self, span: int = 64) -> None:
        self._times: collections.deque[float] = collections.deque(maxlen=span)
        self._poses: collections.deque[FloatArray] = collections.deque(maxlen=span)

    def add(self, t_s: float, pose: FloatArray) -> None:
        self._times.append(t_s)
        self._poses.append(pose.copy())

    def at(self, t_s: float) -> FloatArray:
        times, poses = self._times, self._poses
        if t_s >= times[-1]:
            return poses[-1].copy()
        if t_s <= times[0]:
            return poses[0].copy()
        i = next(k for k in range(len(times) - 1, 0, -1) if times[k - 1] <= t_s)
        w = (t_s - times[i - 1]) / (times[i] - times[i - 1])
        a, b = poses[i - 1], poses[i]
        dyaw = math.atan2(math.sin(b[2] - a[2]), math.cos(b[2] - a[2]))
        return np.array([a[0] + w * (b[0] - a[0]), a[1] + w * (b[1] - a[1]), a[2] + w * dyaw])


@dataclass(frozen=True)
class SimulatedRun:
    """A log whose records carry the true base pose as their reference pose, with the fixes beside it."""

    log: SlamLog
    fixes: tuple[TimedFix, ...]
    fix_leds: tuple[int, ...]  # LEDs used by each fix
    fix_truth: FloatArray  # (F, 3) the true base pose at each fix's own time
    distance_m: float  # true distance driven
    turned_rad: float  # true heading change, summed in absolute value
    frames_without_fix: int  # camera instants that gave no fix
    no_fix_reasons: dict[str, int]  # why, counted
    # (N, 3) per record: the odometry the same wheels give with the nominal geometry (the records' own
    # is with ``geometry``), and the fixes paired with that odometry
    nominal_odometry: FloatArray
    nominal_fixes: tuple[TimedFix, ...]
    geometry: WheelGeometry

    def with_nominal_odometry(self) -> SlamLog:
        """The log as an uncalibrated robot would have recorded it: the same scans, the same wheel
        readings, odometry computed with the nominal geometry."""
        records = tuple(
            dataclasses.replace(r, odom_pose=pose)
            for r, pose in zip(self.log.records, self.nominal_odometry, strict=True)
        )
        return dataclasses.replace(self.log, records=records)

    @property
    def truth(self) -> FloatArray:
        reference = self.log.reference_poses()
        assert reference is not None
        return reference

    def start_pose(self, from_fix: bool, nominal: bool = False) -> tuple[float, float, float]:
        """Where a filter should start its map: at the first fix carried by odometry to the first scan
        (the LED frame), or, without fixes, at the true start (the only frame there is then).
        ``nominal``: carried by the nominal geometry's odometry (for :meth:`with_nominal_odometry`)."""
        if not from_fix:
            truth = self.truth[0]
            return (float(truth[0]), float(truth[1]), float(truth[2]))
        fixes = self.nominal_fixes if nominal else self.fixes
        if not fixes:
            raise ValueError("no fixes to start from")
        first = fixes[0]
        if first.fix.yaw_rad is None:
            raise ValueError("the first fix has no heading to start a map with")
        at_fix = np.array([first.fix.x_m, first.fix.y_m, first.fix.yaw_rad])
        odometry = self.nominal_odometry[0] if nominal else self.log.records[0].odom_pose
        start = compose(at_fix, between(first.odom_pose, odometry))
        return (float(start[0]), float(start[1]), float(start[2]))

    def odometry_in_world(self) -> FloatArray:
        """Raw odometry started at the true start pose, for comparison with the truth."""
        odometry = self.log.odometry_poses()
        return compose(self.truth[0], between(odometry[0][None, :], odometry))


def laser_geometry(world: World) -> LaserGeometry:
    """The filter's view of the world's laser: its beams, range limits, mount and beam timing (each beam's
    time relative to the scan's timestamp, the last beam)."""
    lm = world.laser
    steps = np.arange(lm.first_step, lm.last_step + 1, dtype=np.float64)
    step_s = 60.0 / lm.scan_rpm / lm.steps_per_rev
    mount = world.robot.laser_mount
    return LaserGeometry(
        (steps - lm.front_step) * (2.0 * math.pi / lm.steps_per_rev),
        lm.min_range_mm / 1000.0,
        (lm.max_range_mm + 1) / 1000.0,
        (mount.x_m, mount.y_m, mount.yaw_rad),
        (steps - lm.last_step) * step_s,
    )


def leds_in_view(world: World, base: Pose2D, leds: tuple[Led, ...]) -> list[int]:
    """Indices of the LEDs that project inside the upward camera's sensor (pinhole, no tilt) with the base at
    ``base``.

    The camera frame (``drivers/sim/render.py``): x_c along the camera's heading psi = base yaw + mount
    yaw, y_c to its left; u = cx + f (d . x_c) / H, v = cy + f (d . y_c) / H, d the LED's horizontal
    offset from the lens and H its height above it. An LED counts when its whole disk is on the sensor."""
    cam = world.camera
    mount = world.robot.camera_mount
    lens = Simulation.mount_pose(base, mount.x_m, mount.y_m, mount.yaw_rad)
    c, s = math.cos(lens.yaw_rad), math.sin(lens.yaw_rad)
    f_px = cam.focal_length_px
    cx, cy = cam.principal_point_px
    seen = []
    for i, led in enumerate(leds):
        height = led.z_m - mount.z_m
        if height <= 0.0:
            continue
        dx, dy = led.x_m - lens.x_m, led.y_m - lens.y_m
        u = cx + f_px * (dx * c + dy * s) / height
        v = cy + f_px * (-dx * s + dy * c) / height
        r = f_px * led.diameter_m / 2.0 / height
        if r <= u <= cam.sensor_width_px - 1 - r and r <= v <= cam.sensor_height_px - 1 - r:
            seen.append(i)
    return seen


def _integrate(pose: FloatArray, geometry: WheelGeometry, left_rad: float, right_rad: float) -> FloatArray:
    """``pose`` moved by the wheels turning ``left_rad`` and ``right_rad``: differential drive,
    d = r (dphi_l + dphi_r) / 2, dyaw = r (dphi_r - dphi_l) / track, midpoint rule."""
    d = geometry.radius_m * (left_rad + right_rad) / 2.0
    dyaw = geometry.radius_m * (right_rad - left_rad) / geometry.track_m
    x, y, yaw = pose
    return np.array(
        [
            x + d * math.cos(yaw + dyaw / 2.0),
            y + d * math.sin(yaw + dyaw / 2.0),
            math.atan2(math.sin(yaw + dyaw), math.cos(yaw + dyaw)),
        ]
    )


class _Odometry:
    """Wheel odometry through a :class:`WheelErrorModel`: ``pose`` integrated with ``geometry``,
    ``nominal_pose`` from the same encoder readings with the nominal geometry."""

    def __init__(
        self,
        world: World,
        errors: WheelErrorModel,
        geometry: WheelGeometry,
        start: tuple[float, float],
        rng: np.random.Generator,
    ) -> None:
        self.radius_m = world.robot.wheel_radius_m
        self.errors = errors
        self.geometry = geometry
        self.nominal = nominal_geometry(world, errors)
        self.rng = rng
        self.true_last = start
        self.measured = [0.0, 0.0]  # what the encoders would read, radians (before quantization)
        self.ticks_last = (0, 0)
        self.pose = np.zeros(3)
        self.nominal_pose = np.zeros(3)

    def update(self, wheel_rad: tuple[float, float]) -> None:
        e = self.errors
        for i, scale in ((0, e.left_scale), (1, e.right_scale)):
            self.measured[i] += e.counted_rad(
                wheel_rad[i] - self.true_last[i], scale, self.radius_m, self.rng
            )
        self.true_last = wheel_rad
        per_rad = e.ticks_per_turn / (2.0 * math.pi)
        ticks = (math.floor(self.measured[0] * per_rad), math.floor(self.measured[1] * per_rad))
        a_left = (ticks[0] - self.ticks_last[0]) / per_rad
        a_right = (ticks[1] - self.ticks_last[1]) / per_rad
        self.ticks_last = ticks
        self.pose = _integrate(self.pose, self.geometry, a_left, a_right)
        self.nominal_pose = _integrate(self.nominal_pose, self.nominal, a_left, a_right)


class _FakeClock:
    def __init__(self) -> None:
        self.t_s = 0.0

    def __call__(self) -> float:
        return self.t_s


@dataclass
class _Scanner:
    """Sweeps of the world's laser, each beam cast at its own time."""

    sim: Simulation
    laser: LaserModel
    geometry: LaserGeometry
    rng: np.random.Generator

    def ranges(self, stamp_s: float) -> FloatArray:
        g = self.geometry
        assert g.beam_time_s is not None
        times = stamp_s + g.beam_time_s
        first, last = self.sim.pose_at(float(times[0])), self.sim.pose_at(float(times[-1]))
        turned = abs(
            math.atan2(math.sin(last.yaw_rad - first.yaw_rad), math.cos(last.yaw_rad - first.yaw_rad))
        )
        moved = math.hypot(last.x_m - first.x_m, last.y_m - first.y_m)
        n = g.beams
        chunks = int(
            min(max(math.ceil(turned / MAX_CHUNK_YAW_RAD), math.ceil(moved / MAX_CHUNK_MOVE_M), 1), n)
        )
        true_m = np.empty(n)
        for part in np.array_split(np.arange(n), chunks):
            t_mid = float(times[part].mean())
            true_m[part] = self.sim.laser_ranges_m(g.angles_rad[part], t_mid)
        lm = self.laser
        noisy_mm = np.rint(
            np.where(np.isfinite(true_m), true_m * 1000.0, 0.0) + self.rng.normal(0.0, lm.range_noise_mm, n)
        )
        valid = np.isfinite(true_m) & (noisy_mm >= lm.min_range_mm) & (noisy_mm <= lm.max_range_mm)
        if lm.dropout > 0.0:
            valid &= self.rng.random(n) >= lm.dropout
        out: FloatArray = np.where(valid, noisy_mm / 1000.0, 0.0)
        return out


@dataclass
class SimulatedSensors:
    """A simulated robot on a clock the caller sets (``clock.t_s``), with the sensors an offline evaluation
    reads as it drives: laser sweeps, wheel odometry with the default wheel errors, and modelled VLP fixes.
    ``rng`` is what is left of the seed's generator, for the caller's own draws (goals, ...)."""

    clock: _FakeClock
    sim: Simulation
    geometry: LaserGeometry
    scanner: _Scanner
    odometry: _Odometry
    fixes: _ModelledFixes
    rng: np.random.Generator


def simulated_sensors(world: World, seed: int) -> SimulatedSensors:
    """``world`` at time 0 with its sensors, every random stream drawn from ``seed`` (``eval nav``,
    ``eval explore``)."""
    rng = np.random.default_rng(seed)
    clock = _FakeClock()
    sim = Simulation(world, clock=clock, seed=seed)
    geometry = laser_geometry(world)
    scanner = _Scanner(sim, world.laser, geometry, np.random.default_rng(rng.integers(1 << 32)))
    errors = WheelErrorModel()
    odometry = _Odometry(
        world,
        errors,
        nominal_geometry(world, errors),
        sim.wheels().position_rad,
        np.random.default_rng(rng.integers(1 << 32)),
    )
    fixes = _ModelledFixes(world, VlpFixModel(), np.random.default_rng(rng.integers(1 << 32)))
    return SimulatedSensors(clock, sim, geometry, scanner, odometry, fixes, rng)


def simulate_log(
    world: World,
    seconds: float,
    *,
    wheel_errors: WheelErrorModel | None = None,
    wheel_geometry: WheelGeometry | None = None,
    fixes: VlpFixModel | FixSource | None = None,
    seed: int = 0,
) -> SimulatedRun:
    """Drive ``world.route`` for ``seconds`` of simulated time; see the module docstring.
    ``wheel_geometry``: what the odometry computes with (default: the nominal geometry, an uncalibrated
    robot)."""
    if not world.route:
        raise ValueError(f"world {world.name!r} has no route to drive")
    if seconds <= 0.0:
        raise ValueError("seconds must be positive")
    wheel_errors = wheel_errors or WheelErrorModel()
    rng = np.random.default_rng(seed)
    clock = _FakeClock()
    sim = Simulation(world, clock=clock, seed=seed)
    geometry = laser_geometry(world)
    scanner = _Scanner(sim, world.laser, geometry, np.random.default_rng(rng.integers(1 << 32)))
    wheels = wheel_geometry or nominal_geometry(world, wheel_errors)
    odometry = _Odometry(
        world, wheel_errors, wheels, sim.wheels().position_rad, np.random.default_rng(rng.integers(1 << 32))
    )
    fix_rng = np.random.default_rng(rng.integers(1 << 32))
    source: FixSource = (
        _ModelledFixes(world, fixes or VlpFixModel(), fix_rng)
        if fixes is None or isinstance(fixes, VlpFixModel)
        else fixes
    )
    follower = RouteFollower(world.route, world.route_speed_mps)
    odometry_history = _OdometryHistory()
    nominal_history = _OdometryHistory()
    scan_period_s = 60.0 / world.laser.scan_rpm
    scan_every = max(round(scan_period_s / TICK_S), 1)
    fix_every = max(round(1.0 / source.rate_hz / TICK_S), 1)
    # The first scan is stamped once a whole sweep has been measured.
    first_scan_tick = (
        math.ceil(-float(geometry.beam_time_s[0]) / TICK_S) if geometry.beam_time_s is not None else 0
    )
    records: list[LogRecord] = []
    nominal_odometry: list[FloatArray] = []
    nominal_fixes: list[TimedFix] = []
    found: list[TimedFix] = []
    found_leds: list[int] = []
    found_truth: list[tuple[float, float, float]] = []
    misses: collections.Counter[str] = collections.Counter()
    distance_m = turned_rad = 0.0
    last_truth = sim.pose()
    ticks = round(seconds / TICK_S)
    for tick in range(ticks + 1):
        clock.t_s = tick * TICK_S
        truth = sim.pose()
        distance_m += math.hypot(truth.x_m - last_truth.x_m, truth.y_m - last_truth.y_m)
        turned_rad += abs(
            math.atan2(
                math.sin(truth.yaw_rad - last_truth.yaw_rad), math.cos(truth.yaw_rad - last_truth.yaw_rad)
            )
        )
        last_truth = truth
        odometry.update(sim.wheels().position_rad)
        odometry_history.add(clock.t_s, odometry.pose)
        nominal_history.add(clock.t_s, odometry.nominal_pose)
        if tick >= first_scan_tick and (tick - first_scan_tick) % scan_every == 0:
            ranges = scanner.ranges(clock.t_s)
            records.append(
                LogRecord(
                    len(records) + 1,
                    clock.t_s,
                    ranges,
                    odometry.pose.copy(),
                    np.array([truth.x_m, truth.y_m, truth.yaw_rad]),
                )
            )
            nominal_odometry.append(odometry.nominal_pose.copy())
        if tick % fix_every == 0:
            got = source(sim, clock.t_s, odometry.pose)
            if isinstance(got, str):
                misses[got] += 1
            else:
                t_fix, fix, n_leds = got
                at = sim.pose_at(t_fix)
                found.append(TimedFix(t_fix, fix, odometry_history.at(t_fix)))
                nominal_fixes.append(TimedFix(t_fix, fix, nominal_history.at(t_fix)))
                found_leds.append(n_leds)
                found_truth.append((at.x_m, at.y_m, at.yaw_rad))
        if tick % AUTOPILOT_EVERY == 0:
            sim.set_body_velocity(*follower.command(truth.x_m, truth.y_m, truth.yaw_rad))
    log = SlamLog(f"simulated:{world.name}", LogFormat.SIMULATED, geometry, tuple(records))
    return SimulatedRun(
        log,
        tuple(found),
        tuple(found_leds),
        np.array(found_truth, dtype=np.float64).reshape(-1, 3),
        distance_m,
        turned_rad,
        misses.total(),
        dict(misses),
        np.array(nominal_odometry, dtype=np.float64).reshape(-1, 3),
        tuple(nominal_fixes),
        wheels,
    )
