"""Recovery when the robot is blocked: wait, rotate, back up, each followed by a fresh plan; give up
after a bound.

A small state machine, pure (time and pose are passed in, a velocity comes out):

* :meth:`Recovery.begin` starts the next round; rounds go through ``SEQUENCE`` (wait, rotate, back up,
  wait, ...), so a person who lingers is waited for first, a robot boxed in by stale marks looks
  around (the laser clears them), and one wedged against something backs off;
* :meth:`Recovery.step` gives the round's command until it is done (``None``); the navigator then clears
  the costmap's obstacle layer and replans;
* after ``max_recoveries`` rounds without real progress in between (:meth:`Recovery.progressed` resets
  the count once the robot has made ``RESET_PROGRESS_M`` of way), :meth:`Recovery.exhausted` is true and
  the goal fails with the reason it was blocked and the rounds that were tried.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from agent.navigation.config import NavConfig
from agent.navigation.controller import Command, wrap

# Way made along the path after which the recovery count starts again.
RESET_PROGRESS_M = 1.0
BACKUP_SPEED_MPS = 0.05
TURN_SPEED_RADPS = 0.8
# A rotation or back-up that cannot finish (the collision monitor holds it) ends after this long.
ACTION_TIMEOUT_S = 8.0


class Action(enum.StrEnum):
    WAIT = "wait"
    ROTATE = "rotate"
    BACK_UP = "back_up"


SEQUENCE = (Action.WAIT, Action.ROTATE, Action.BACK_UP, Action.WAIT)


@dataclass
class _Round:
    action: Action
    t_start_s: float
    start_pose: tuple[float, float, float]
    turned_rad: float = 0.0
    last_yaw_rad: float = 0.0


class Recovery:
    def __init__(self, config: NavConfig) -> None:
        self.config = config
        self.rounds = 0
        self.history: list[str] = []  # "why: action" per round, for the failure's reason
        self._round: _Round | None = None

    def reset(self) -> None:
        self.rounds = 0
        self.history.clear()
        self._round = None

    @property
    def active(self) -> bool:
        return self._round is not None

    @property
    def action(self) -> Action | None:
        return self._round.action if self._round else None

    def abort(self) -> None:
        """End the round in progress (it still counts)."""
        self._round = None

    def exhausted(self) -> bool:
        return self.rounds >= self.config.max_recoveries

    def progressed(self, way_m: float) -> None:
        if way_m >= RESET_PROGRESS_M:
            self.rounds = 0

    def begin(self, t_s: float, pose: tuple[float, float, float], why: str) -> Action:
        action = SEQUENCE[self.rounds % len(SEQUENCE)]
        self.rounds += 1
        self.history.append(f"{why}: {action.value}")
        self._round = _Round(action, t_s, pose, last_yaw_rad=pose[2])
        return action

    def step(self, t_s: float, pose: tuple[float, float, float], backward_clear: bool) -> Command | None:
        """The round's command now, or None when the round is over."""
        r = self._round
        if r is None:
            return None
        cfg = self.config
        elapsed = t_s - r.t_start_s
        done = False
        command = Command(0.0, 0.0)
        if r.action is Action.WAIT:
            done = elapsed >= cfg.wait_s
        elif r.action is Action.ROTATE:
            r.turned_rad += abs(wrap(pose[2] - r.last_yaw_rad))
            r.last_yaw_rad = pose[2]
            left = cfg.rotate_rad - r.turned_rad
            done = left <= math.radians(2.0) or elapsed >= ACTION_TIMEOUT_S
            command = Command(0.0, min(TURN_SPEED_RADPS, max(left, 0.2)))
        else:
            moved = math.hypot(pose[0] - r.start_pose[0], pose[1] - r.start_pose[1])
            done = moved >= cfg.backup_m or not backward_clear or elapsed >= ACTION_TIMEOUT_S
            command = Command(-min(BACKUP_SPEED_MPS, cfg.max_reverse_mps), 0.0)
        if done:
            self._round = None
            return None
        return command

    def reason(self, why: str) -> str:
        tried = ", ".join(self.history) if self.history else "none"
        return f"{why}; gave up after {self.rounds} recoveries ({tried})"
