"""What every explorer is: one interface (``Explorer``), an explicit lifecycle with the reason for the
state it is in, and the decision it hands the driver each cycle.

States (``ExploreState``) and the commands that move between them (anything else is refused, the state
unchanged; the explorer's own progress moves it from EXPLORING to RETURNING, COMPLETE or FAILED):

| from \\ command | start | pause | resume | return_home | cancel |
|---|---|---|---|---|---|
| idle | exploring | | | returning | |
| exploring | | paused | | returning | idle |
| paused | | | exploring | returning | idle |
| returning | | paused | | | idle |
| complete | exploring | | | returning | |
| failed | exploring | | | returning | |

"complete" means no reachable frontier is left (an explorer never says it while one is); "failed" means
reachable space is left that the robot could not get to, with the reason. The driver (the agent's mission
loop, or ``vlp-agent eval explore``) calls ``update`` every cycle with the map, the pose and the time,
drives to the target it gets back (none: stand still), and reports what became of each target.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from agent.exploration.frontiers import Frontier, GridMap
from agent.navigation.costmap import FloatArray


class ExploreState(enum.StrEnum):
    IDLE = "idle"
    EXPLORING = "exploring"
    PAUSED = "paused"
    RETURNING = "returning"
    COMPLETE = "complete"
    FAILED = "failed"


class Command(enum.StrEnum):
    START = "start"
    PAUSE = "pause"
    RESUME = "resume"
    RETURN_HOME = "return_home"
    CANCEL = "cancel"


S, C = ExploreState, Command
TRANSITIONS: dict[tuple[ExploreState, Command], ExploreState] = {
    (S.IDLE, C.START): S.EXPLORING,
    (S.IDLE, C.RETURN_HOME): S.RETURNING,
    (S.EXPLORING, C.PAUSE): S.PAUSED,
    (S.EXPLORING, C.RETURN_HOME): S.RETURNING,
    (S.EXPLORING, C.CANCEL): S.IDLE,
    (S.PAUSED, C.RESUME): S.EXPLORING,
    (S.PAUSED, C.RETURN_HOME): S.RETURNING,
    (S.PAUSED, C.CANCEL): S.IDLE,
    (S.RETURNING, C.PAUSE): S.PAUSED,
    (S.RETURNING, C.CANCEL): S.IDLE,
    (S.COMPLETE, C.START): S.EXPLORING,
    (S.COMPLETE, C.RETURN_HOME): S.RETURNING,
    (S.FAILED, C.START): S.EXPLORING,
    (S.FAILED, C.RETURN_HOME): S.RETURNING,
}
del S, C

# States in which the robot is meant to be still.
STOPPED = frozenset({ExploreState.IDLE, ExploreState.PAUSED, ExploreState.COMPLETE, ExploreState.FAILED})


@dataclass(frozen=True)
class Target:
    x_m: float
    y_m: float
    yaw_rad: float | None = None  # facing the unknown it is meant to see; None: any


@dataclass(frozen=True)
class Decision:
    """One cycle's answer. ``target`` None: stand still. ``new_target``: it differs from the last one
    (send it to the navigator). ``decided``: the map was searched this cycle (``decision_ms`` is its wall
    time, ``decision_cpu_ms`` its CPU time; otherwise 0). ``frontiers``: what that search found (empty
    when it did not run)."""

    state: ExploreState
    target: Target | None
    reason: str
    new_target: bool = False
    decided: bool = False
    decision_ms: float = 0.0
    decision_cpu_ms: float = 0.0  # this thread's CPU time for the search (what one core spent)
    frontiers: tuple[Frontier, ...] = field(default=())


class Explorer(Protocol):
    """The interface every explorer (frontier, SP2ATM) offers its driver."""

    # Optional: where the evidence of a shut passage comes from when a failure is reported without it
    # (``report_failed``); the driver sets it (e.g. the navigator's obstacle layer as points, metres).
    evidence: Callable[[], FloatArray | None] | None

    @property
    def state(self) -> ExploreState: ...

    @property
    def reason(self) -> str: ...

    def command(self, command: Command, pose: tuple[float, float, float], t_s: float) -> bool:
        """Apply a lifecycle command (``TRANSITIONS``); False, state unchanged, when it does not apply."""
        ...

    def update(self, grid: GridMap, pose: tuple[float, float, float], t_s: float) -> Decision:
        """One cycle: the map as it is now, the robot's estimated pose, the time."""
        ...

    def report_reached(self, t_s: float) -> None:
        """The navigator reached the current target (position and heading)."""
        ...

    def report_failed(self, reason: str, t_s: float, obstacles_m: FloatArray | None = None) -> None:
        """The navigator gave up on the current target; ``obstacles_m``: the (N, 2) points (metres) the
        sensors see occupied now, if the driver has them (evidence of a passage shut: the branch is
        pruned at once instead of retried)."""
        ...
