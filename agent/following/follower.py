"""The follower: a velocity command that keeps a set distance behind the person (``docs/following.md``,
"The follower").

Each step takes the robot's pose, the person's track (``person.PersonEstimate``, or None) and the RFID
layer's word (whether the tag is near at all, and the band it says to look in) and answers a
:class:`FollowCommand` with one of four states and a reason:

* ``following``: a point ``distance_m`` short of the person on the line robot -> person is the target;
  the forward speed is a proportional pull toward it plus the person's own speed along the line
  (feed-forward), never backwards, zero when they are nearer than ``min_gap_m`` (the person is an
  obstacle), scaled down while the heading is off (turning in place beyond ``turn_first_rad``); the turn
  keeps the person ahead (in the camera's view);
* ``waiting``: the person stands (slower than ``standing_mps``) and the robot is at its distance: stop;
* ``lost``: the track is gone: stop at once; after ``search_after_s`` turn in place toward the RFID
  bearing (the coarse layer's prediction step carries the turn, which separates front from back) until the
  tracker re-acquires. A track not measured for a while is one of two things: **occluded** (the caller
  says something nearer stands on the line of sight: a passer-by, a corner) and the robot coasts on the
  track's prediction at ``occluded_speed_factor`` of its speed until the tracker drops it; or **vanished**
  (nothing in front explains it): past ``grace_s`` the speed ramps down to zero at ``stop_after_s`` (zero on
  the first missed scan) and the state is ``lost`` from then on (an occluder found later does not resume
  the coasting: only a measurement does), so the robot stands about half a second after the person
  vanishes (issue 23's acceptance; the base's braking is most of it) while a passer-by crossing the line
  of sight does not stop it;
* ``no_tag``: the RFID layer says the person is absent (or gives nothing): stop;
* ``no_camera`` (set by the follow loop, not here): the forward camera has given no frame for a while
  (unplugged, stalled): stop until it is back.

The command then goes through the navigation's costmap, the walkers' motion (:func:`safe_speed`) and the
collision monitor (the runtime's job, ``agent/runtime/follow_loop.py``).
Pure: time passed in.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from agent.following.person import PersonEstimate

__all__ = [
    "FollowCommand",
    "FollowState",
    "Follower",
    "FollowerConfig",
    "WalkerMode",
    "predicted_gaps",
    "safe_speed",
    "walker_candidates",
    "walker_decision",
    "walker_threat",
]

Pose = tuple[float, float, float]


class FollowState(enum.StrEnum):
    FOLLOWING = "following"
    WAITING = "waiting"
    LOST = "lost"
    NO_TAG = "no_tag"
    NO_CAMERA = "no_camera"  # the forward camera the person's estimate relies on gives no frames: stopped


@dataclass(frozen=True, slots=True)
class FollowerConfig:
    distance_m: float = 1.0  # kept between the robot's centre and the person's
    min_gap_m: float = 0.6  # nearer than this the robot does not move toward them
    max_speed_mps: float = 0.95
    max_turn_radps: float = 1.5
    gain_distance: float = 1.2  # 1/s: m/s of pull per metre off the set distance
    gain_heading: float = 2.5  # 1/s: rad/s of turn per radian off the person's bearing
    turn_first_rad: float = math.radians(60.0)  # the person further off the heading: turn in place
    standing_mps: float = 0.12  # slower than this the person stands
    tolerance_m: float = 0.05  # within this of the distance a standing person is waited for
    search_after_s: float = 1.0  # lost this long: turn toward the RFID bearing
    # A track not measured for longer (a scan missed: 10 Hz scans) is occluded or vanished. Vanished
    # (nothing in front), the speed ramps from grace_s to zero at stop_after_s: zero on the first missed
    # scan (the ramp acts only when a camera bearing came between the scans). Both sit well short of the
    # scan period, whose jitter (a few hundredths) must not put the stop a whole scan later.
    grace_s: float = 0.03
    stop_after_s: float = 0.05
    occluded_speed_factor: float = 0.7  # occluded: coast on the prediction at this share of the speed
    search_turn_radps: float = 0.6
    absent_probability: float = 0.8  # the coarse layer's p_absent above this: no tag


@dataclass(frozen=True, slots=True)
class FollowCommand:
    v_mps: float
    omega_radps: float
    state: FollowState
    reason: str
    distance_m: float | None = None  # to the tracked person, when there is one


def _clip(x: float, lo: float, hi: float) -> float:
    return max(lo, min(hi, x))


class Follower:
    def __init__(self, config: FollowerConfig = FollowerConfig()) -> None:
        self.config = config
        self.lost_since_s: float | None = None
        # Stopped for a vanished track: only a measurement resumes following, not an occluder found later
        # (the person gone from the scans' detections may still be the nearer return on the line of sight).
        self.vanished = False

    def step(
        self,
        t_s: float,
        robot: Pose,
        person: PersonEstimate | None,
        p_absent: float | None,
        search_bearing_rad: float | None,
        occluded: bool = False,
        looked_s: float | None = None,
    ) -> FollowCommand:
        """``p_absent``: the coarse layer's probability that the person is out of reach (None: no RFID
        answer yet); ``search_bearing_rad``: where it says to turn to (robot frame), None for no idea;
        ``occluded``: something nearer stands on the line of sight to the track (see the module's text);
        ``looked_s``: the time of the last look for the person (the last scan), so that a late scan is not
        taken for a person gone (None: ``t_s``)."""
        cfg = self.config
        looked = t_s if looked_s is None else min(t_s, looked_s)
        # Since the last *scan* that showed them: a camera bearing taken a few hundredths after a scan's
        # stamp (step 0; the person ahead is swept 0.04 s later) made the first scan that missed them look
        # older than the track, and the stop came on the second, 0.1 s later.
        unseen_s = 0.0
        if person is not None:
            seen = person.last_seen_s if person.scan_seen_s is None else person.scan_seen_s
            unseen_s = max(0.0, looked - seen)
        if person is None or unseen_s <= cfg.grace_s:
            self.vanished = False
        if person is not None and unseen_s > cfg.grace_s and (self.vanished or not occluded):
            ramp = (cfg.stop_after_s - unseen_s) / max(cfg.stop_after_s - cfg.grace_s, 1e-6)
            if ramp <= 0.0 or self.vanished:
                # Vanished: stopped, and the wait and search of a lost track follow (once it is dropped).
                self.vanished = True
                if self.lost_since_s is None:
                    self.lost_since_s = t_s
                return FollowCommand(
                    0.0,
                    0.0,
                    FollowState.LOST,
                    f"the person vanished {unseen_s:.2f} s ago with nothing in front: stopped",
                )
            cmd = self._follow(robot, person)
            return FollowCommand(
                cmd.v_mps * ramp,
                cmd.omega_radps,
                cmd.state,
                f"not seen for {unseen_s:.2f} s, nothing in front: slowing down",
                cmd.distance_m,
            )
        if person is None:
            if self.lost_since_s is None:
                self.lost_since_s = t_s
            if p_absent is None or p_absent > cfg.absent_probability:
                why = "no RFID answer yet" if p_absent is None else f"tag absent (p={p_absent:.2f})"
                return FollowCommand(0.0, 0.0, FollowState.NO_TAG, why)
            lost_s = t_s - self.lost_since_s
            if lost_s < cfg.search_after_s or search_bearing_rad is None:
                return FollowCommand(
                    0.0, 0.0, FollowState.LOST, f"no person track for {lost_s:.1f} s: stopped"
                )
            turn = math.copysign(cfg.search_turn_radps, search_bearing_rad if search_bearing_rad else 1.0)
            return FollowCommand(
                0.0,
                turn,
                FollowState.LOST,
                f"searching: turning toward the RFID bearing {math.degrees(search_bearing_rad):.0f} deg",
            )
        self.lost_since_s = None
        cmd = self._follow(robot, person)
        if occluded and unseen_s > cfg.grace_s:
            return FollowCommand(
                cmd.v_mps * cfg.occluded_speed_factor,
                cmd.omega_radps,
                cmd.state,
                f"occluded for {unseen_s:.2f} s: coasting on the prediction",
                cmd.distance_m,
            )
        return cmd

    def _follow(self, robot: Pose, person: PersonEstimate) -> FollowCommand:
        cfg = self.config
        dx, dy = person.xy[0] - robot[0], person.xy[1] - robot[1]
        dist = math.hypot(dx, dy)
        bearing = math.remainder(math.atan2(dy, dx) - robot[2], math.tau)
        omega = _clip(cfg.gain_heading * bearing, -cfg.max_turn_radps, cfg.max_turn_radps)
        ux, uy = (dx / dist, dy / dist) if dist > 1e-6 else (math.cos(robot[2]), math.sin(robot[2]))
        along = person.velocity[0] * ux + person.velocity[1] * uy  # the person's speed away from the robot
        error = dist - cfg.distance_m
        if person.speed_mps < cfg.standing_mps and error < cfg.tolerance_m:
            return FollowCommand(
                0.0,
                omega if abs(bearing) > 0.2 else 0.0,
                FollowState.WAITING,
                "the person stands: waiting at the distance",
                dist,
            )
        if dist < cfg.min_gap_m:
            return FollowCommand(
                0.0, omega, FollowState.FOLLOWING, "too near the person: not closing in", dist
            )
        v = cfg.gain_distance * error + max(along, 0.0)
        # Turn first when they are well off to the side (out of the camera's view), slow down on the way.
        v = 0.0 if abs(bearing) > cfg.turn_first_rad else v * math.cos(bearing) ** 2
        v = _clip(v, 0.0, cfg.max_speed_mps)
        return FollowCommand(v, omega, FollowState.FOLLOWING, "keeping the distance", dist)


class WalkerMode(enum.StrEnum):
    """The walker check's standing decision, kept from step to step (:func:`walker_decision`)."""

    GO = "go"  # driving on: clear of the walkers, or crossing in front of one (committed)
    YIELD = "yield"  # stopped to let a walker pass: stays stopped until a speed is clear with a margin


def walker_decision(
    speeds: Sequence[float],
    gaps: Sequence[float],
    *,
    v_mps: float,
    faster: Sequence[float],
    previous: WalkerMode,
    clearance_m: float,
    keep_m: float = math.inf,
    resume_m: float | None = None,
    hit_m: float = 0.35,
) -> tuple[float, WalkerMode]:
    """The speed to drive at among ``speeds`` (the follower's ``v_mps`` first, then each of ``faster``,
    then slower ones, then 0 last) given each one's predicted least gap to the walkers (``gaps``, centre to
    centre, :func:`predicted_gaps`), and the decision it stands for. A hysteresis on the decision to yield:

    * ``GO`` (driving on): the follower's speed or the first faster one that keeps more than
      ``clearance_m``; else, committed to crossing in front, the one of them whose gap stays above
      ``keep_m`` (the best, the slowest of equals); else the first slower one that keeps
      ``clearance_m``; else standing when it keeps it (``YIELD``): a dip of the prediction
      under ``clearance_m`` (a few centimetres of track noise, the person's pace between a camera bearing
      and a scan) does not turn a crossing into a stop in the walker's way and back, step after step;
      else a faster speed clearly (5 cm) better than standing (out of the walker's way rather than
      stopped in it); else 0, ``YIELD``;
    * ``YIELD`` (stopped for a walker): the first moving speed that keeps more than ``resume_m`` (default
      ``clearance_m``); else standing when it keeps it; else, only when standing itself comes within
      ``hit_m`` (the walker walks into the robot: contact is at 0.305 m), a faster speed clearly better
      than standing; else 0: it lets the walker pass. (A few hundredths of a m/s of the walker's
      velocity toward the robot, noise, put standing under ``keep_m`` and the escape drove the robot
      into the walker's way.)

    With ``keep_m`` = inf and ``previous`` = ``GO`` this is the plain check of :func:`safe_speed`. Pure."""
    if len(speeds) != len(gaps) or not speeds or speeds[-1] != 0.0:
        raise ValueError("speeds and gaps must align, with standing (0) last")
    resume = clearance_m if resume_m is None else resume_m
    need = clearance_m if previous is WalkerMode.GO else resume
    ahead = [(v, g) for v, g in zip(speeds, gaps, strict=True) if v > 0.0 and (v == v_mps or v in faster)]
    slower = [(v, g) for v, g in zip(speeds[:-1], gaps[:-1], strict=True) if (v, g) not in ahead]
    for v, gap in ahead:
        if gap > need:
            return v, WalkerMode.GO
    if previous is WalkerMode.GO and ahead:
        # Committed: a crossing in front under way is kept before slowing down or stopping is considered
        # (a slower speed or a stop "clear" by the prediction is not, for a robot driving into the
        # walker's way at speed, and alternating them was the flip of issue 23).
        top = max(g for _, g in ahead)
        if top > keep_m:
            # The slowest as good as the best (within 1 cm): once the robot is close behind its person every
            # speed drives at their pace in the prediction, and a faster command only closes in.
            return min(v for v, g in ahead if g >= top - 0.01), WalkerMode.GO
    for v, gap in slower:
        if gap > need:
            return v, WalkerMode.GO
    standing = gaps[-1]
    if standing > need:
        return 0.0, WalkerMode.YIELD
    if previous is WalkerMode.GO or standing <= hit_m:
        best, best_gap = 0.0, -math.inf
        for v, gap in zip(speeds, gaps, strict=True):
            if gap > best_gap + 0.05:  # a faster escape must be clearly better than standing or slower
                best, best_gap = v, gap
        if best_gap > 0.0 and best in faster:
            return best, WalkerMode.GO
    return 0.0, WalkerMode.YIELD


def safe_speed(
    pose: Pose,
    v_mps: float,
    walkers: npt.NDArray[np.float64],
    clearance_m: float,
    horizon_s: float = 2.5,
    dt_s: float = 0.1,
    fractions: tuple[float, ...] = (1.0, 0.66, 0.33),
    *,
    faster: tuple[float, ...] = (),
    lead: tuple[float, float, float] | None = None,
) -> float:
    """The first speed of ``v_mps``, then each of ``faster`` (absolute speeds, tried in order), then
    ``v_mps`` x each of ``fractions`` at which the robot keeps more than ``clearance_m`` (centre to centre)
    from every walker (rows x, y, vx, vy in the map frame, walking on at their velocity) over ``horizon_s``;
    0 when none does. The robot drives straight on at the speed; with ``lead`` = (the followed person's
    distance ahead along the heading, their speed along it, the nearest the robot comes to them) it drives
    at the speed only until it is that near, then at the person's pace behind them. A walker who crosses
    far ahead is let pass or crossed in front of, by when they get there, rather than waited for as their
    whole sweep would have it; one who would cut between the robot and its person is crossed in front of by
    closing up on the person (``faster``) when that keeps clear. When no speed keeps clear, a faster one
    that keeps clearly further (5 cm) than standing is taken: the robot drives on out of the walker's path
    rather than stopping in it; otherwise 0 (the caller then steps aside). Memoryless: the follow loop
    keeps its decision from step to step with :func:`walker_decision`."""
    if v_mps <= 0.0 or len(walkers) == 0:
        return v_mps
    speeds = walker_candidates(v_mps, faster, fractions)
    gaps = predicted_gaps(pose, speeds, walkers, horizon_s, dt_s, lead)
    v, _ = walker_decision(
        speeds, gaps.tolist(), v_mps=v_mps, faster=faster, previous=WalkerMode.GO, clearance_m=clearance_m
    )
    return v


def walker_candidates(
    v_mps: float, faster: Sequence[float], fractions: Sequence[float] = (1.0, 0.66, 0.33)
) -> list[float]:
    """The speeds the walker check tries, in order: ``v_mps``, each of ``faster`` above it, ``v_mps`` x
    each of ``fractions`` below 1, standing (0) last."""
    return [v_mps, *(f for f in faster if f > v_mps), *(v_mps * f for f in fractions if f < 1.0), 0.0]


def predicted_gaps(
    pose: Pose,
    speeds: list[float],
    walkers: npt.NDArray[np.float64],
    horizon_s: float,
    dt_s: float = 0.1,
    lead: tuple[float, float, float] | None = None,
) -> npt.NDArray[np.float64]:
    """Per speed of ``speeds``: the least distance between the robot's centre and any walker's (rows x, y,
    vx, vy, walking on at their velocity) over ``horizon_s``, the robot driving straight on at that speed
    (with ``lead``, as in :func:`safe_speed`, only until it is that near its person, then at their pace);
    ``inf`` with no walker."""
    if len(walkers) == 0:
        return np.full(len(speeds), math.inf)
    tau = np.arange(0.0, horizon_s + 1e-9, dt_s)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    wx = walkers[:, 0:1] + walkers[:, 2:3] * tau  # (n, t)
    wy = walkers[:, 1:2] + walkers[:, 3:4] * tau
    limit = None
    if lead is not None:
        ahead, pace, nearest = lead
        limit = max(ahead - nearest, 0.0) + max(pace, 0.0) * tau
    out = np.empty(len(speeds))
    for i, v in enumerate(speeds):
        d = v * tau if limit is None else np.minimum(v * tau, limit)
        rx, ry = pose[0] + c * d, pose[1] + s * d
        out[i] = float(np.min(np.hypot(wx - rx, wy - ry)))
    return out


def walker_threat(
    pose: Pose,
    walkers: npt.NDArray[np.float64],
    clearance_m: float,
    horizon_s: float = 2.5,
    dt_s: float = 0.1,
) -> bool:
    """Whether a walker (rows x, y, vx, vy), walking on at their velocity, comes within ``clearance_m`` of
    the robot standing at ``pose`` over ``horizon_s``: standing still will not keep it clear, it must step
    aside."""
    if len(walkers) == 0:
        return False
    tau = np.arange(0.0, horizon_s + 1e-9, dt_s)
    wx = walkers[:, 0:1] + walkers[:, 2:3] * tau
    wy = walkers[:, 1:2] + walkers[:, 3:4] * tau
    return float(np.min(np.hypot(wx - pose[0], wy - pose[1]))) <= clearance_m
