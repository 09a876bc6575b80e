"""The exploration loop: the configured explorer (``agent.exploration``) inside the running agent.

It keeps the newest SLAM map (:meth:`ExplorationLoop.on_map`, from the SLAM loop every ``map_period_s``,
beside the navigation's), and in a thread of its own (decisions cost tens of milliseconds of CPU, too much
for the command loop's 10 ms poll) every ``period_s``:

1. applies the lifecycle commands asked for (:meth:`command`: start, pause, resume, return_home, cancel).
   After start it first **looks around**: ``LOOK_AROUND_TURNS`` mission goals in place, each turning the
   robot a third of a turn (unknown space allowed: at the start the map is one scan). The SLAM filter
   integrates a scan only every ``angular_update_rad`` of turn or ``linear_update_m`` of travel, and the
   map image calls a cell free only after about four misses (``free_thresh`` 0.196 at ``miss`` -0.4): a
   robot that has not moved has a map of unknown cells, no frontier to reach and no target to move to.
   One turn in place integrates ~30 scans all round;
2. tells the explorer what became of its last target, from the goal statuses the agent sent
   (:meth:`on_status`, a listener on the command loop's answers): REACHED -> ``report_reached``;
   FAILED or REJECTED -> ``report_failed`` with the reason; CANCELLED (the controller took over with a
   goal, a velocity or a stop) -> the exploration pauses, to be resumed;
3. calls ``explorer.update`` with the map and the fused pose, and hands a new target to the command
   arbiter as a *mission goal* (``CommandArbiter.mission_goal``: driven only while the controller drives
   nothing, checked like a controller's goal), or cancels the mission goal when there is none.

No pose (localization lost): no update, nothing new is sent (the navigation loop drives zero without a
pose). The loop decides and keeps state; the arbiter, the navigation loop and the wheels' dead-man do the
driving. :meth:`status` is what it has done, for the agent's summary.
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from agent.exploration import Command, Explorer, ExploreState, GridMap
from agent.runtime.arbiter import CommandArbiter
from agent.runtime.health import Heartbeat
from agent.runtime.navigation_loop import static_layers
from agent.slam.render import OccupancyImage
from firmware_protocol.command_frame import NO_SEQUENCE, GoalCommand, GoalReason, GoalState, GoalStatus

__all__ = ["MISSION_GOAL_IDS", "ExplorationLoop"]

log = logging.getLogger(__name__)

Pose = tuple[float, float, float]
# Mission goals are numbered here, apart from the controller's (which count up from 1).
MISSION_GOAL_IDS = range(0xC000, 0xFFFF)
LOOK_AROUND_TURNS = 3  # goals in place, a third of a turn each, after start


class ExplorationLoop:
    def __init__(
        self,
        explorer: Explorer,
        arbiter: CommandArbiter,
        answer: Callable[[GoalStatus], None],
        pose: Callable[[], Pose | None],
        clock_ns: Callable[[], int] = time.monotonic_ns,
        *,
        period_s: float = 0.1,
    ) -> None:
        self.explorer = explorer
        self.arbiter = arbiter
        self.answer = answer
        self.pose = pose
        self.clock_ns = clock_ns
        self.period_s = period_s
        self.counts: collections.Counter[str] = collections.Counter()
        self.decision_ms: collections.deque[float] = collections.deque(maxlen=4096)
        self.last_grid: GridMap | None = None
        self._lock = threading.Lock()
        self._commands: list[Command] = []
        self._outcomes: list[GoalStatus] = []
        self._goal_id: int | None = None  # the mission goal in force (ours)
        self._look: list[float] = []  # headings still to turn to in place before exploring
        self._looking = False  # the goal in force is one of them
        self._next_id = MISSION_GOAL_IDS.start

    # -- inputs (other threads) ---------------------------------------------------------------------

    def on_map(self, image: OccupancyImage) -> None:
        spec, occupied, unknown = static_layers(image)
        with self._lock:
            self.last_grid = GridMap(spec, occupied, unknown)
            self.counts["maps"] += 1

    def on_status(self, status: GoalStatus) -> None:
        """Every goal status the agent sends; those ending our mission goal are passed on."""
        if status.state in (GoalState.ACCEPTED, GoalState.ACTIVE, GoalState.REJECTED):
            return  # a rejection answers the mission goal's sending, handled there
        with self._lock:
            if status.goal_id == self._goal_id:
                self._outcomes.append(status)

    def command(self, command: Command) -> None:
        """Ask for a lifecycle command; applied at the next pass (with the pose of then)."""
        with self._lock:
            self._commands.append(command)

    # -- the pass -----------------------------------------------------------------------------------

    def step(self) -> None:
        pose = self.pose()
        t_s = self.clock_ns() * 1e-9
        if pose is None:
            # Localization lost: commands and outcomes wait for a pose; nothing new is sent.
            self.counts["passes_without_pose"] += 1
            return
        with self._lock:
            commands, self._commands = self._commands, []
            outcomes, self._outcomes = self._outcomes, []
            grid = self.last_grid
        for command in commands:
            if self.explorer.command(command, pose, t_s):
                self.counts[f"command_{command.value}"] += 1
                if command is not Command.RESUME:
                    self._cancel_goal()
                    self._look = []
                if command is Command.START:
                    step = 2.0 * math.pi / LOOK_AROUND_TURNS
                    self._look = [pose[2] + step * (k + 1) for k in range(LOOK_AROUND_TURNS)]
            else:
                self.counts[f"command_{command.value}_refused"] += 1
        for status in outcomes:
            self._outcome(status, pose, t_s)
        if grid is None:
            return  # no map yet (nor a navigator)
        if (self._look or self._looking) and self.explorer.state is ExploreState.EXPLORING:
            if self._goal_id is None and self._look:
                yaw = math.remainder(self._look[0], 2.0 * math.pi)
                if self._send(pose[0], pose[1], yaw, t_s, look=True):
                    self._look.pop(0)
            return
        decision = self.explorer.update(grid, pose, t_s)
        if decision.decided:
            self.counts["decisions"] += 1
            self.decision_ms.append(decision.decision_ms)
        if decision.new_target:
            if decision.target is None:
                self._cancel_goal()
            else:
                self._send(decision.target.x_m, decision.target.y_m, decision.target.yaw_rad, t_s)

    def _outcome(self, status: GoalStatus, pose: Pose, t_s: float) -> None:
        with self._lock:
            self._goal_id = None
        if self._looking:
            self._looking = False
            if status.state is GoalState.REACHED:
                self.counts["look_around_turns"] += 1
                return
            self.counts[f"look_around_{status.state.name.lower()}"] += 1
            self._look = []  # exploring with what has been seen
            if status.state is GoalState.CANCELLED:
                self.explorer.command(Command.PAUSE, pose, t_s)
            return
        if status.state is GoalState.REACHED:
            self.counts["targets_reached"] += 1
            self.explorer.report_reached(t_s)
        elif status.state is GoalState.CANCELLED:
            # The controller took over (a goal, a velocity, a stop): exploring waits to be resumed.
            self.counts["targets_cancelled"] += 1
            self.explorer.command(Command.PAUSE, pose, t_s)
        else:
            self.counts["targets_failed"] += 1
            self.explorer.report_failed(f"navigation: {status.reason.name.lower()}", t_s)

    def _send(self, x_m: float, y_m: float, yaw_rad: float | None, t_s: float, look: bool = False) -> bool:
        """Hand a mission goal to the arbiter; False if it was rejected."""
        self._cancel_goal()
        goal_id = self._next_id
        self._next_id = goal_id + 1 if goal_id + 1 < MISSION_GOAL_IDS.stop else MISSION_GOAL_IDS.start
        # A turn in place may start in cells the map does not know yet; a target is in known free space.
        goal = GoalCommand(NO_SEQUENCE, goal_id, x_m, y_m, yaw_rad, allow_unknown=look)
        with self._lock:
            self._goal_id = goal_id
        self._looking = look
        status = self.arbiter.mission_goal(goal)
        self.counts["look_around_sent" if look else "targets_sent"] += 1
        self.answer(status)  # to the controller too: it sees what the robot is driving to, and why not
        if status.state is GoalState.REJECTED:
            with self._lock:
                self._goal_id = None
            self._looking = False
            what = "look_around" if look else "targets"
            self.counts[f"{what}_rejected_{status.reason.name.lower()}"] += 1
            if look and status.reason is not GoalReason.NOT_LOCALIZED:
                self._look = []  # a turn here is refused (not a passing lack of pose): explore as it is
            elif not look:
                self.explorer.report_failed(f"rejected: {status.reason.name.lower()}", t_s)
            return False
        return True

    def _cancel_goal(self) -> None:
        with self._lock:
            goal_id, self._goal_id = self._goal_id, None
        if goal_id is not None:
            status = self.arbiter.cancel_mission(goal_id)
            if status is not None:
                self.answer(status)

    def run(self, beat: Heartbeat, stop: threading.Event) -> None:
        while not stop.is_set():
            beat.beat()
            self.step()
            stop.wait(self.period_s)
        self._cancel_goal()

    # -- what it did --------------------------------------------------------------------------------

    @property
    def ended(self) -> bool:
        return self.explorer.state in (ExploreState.COMPLETE, ExploreState.FAILED)

    def status(self) -> dict[str, Any]:
        ms = list(self.decision_ms)
        return {
            "state": self.explorer.state.value,
            "reason": self.explorer.reason,
            "complete": self.explorer.state is ExploreState.COMPLETE,
            "decision_ms_median": round(float(np.median(ms)), 2) if ms else None,
            **dict(self.counts),
        }
