"""The moving state of a simulated world, shared by every fake device in one process.

The robot moves only from the wheel velocities the fake servos receive, so the loop is closed through the
real bytes: agent -> Dynamixel packets -> ``set_wheel_velocity`` -> motion -> laser, camera, IMU, odometry.
Time comes from an injectable clock (``time.monotonic`` by default); the state is integrated lazily up to
"now" whenever it is read, in sub-steps of at most ``max_step_s``, and a short pose history is kept so the
camera can render motion during its rolling readout.
"""

from __future__ import annotations

import bisect
import collections
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from drivers.sim.pedestrians import Walker, WalkPath, lookahead_m, step_walker
from drivers.sim.raycast import cast_rays, distance_to_segments, walls_array
from drivers.sim.world import Person, Pose2D, World, door_scheduled_closed

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class WheelTruth:
    position_rad: tuple[float, float]
    velocity_radps: tuple[float, float]


@dataclass(frozen=True, slots=True)
class TagInRange:
    tag_id: str
    person: str
    distance_m: float
    bearing_rad: float


def _wrap(angle_rad: float) -> float:
    return math.atan2(math.sin(angle_rad), math.cos(angle_rad))


class Simulation:
    """Ground truth for one world, advanced in time on demand. All methods are thread-safe."""

    history_s = 2.0
    max_step_s = 0.002

    def __init__(self, world: World, clock: Callable[[], float] = time.monotonic, seed: int = 0) -> None:
        self.world = world
        self.clock = clock
        self.rng = np.random.default_rng(seed)
        self._lock = threading.RLock()
        self._walls = walls_array(world.walls)
        # Doors (``World.doors``): a wall while closed. The state changes on the schedule, except that a
        # door does not close on the robot: it waits until its footprint is clear of the doorway.
        self._door_segments = walls_array(world.doors)
        self._door_closed = np.zeros(len(world.doors), dtype=bool)
        self._door_events: list[tuple[float, str, bool]] = []  # (elapsed s, name, closed)
        self._segments = self._walls
        robot = world.robot
        self._t = clock()
        self.t_start = self._t
        self.people_start = self._t  # the people's cues (Person.start_s) count from here
        self._x, self._y, self._yaw = robot.start.x_m, robot.start.y_m, robot.start.yaw_rad
        self._wheel_pos = [0.0, 0.0]
        self._wheel_vel = [0.0, 0.0]
        self._wheel_goal = [0.0, 0.0]
        self._v_mps = 0.0
        self._a_long_mps2 = 0.0
        self._omega_radps = 0.0
        # People: distance walked along each one's path (they stop for the robot: drivers/sim/pedestrians.py).
        self._paths = [WalkPath(p.path, p.loop) for p in world.people]
        self._walkers = [Walker(0.0, p.speed_mps) for p in world.people]
        self._person_index = {p.name: i for i, p in enumerate(world.people)}
        self._times: collections.deque[float] = collections.deque()
        self._poses: collections.deque[tuple[float, float, float]] = collections.deque()
        self._walked: collections.deque[tuple[float, ...]] = collections.deque()
        self._record()
        if len(self._door_closed):
            self._update_doors()  # the doors closed at the start

    # -- time ----------------------------------------------------------------------------------------
    def now(self) -> float:
        return self.clock()

    def elapsed_s(self) -> float:
        return self.clock() - self.t_start

    def hold_people(self) -> None:
        """Keep everyone at their path's start until :meth:`cue_people`."""
        with self._lock:
            self.people_start = math.inf

    def cue_people(self) -> None:
        """Count the people's cues (``Person.start_s``) from now: a scenario that starts when the robot is
        ready (``vlp-agent sim --follow``), not when the simulation was made. Call before any has started."""
        with self._lock:
            self._integrate_to(self.clock())
            self.people_start = self._t

    def advance(self) -> float:
        """Integrate the state up to the clock's now; returns now."""
        with self._lock:
            now = self.clock()
            self._integrate_to(now)
            return now

    def _record(self) -> None:
        self._times.append(self._t)
        self._poses.append((self._x, self._y, self._yaw))
        self._walked.append(tuple(w.s_m for w in self._walkers))
        while self._times and self._times[0] < self._t - self.history_s:
            self._times.popleft()
            self._poses.popleft()
            self._walked.popleft()

    def _step_people(self, dt: float) -> None:
        radius = self.world.robot.radius_m
        elapsed = self._t - self.people_start
        for person, path, walker in zip(self.world.people, self._paths, self._walkers, strict=True):
            if elapsed < person.start_s:
                walker.v_mps = 0.0  # waiting for their cue
                continue
            seen: tuple[float, float] | None = None
            if person.yields:
                px, py = path.point_at(walker.s_m)
                # The robot moves less than 0.5 m in a reaction time: farther than this, it cannot matter.
                far = lookahead_m(person.speed_mps, person.reaction_s) + person.radius_m + radius + 0.6
                if math.hypot(self._x - px, self._y - py) <= far:
                    x, y, _ = self._interpolate(self._t - person.reaction_s)
                    seen = (x, y)
            step_walker(walker, person, path, dt, seen, radius)
            if not path.loop and walker.s_m >= path.total_m:
                walker.s_m, walker.v_mps = path.total_m, 0.0  # arrived: they stand at the end

    def _integrate_to(self, t: float) -> None:
        robot = self.world.robot
        r, track = robot.wheel_radius_m, robot.track_m
        max_dv = robot.max_wheel_accel_radps2
        while self._t < t:
            dt = min(self.max_step_s, t - self._t)
            v_before = self._v_mps
            for i in (0, 1):
                goal = max(-robot.max_wheel_radps, min(robot.max_wheel_radps, self._wheel_goal[i]))
                step = max(-max_dv * dt, min(max_dv * dt, goal - self._wheel_vel[i]))
                self._wheel_vel[i] += step
                self._wheel_pos[i] += self._wheel_vel[i] * dt
            # Differential drive: v = r (wl + wr) / 2, omega = r (wr - wl) / track; exact arc per sub-step.
            v = r * (self._wheel_vel[0] + self._wheel_vel[1]) / 2.0
            omega = r * (self._wheel_vel[1] - self._wheel_vel[0]) / track
            if abs(omega) < 1e-9:
                self._x += v * dt * math.cos(self._yaw)
                self._y += v * dt * math.sin(self._yaw)
            else:
                yaw2 = self._yaw + omega * dt
                self._x += v / omega * (math.sin(yaw2) - math.sin(self._yaw))
                self._y -= v / omega * (math.cos(yaw2) - math.cos(self._yaw))
                self._yaw = _wrap(yaw2)
            self._v_mps, self._omega_radps = v, omega
            self._a_long_mps2 = (v - v_before) / dt if dt > 0 else 0.0
            self._step_people(dt)
            self._t += dt
            self._record()
            if len(self._door_closed):
                self._update_doors()

    def _update_doors(self) -> None:
        elapsed = self._t - self.t_start
        changed = False
        clear_m = self.world.robot.radius_m + 0.02
        for i, door in enumerate(self.world.doors):
            want = door_scheduled_closed(door, elapsed)
            if want == self._door_closed[i]:
                continue
            if want and distance_to_segments((self._x, self._y), self._door_segments[i : i + 1]) < clear_m:
                continue  # the robot is in the doorway: the door waits
            self._door_closed[i] = want
            self._door_events.append((elapsed, door.name, want))
            changed = True
        if changed:
            self._segments = np.vstack([self._walls, self._door_segments[self._door_closed]])

    # -- doors ---------------------------------------------------------------------------------------
    def segments(self) -> FloatArray:
        """The (N, 4) wall segments now: the walls and the doors that are closed."""
        with self._lock:
            self._integrate_to(self.clock())
            return self._segments

    def doors_closed(self) -> dict[str, bool]:
        """Each door's state now, by name (True: closed)."""
        with self._lock:
            self._integrate_to(self.clock())
            return {d.name: bool(c) for d, c in zip(self.world.doors, self._door_closed, strict=True)}

    def door_events(self) -> list[tuple[float, str, bool]]:
        """Every change of a door so far: (simulated seconds from the start, name, closed)."""
        with self._lock:
            self._integrate_to(self.clock())
            return list(self._door_events)

    # -- the robot -----------------------------------------------------------------------------------
    def set_wheel_velocity(self, left_radps: float, right_radps: float) -> None:
        """Command the wheels (what the servos' Goal Velocity registers say)."""
        with self._lock:
            self._integrate_to(self.clock())
            self._wheel_goal = [float(left_radps), float(right_radps)]

    def set_body_velocity(self, v_mps: float, omega_radps: float) -> None:
        robot = self.world.robot
        half = omega_radps * robot.track_m / 2.0
        self.set_wheel_velocity((v_mps - half) / robot.wheel_radius_m, (v_mps + half) / robot.wheel_radius_m)

    def wheels(self) -> WheelTruth:
        with self._lock:
            self._integrate_to(self.clock())
            return WheelTruth(
                (self._wheel_pos[0], self._wheel_pos[1]), (self._wheel_vel[0], self._wheel_vel[1])
            )

    def pose(self) -> Pose2D:
        """The robot base's true pose now."""
        with self._lock:
            self._integrate_to(self.clock())
            return Pose2D(self._x, self._y, self._yaw)

    def pose_at(self, t: float) -> Pose2D:
        """The true pose at a recent time ``t`` (linear interpolation over the kept history)."""
        with self._lock:
            self._integrate_to(max(t, self.clock()) if t > self._t else self._t)
            return Pose2D(*self._interpolate(t))

    def _bracket(self, t: float) -> tuple[int, float]:
        """(i, w): ``t`` lies w of the way from history entry i - 1 to i (clamped to the history)."""
        times = self._times
        if t <= times[0]:
            return 0, 1.0
        if t >= times[-1]:
            return len(times) - 1, 1.0
        i = bisect.bisect_left(times, t)
        t0, t1 = times[i - 1], times[i]
        return i, (t - t0) / (t1 - t0) if t1 > t0 else 1.0

    def _interpolate(self, t: float) -> tuple[float, float, float]:
        i, w = self._bracket(t)
        (x1, y1, a1) = self._poses[i]
        if i == 0 or w >= 1.0:
            return x1, y1, a1
        (x0, y0, a0) = self._poses[i - 1]
        return x0 + w * (x1 - x0), y0 + w * (y1 - y0), _wrap(a0 + w * _wrap(a1 - a0))

    def body_motion(self) -> tuple[float, float, float]:
        """(forward speed m/s, forward acceleration m/s^2, yaw rate rad/s), true values now."""
        with self._lock:
            self._integrate_to(self.clock())
            return self._v_mps, self._a_long_mps2, self._omega_radps

    @staticmethod
    def mount_pose(base: Pose2D, mx: float, my: float, myaw: float) -> Pose2D:
        c, s = math.cos(base.yaw_rad), math.sin(base.yaw_rad)
        return Pose2D(base.x_m + c * mx - s * my, base.y_m + s * mx + c * my, _wrap(base.yaw_rad + myaw))

    # -- people --------------------------------------------------------------------------------------
    def person_position(self, person: Person, t: float | None = None) -> tuple[float, float]:
        """Where a person is at time ``t`` (now by default; a past time within the kept history) on their
        looped path: walking at their speed, or stopped for the robot (``Person.yields``)."""
        with self._lock:
            t = self.clock() if t is None else t
            self._integrate_to(max(t, self._t))
            k = self._person_index[person.name]
            i, w = self._bracket(t)
            s1 = self._walked[i][k]
            s = s1 if i == 0 or w >= 1.0 else self._walked[i - 1][k] + w * (s1 - self._walked[i - 1][k])
            return self._paths[k].point_at(s)

    def person_pose(self, person: Person, t: float | None = None) -> tuple[float, float, float, float]:
        """(x, y, heading, distance walked) of a person at time ``t`` (now by default): they face along
        their path (along its last leg once a walk-once path has ended)."""
        with self._lock:
            t = self.clock() if t is None else t
            self._integrate_to(max(t, self._t))
            k = self._person_index[person.name]
            i, w = self._bracket(t)
            s1 = self._walked[i][k]
            s = s1 if i == 0 or w >= 1.0 else self._walked[i - 1][k] + w * (s1 - self._walked[i - 1][k])
            path = self._paths[k]
            x, y = path.point_at(s)
            ahead = path.pieces(min(s, path.total_m - 1e-3) if not path.loop else s, 1e-3)
            heading = math.atan2(ahead[0][3], ahead[0][2]) if ahead else 0.0
            return x, y, heading, s

    def person_speed_mps(self, person: Person) -> float:
        """How fast a person walks now (0 while they stand for the robot)."""
        with self._lock:
            self._integrate_to(self.clock())
            return self._walkers[self._person_index[person.name]].v_mps

    def tags_in_range(self, range_m: float | None = None) -> list[TagInRange]:
        range_m = self.world.rfid.range_m if range_m is None else range_m
        base = self.pose()
        found = []
        for person in self.world.people:
            px, py = self.person_position(person)
            dist = math.hypot(px - base.x_m, py - base.y_m)
            if dist <= range_m:
                bearing = _wrap(math.atan2(py - base.y_m, px - base.x_m) - base.yaw_rad)
                found.append(TagInRange(person.tag_id, person.name, dist, bearing))
        return found

    # -- sensors' geometry ---------------------------------------------------------------------------
    def laser_ranges_m(self, angles_rad: FloatArray, t: float | None = None) -> FloatArray:
        """True distances from the laser along each beam (laser frame angles), ``inf`` beyond max range."""
        base = self.pose() if t is None else self.pose_at(t)
        mount = self.world.robot.laser_mount
        lp = self.mount_pose(base, mount.x_m, mount.y_m, mount.yaw_rad)
        circles = None
        if self.world.people:
            circles = np.array([(*self.person_position(p, t), p.radius_m) for p in self.world.people])
        max_m = self.world.laser.max_range_mm / 1000.0
        angles = np.asarray(angles_rad) + lp.yaw_rad
        return cast_rays((lp.x_m, lp.y_m), angles, self._segments, circles, max_m)

    def clearances_m(self, x_m: float, y_m: float, t: float | None = None) -> tuple[float, float]:
        """The gaps between the robot's footprint (a circle of ``robot.radius_m`` at ``x_m, y_m``) and the
        nearest wall and the nearest person at time ``t``: <= 0 is contact (``inf`` where there is none)."""
        radius = self.world.robot.radius_m
        wall = distance_to_segments((x_m, y_m), self.segments()) - radius
        person = float("inf")
        for p in self.world.people:
            px, py = self.person_position(p, t)
            person = min(person, math.hypot(px - x_m, py - y_m) - p.radius_m - radius)
        return wall, person

    def imu_truth(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """Specific force (m/s^2) and angular rate (rad/s) in the base frame (x fwd, y left, z up)."""
        v, a_long, omega = self.body_motion()
        g = 9.80665
        return (a_long, v * omega, g), (0.0, 0.0, omega)
