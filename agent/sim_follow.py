"""``vlp-agent sim --follow``: the follow loop wired on the simulated robot, and its score against the
simulation's truth (``docs/following.md``, "Following in the simulator").

:class:`FollowScore` samples the truth every ``period_s`` of the simulation's clock: the robot's true
pose, the tagged user's position and speed, every person's, and the follow loop's latest state, and
reports

* ``within_band``: the share of the time the user walks (true speed > 0.05 m/s) that the true centre
  distance robot-user is within ``distance_m`` +- ``band_m``; ``within_band_after_reached`` the same from
  the first time it was in the band (the start's approach left out); ``distance_m_median`` while walking;
* ``time_lost_s``: time in the states ``lost`` and ``no_tag`` after the first acquisition;
* ``identity_switches``: how often the person the track is on (the true person nearest the track, within
  ``match_m``) changes from one person to another;
* ``collisions_people``: contacts (footprint touching a body) begun; ``contacts_robot_moving``: those begun
  while the robot moved (faster than 0.05 m/s between two samples: the robot drove into someone; the
  simulated walkers do not yield, so the rest are people walking into a robot at rest);
  ``min_person_gap_m`` (footprint to body), ``min_person_distance_m`` (centre to centre);
* ``stop_latency_s_max``: per entry into ``lost`` (or ``no_tag``) after the first acquisition, the time
  until the robot's true speed is below 0.02 m/s (0 when it already was; the acceptance: 0.5 s) or it
  steps out of a walker's way (``lost_then_aside`` counts those);
  ``lost_events`` and ``lost_speed_mps_max``, the fastest it was going at one;
* with ``--fault person`` (the user hidden from the follow loop: they vanish), per hiding the time from
  its start to the first zero forward speed the loop sent (``vanish_stop_command_s``) and to the robot's
  true speed (the wheels') below 0.02 m/s, the crossing interpolated between samples (``vanish_stop_s``;
  the acceptance: 0.5 s; ``vanish_stop_sampled_s``: from the speed between samples, as measured before),
  the speed it had (``vanish_speed_mps``); a step out of a walker's way ends it too (``vanish_then_aside``
  counts those).
"""

from __future__ import annotations

import logging
import math
import statistics
import threading
from typing import Any

from agent.following.follower import FollowState
from agent.runtime.follow_loop import NO_POSE, FollowLoop
from agent.runtime.follow_setup import camera_view, make_follow_loop
from drivers.sim.harness import SimulatedRobot

__all__ = ["FollowScore", "camera_view", "make_follow_loop"]

log = logging.getLogger(__name__)

STOPPED_MPS = 0.02
MOVING_MPS = 0.05  # a contact begun faster than this is the robot driving into someone
CUE_LATEST_S = 5.0
# ``--follow-trace``'s columns: the simulation's seconds from its start, the robot's true pose and speed
# (between samples), the user's true position and distance, the footprint's gap to the nearest body, the
# loop's state and the velocity it sent, the track's position, the command's reason.
TRACE_COLUMNS = (
    "t_s",
    "robot_x_m",
    "robot_y_m",
    "robot_yaw_rad",
    "robot_speed_mps",
    "user_x_m",
    "user_y_m",
    "user_distance_m",
    "person_gap_m",
    "state",
    "sent_v_mps",
    "sent_omega_radps",
    "track_x_m",
    "track_y_m",
    "reason",
)
SAFETY_COUNTS = ("costmap_stops", "walker_slowdowns", "steps_aside")


class FollowScore:
    def __init__(
        self,
        robot: SimulatedRobot,
        loop: FollowLoop,
        tag_id: str | None,
        distance_m: float,
        band_m: float = 0.25,
    ) -> None:
        self.sim = robot.simulation
        self.sim.hold_people()  # until the robot has a pose (sample())
        self.loop = loop
        people = self.sim.world.people
        tag = (tag_id or "").upper()
        users = [p for p in people if p.tag_id.upper() == tag]
        self.user = users[0] if users else None
        self.distance_m = distance_m
        self.band_m = band_m
        self.match_m = 0.6
        self._lock = threading.Lock()
        self._last_t: float | None = None
        self._last_pose: tuple[float, float] | None = None
        self.walking_s = 0.0
        self.within_s = 0.0
        self.reached = False
        self.after_s = 0.0
        self.after_within_s = 0.0
        self.distances: list[float] = []
        self.lost_s = 0.0
        self.acquired = False
        self.acquired_t: float | None = None
        self.walking_untracked_s = 0.0  # the user walking before the first track
        self.on_person: str | None = None
        self.switches = 0
        self.contacts = 0
        self.contacts_moving = 0
        self._in_contact = False
        self.min_gap = math.inf
        self.min_dist = math.inf
        self.lost_events = 0
        self._lost_since: float | None = None
        self._was_lost = False
        self.latencies: list[float] = []
        self.lost_speeds: list[float] = []
        self.aside_ended = 0  # losses whose stop was cut short by a step out of a walker's way
        self.cued = False
        self.ready_t: float | None = None
        self._vanishings_seen = 0
        self._vanish_t: float | None = None
        self.vanish_stops: list[float] = []
        self.vanish_stops_sampled: list[float] = []
        self._vanish_sampled_t: float | None = None
        self._last_v: float | None = None
        self.vanish_speeds: list[float] = []
        self.vanish_aside = 0  # hidings whose stop was cut short by a step out of a walker's way
        # With ``trace``: one row per sample (TRACE_COLUMNS), for ``--follow-trace``.
        self.trace: list[tuple[Any, ...]] | None = None

    def sample(self) -> None:
        sim = self.sim
        t = sim.now()
        base = sim.pose()
        with self._lock:
            dt = 0.0 if self._last_t is None else t - self._last_t
            speed = 0.0
            if self._last_pose is not None and dt > 0:
                speed = math.hypot(base.x_m - self._last_pose[0], base.y_m - self._last_pose[1]) / dt
            self._last_t, self._last_pose = t, (base.x_m, base.y_m)
            # The true forward speed now (the wheels'), and when it fell under STOPPED_MPS: between the last
            # sample and this one, linearly (the base brakes at a constant rate). The speed above is over
            # the last period_s, which lags a braking base by half of it.
            v_true = abs(sim.body_motion()[0])
            stopped_t = t
            if self._last_v is not None and self._last_v > STOPPED_MPS >= v_true and dt > 0:
                stopped_t = t - dt * (STOPPED_MPS - v_true) / (self._last_v - v_true)
            self._last_v = v_true
            positions = {p.name: sim.person_position(p, t) for p in sim.world.people}
            for p in sim.world.people:
                px, py = positions[p.name]
                d = math.hypot(px - base.x_m, py - base.y_m)
                self.min_dist = min(self.min_dist, d)
                self.min_gap = min(self.min_gap, d - p.radius_m - sim.world.robot.radius_m)
            _, person_gap = sim.clearances_m(base.x_m, base.y_m, t)
            contact = person_gap <= 0.0
            if contact and not self._in_contact:
                self.contacts += 1
                self.contacts_moving += int(speed > MOVING_MPS)
                snap = self.loop.latest
                log.warning(
                    "follow: contact at t=%.2f, robot %.2f,%.2f yaw %.2f at %.2f m/s, people %s; last %s",
                    t,
                    base.x_m,
                    base.y_m,
                    base.yaw_rad,
                    speed,
                    {n: (round(x, 2), round(y, 2)) for n, (x, y) in positions.items()},
                    None if snap is None else (snap.command, snap.sent, snap.aside),
                )
            self._in_contact = contact
            if self.user is not None:
                ux, uy = positions[self.user.name]
                d_user = math.hypot(ux - base.x_m, uy - base.y_m)
                if sim.person_speed_mps(self.user) > 0.05:
                    self.walking_s += dt
                    self.walking_untracked_s += 0.0 if self.acquired else dt
                    within = abs(d_user - self.distance_m) <= self.band_m
                    self.within_s += dt if within else 0.0
                    self.distances.append(d_user)
                    if len(self.distances) % 5 == 0:
                        log.debug(
                            "follow truth t=%.2f user=%.2f,%.2f robot=%.2f,%.2f d=%.2f",
                            t,
                            ux,
                            uy,
                            base.x_m,
                            base.y_m,
                            d_user,
                        )
                    self.reached |= within
                    if self.reached:
                        self.after_s += dt
                        self.after_within_s += dt if within else 0.0
            vanishings = self.loop.vanishings_s
            if len(vanishings) > self._vanishings_seen:
                self._vanishings_seen = len(vanishings)
                self._vanish_t = self._vanish_sampled_t = vanishings[-1]
                self.vanish_speeds.append(v_true)
            snap = self.loop.latest
            aside = snap is not None and snap.aside
            if self._vanish_t is not None and (v_true <= STOPPED_MPS or aside):
                # Stopped, or stepping out of a walker's way (the walkers do not yield; counted apart).
                self.vanish_stops.append(
                    max(0.0, (stopped_t if v_true <= STOPPED_MPS else t) - self._vanish_t)
                )
                self.vanish_aside += int(aside and v_true > STOPPED_MPS)
                self._vanish_t = None
            if self._vanish_sampled_t is not None and (speed <= STOPPED_MPS or aside):
                # The same from the speed between samples, on the samples' times (the measure before).
                self.vanish_stops_sampled.append(max(0.0, t - self._vanish_sampled_t))
                self._vanish_sampled_t = None
            if self.trace is not None:
                user_xy = positions[self.user.name] if self.user is not None else (math.nan, math.nan)
                person = None if snap is None else snap.person
                self.trace.append(
                    (
                        round(t - sim.t_start, 3),
                        round(base.x_m, 3),
                        round(base.y_m, 3),
                        round(base.yaw_rad, 3),
                        round(speed, 3),
                        round(user_xy[0], 3),
                        round(user_xy[1], 3),
                        round(math.hypot(user_xy[0] - base.x_m, user_xy[1] - base.y_m), 3),
                        round(person_gap, 3),
                        "" if snap is None else snap.command.state.value,
                        "" if snap is None else round(snap.sent[0], 3),
                        "" if snap is None else round(snap.sent[1], 3),
                        "" if person is None else round(person.xy[0], 3),
                        "" if person is None else round(person.xy[1], 3),
                        "" if snap is None else snap.command.reason,
                    )
                )
            if snap is None:
                return
            if self.ready_t is None and snap.command.reason != NO_POSE:
                self.ready_t = t
            locked = snap.person is not None and snap.command.state in (
                FollowState.FOLLOWING,
                FollowState.WAITING,
            )
            if not self.cued and self.ready_t is not None and (locked or t - self.ready_t >= CUE_LATEST_S):
                # The scenario starts when the robot has locked on (a pose, a track, and the camera the
                # follower needs giving frames: it follows; at the latest CUE_LATEST_S after the pose): the
                # user waits for it, as a real one would. The user's walk after that counts, tracked or not.
                sim.cue_people()
                self.cued = True
            state = snap.command.state
            if snap.person is not None:
                if not self.acquired:
                    self.acquired_t = t
                self.acquired = True
                best = min(positions, key=lambda n: math.dist(positions[n], snap.person.xy))  # type: ignore[union-attr]
                if math.dist(positions[best], snap.person.xy) <= self.match_m:
                    if self.on_person is not None and best != self.on_person:
                        self.switches += 1
                    self.on_person = best
            lost = state in (FollowState.LOST, FollowState.NO_TAG, FollowState.NO_CAMERA)
            if self.acquired and lost:
                self.lost_s += dt
            if lost and not self._was_lost and self.acquired:
                self.lost_events += 1
                self.lost_speeds.append(speed)
                self._lost_since = t
            if self._lost_since is not None and (not lost or speed <= STOPPED_MPS or snap.aside):
                if speed <= STOPPED_MPS or snap.aside:
                    self.latencies.append(t - self._lost_since)
                    self.aside_ended += int(snap.aside and speed > STOPPED_MPS)
                self._lost_since = None
            self._was_lost = lost

    def write_trace(self, path: str) -> None:
        """The samples as CSV (``TRACE_COLUMNS``); nothing without ``trace``."""
        import csv

        with self._lock:
            rows = list(self.trace or ())
        with open(path, "w", newline="", encoding="utf-8") as f:
            out = csv.writer(f)
            out.writerow(TRACE_COLUMNS)
            out.writerows(rows)

    def run(self, stop: threading.Event, period_s: float = 0.05) -> None:
        while not stop.wait(period_s):
            self.sample()

    def figures(self) -> dict[str, Any]:
        with self._lock:

            def r(x: float, n: int = 3) -> float | None:
                return round(x, n) if math.isfinite(x) else None

            return {
                "user": self.user.name if self.user is not None else None,
                "distance_set_m": self.distance_m,
                "band_m": self.band_m,
                "walking_s": r(self.walking_s, 2),
                "within_band": r(self.within_s / self.walking_s) if self.walking_s > 0 else None,
                "within_band_after_reached": r(self.after_within_s / self.after_s)
                if self.after_s > 0
                else None,
                "distance_m_median": r(statistics.median(self.distances)) if self.distances else None,
                "time_lost_s": r(self.lost_s, 2),
                "acquired_after_s": r(self.acquired_t - self.ready_t, 2)
                if self.acquired_t is not None and self.ready_t is not None
                else None,
                "walking_untracked_s": r(self.walking_untracked_s, 2),
                "identity_switches": self.switches,
                "followed": self.on_person,
                "collisions_people": self.contacts,
                "contacts_robot_moving": self.contacts_moving,
                "min_person_gap_m": r(self.min_gap),
                "min_person_distance_m": r(self.min_dist),
                "lost_events": self.lost_events,
                "stop_latency_s_max": r(max(self.latencies)) if self.latencies else None,
                "lost_speed_mps_max": r(max(self.lost_speeds)) if self.lost_speeds else None,
                "lost_then_aside": self.aside_ended,
                "vanish_stop_command_s": [round(x, 3) for x in self.loop.vanish_stops_s],
                "vanish_stop_s": [round(x, 3) for x in self.vanish_stops],
                "vanish_stop_sampled_s": [round(x, 3) for x in self.vanish_stops_sampled],
                "vanish_speed_mps": [round(x, 3) for x in self.vanish_speeds],
                "vanish_then_aside": self.vanish_aside,
                "occluded_scans": self.loop.counts.get("occluded_scans", 0),
                "fine": {k: n for k, n in self.loop.counts.items() if k.startswith("fine_")}
                | (dict(self.loop.locator.counts) if self.loop.locator is not None else {}),
                "states": {k: n for k, n in self.loop.counts.items() if k.startswith("state_")},
                "safety": {
                    k: self.loop.counts.get(k, 0)
                    for k in (
                        "costmap_stops",
                        "walker_slowdowns",
                        "walker_yield",
                        "walker_go",
                        "walker_velocity_carried",
                        "steps_aside",
                        "asides_refused",
                        "acquired_on_map",
                        "acquire_waits_on_map",
                        "late_scan_slowdowns",
                        "reframes",
                        "scans_out_of_order",
                    )
                },
                "tracker": dict(self.loop.tracker.counts),
                "last_reason": self.loop.latest.command.reason if self.loop.latest is not None else None,
            }
