"""The mission loop: local missions inside the running agent, exploring (``agent.exploration``'s configured
explorer) and going to named places, driven through the navigation as *mission goals*.

Missions come as commands (``ExploreCommand``, ``PlaceCommand``: the serial link's explore and go-to-place
frames, docs/wire-format.md, or ``vlp-agent sim --explore`` / ``--deliver``). :meth:`MissionLoop.take`
answers each at once, from the command loop's thread: REJECTED with a clear reason when it cannot be done
now (a stop in force: STOPPED; no pose: NOT_LOCALIZED; a place it does not know: UNKNOWN_PLACE; a map
with no free cell: NO_FREE_SPACE; the robot inside an obstacle on the map with no free cell within
``ESCAPE_M``: START_BLOCKED; a controller's velocity or goal in force, or another mission running: BUSY),
else ACCEPTED. A mission ends with a status of its own ``mission_id``: REACHED (explored, or at the place
and back), FAILED with the reason (a leg's navigation failure; EXPLORED when exploration gave up on
reachable space), or CANCELLED. Whatever is rejected leaves the robot as it was (stopped, or driving what
it drove); whatever fails stops it (the navigation's goal ends, and nothing else drives).

The loop's own thread, every ``period_s``:

* keeps the newest SLAM map (:meth:`on_map`, from the SLAM loop every ``map_period_s``, beside the
  navigation's) and learns the end of each mission goal from the goal statuses the agent sends
  (:meth:`on_status`, a listener on the command loop's answers);
* **exploring**: after start it first **looks around**: ``LOOK_AROUND_TURNS`` goals in place, a third of
  a turn each (unknown space allowed: at the start the map is one scan). The SLAM filter integrates a scan
  only every ``angular_update_rad`` of turn or ``linear_update_m`` of travel, and the map image calls a
  cell free only after about four misses (``free_thresh`` 0.196 at ``miss`` -0.4): a robot that has not
  moved has a map of unknown cells, no frontier it can reach and no target to move to. Then it calls
  ``explorer.update`` with the map and the fused pose and hands each new target to the command arbiter
  as a mission goal (driven only while the controller drives nothing, checked as a controller's goal). A
  target's end goes back to the explorer: REACHED -> ``report_reached``; FAILED or REJECTED ->
  ``report_failed`` with the reason; CANCELLED (the controller took over) -> the exploration pauses;
* **going to a place**: one mission goal per leg (the place; with ``come_back``, then where the robot was
  when the command came).

No pose (localization lost): no update, nothing new is sent (the navigation loop drives zero without a
pose). The loop decides and keeps state; the arbiter, the navigation loop and the wheels' dead-man drive.

**The topological map** (:meth:`topology`, for the map saver, which writes it beside the occupancy map;
format: docs/exploration.md): the sp2atm explorer's HTM (a copy taken on this loop's thread every
``TOPOLOGY_EVERY_S`` while exploring), or for an explorer without one the rooms of the last map; with the
named places (the caller's and the config's ``[[exploration.places]]``) as named PLACE nodes naming their
rooms. :meth:`load_topology` takes a saved one back at start: its named places (and rooms) become places
missions can go to, so a robot restarted on its saved map still knows them.
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from agent.exploration import Command, Explorer, ExploreState, GridMap
from agent.navigation.config import NavConfig
from agent.navigation.costmap import Costmap
from agent.runtime.arbiter import CommandArbiter
from agent.runtime.health import Heartbeat
from agent.runtime.navigation_loop import static_layers
from agent.slam.render import OccupancyImage
from firmware_protocol.command_frame import (
    NO_SEQUENCE,
    ExploreAction,
    ExploreCommand,
    GoalCommand,
    GoalReason,
    GoalState,
    GoalStatus,
    PlaceCommand,
)

__all__ = ["ESCAPE_M", "LOOK_AROUND_TURNS", "MISSION_GOAL_IDS", "MissionLoop", "NamedPlace"]

log = logging.getLogger(__name__)

Pose = tuple[float, float, float]
# The goals a mission hands the navigation are numbered here, apart from the controller's ids.
MISSION_GOAL_IDS = range(0xC000, 0xFFFF)
LOOK_AROUND_TURNS = 3  # goals in place, a third of a turn each, after start
ESCAPE_M = 0.3  # a robot inside an obstacle's footprint needs a free cell this close (the planner's escape)
TOPOLOGY_EVERY_S = 5.0  # the explorer's HTM is copied for the map saver this often while exploring

_ACTIONS = {
    ExploreAction.START: Command.START,
    ExploreAction.PAUSE: Command.PAUSE,
    ExploreAction.RESUME: Command.RESUME,
    ExploreAction.RETURN_HOME: Command.RETURN_HOME,
    ExploreAction.CANCEL: Command.CANCEL,
}


@dataclass(frozen=True)
class NamedPlace:
    """A place a mission can go to (the world file's ``[[places]]`` in the simulator)."""

    name: str
    x_m: float
    y_m: float
    yaw_rad: float | None = None


@dataclass
class _Route:
    mission_id: int
    legs: list[tuple[float, float, float | None]]
    sent: bool = False  # the current leg's goal has been handed over
    done: int = 0  # legs reached


class MissionLoop:
    def __init__(
        self,
        explorer: Explorer,
        nav: NavConfig,
        arbiter: CommandArbiter,
        answer: Callable[[GoalStatus], None],
        pose: Callable[[], Pose | None],
        clock_ns: Callable[[], int] = time.monotonic_ns,
        *,
        places: Mapping[str, NamedPlace] | None = None,
        period_s: float = 0.1,
    ) -> None:
        self.explorer = explorer
        self.nav = nav
        self.arbiter = arbiter
        self.answer = answer
        self.pose = pose
        self.clock_ns = clock_ns
        self.places = dict(places or {})
        self.period_s = period_s
        self.counts: collections.Counter[str] = collections.Counter()
        self.decision_ms: collections.deque[float] = collections.deque(maxlen=4096)
        self.last_grid: GridMap | None = None
        # How each mission ended, by mission id (the status sent), for a caller that waits on one.
        self.ended: dict[int, GoalStatus] = {}
        # Told (mission id, leg index) when a go-to-place leg is reached (the simulator reads the truth).
        self.on_leg: Callable[[int, int], None] | None = None
        self._lock = threading.Lock()
        self._commands: list[Command] = []
        self._outcomes: list[GoalStatus] = []
        self._goal_id: int | None = None  # the mission goal in force (ours)
        self._look: list[float] = []  # headings still to turn to in place before exploring
        self._looking = False  # the goal in force is one of them
        self._next_id = MISSION_GOAL_IDS.start
        self._explore_id: int | None = None  # the explore mission running, if any
        self._route: _Route | None = None  # the go-to-place mission running, if any
        self._htm_copy: dict[str, Any] | None = None  # the explorer's HTM as GeoJSON, taken on this thread
        self._t_htm = -math.inf

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
        """Ask for an exploration lifecycle command; applied at the next pass (with the pose of then)."""
        with self._lock:
            self._commands.append(command)

    def take(self, command: ExploreCommand | PlaceCommand) -> GoalStatus:
        """A mission command: its answer, at once (see the module docstring)."""
        seq, mission = command.sequence, command.mission_id

        def reply(state: GoalState, reason: GoalReason = GoalReason.NONE) -> GoalStatus:
            self.counts[f"mission_{state.name.lower()}_{reason.name.lower()}"] += 1
            return self.arbiter.mission_status(seq, mission, state, reason)

        if isinstance(command, ExploreCommand) and command.action is not ExploreAction.START:
            with self._lock:
                running = self._explore_id is not None
            if not running:
                return reply(GoalState.REJECTED, GoalReason.UNKNOWN_GOAL)
            self.command(_ACTIONS[command.action])
            return reply(GoalState.ACCEPTED)
        if self.arbiter.stopped:
            return reply(GoalState.REJECTED, GoalReason.STOPPED)
        if self.arbiter.controller_in_force:
            return reply(GoalState.REJECTED, GoalReason.BUSY)
        place = None
        if isinstance(command, PlaceCommand):
            place = self.places.get(command.place)
            if place is None:
                return reply(GoalState.REJECTED, GoalReason.UNKNOWN_PLACE)
        pose = self.pose()
        if pose is None:
            return reply(GoalState.REJECTED, GoalReason.NOT_LOCALIZED)
        with self._lock:
            grid = self.last_grid
            busy = self._explore_id is not None or self._route is not None
        if busy:
            return reply(GoalState.REJECTED, GoalReason.BUSY)
        # Exploring starts from a map of unknown cells (the look-around fills it): only a robot inside an
        # obstacle is refused; a place needs a map with free space to plan in.
        if place is not None or grid is not None:
            why = self._map_problem(grid, pose)
            if why is not None and (place is not None or why is GoalReason.START_BLOCKED):
                return reply(GoalState.REJECTED, why)
        if place is None:
            with self._lock:
                self._explore_id = mission
            self.command(Command.START)
        else:
            assert isinstance(command, PlaceCommand)
            legs: list[tuple[float, float, float | None]] = [(place.x_m, place.y_m, place.yaw_rad)]
            if command.come_back:
                legs.append(pose)
            with self._lock:
                self._route = _Route(mission, legs)
        return reply(GoalState.ACCEPTED)

    def _map_problem(self, grid: GridMap | None, pose: Pose) -> GoalReason | None:
        """NO_FREE_SPACE (no map, or no free cell in it) or START_BLOCKED (the robot inside an obstacle's
        footprint with no free cell within ``ESCAPE_M``), or None."""
        if grid is None or not np.any(grid.free):
            return GoalReason.NO_FREE_SPACE
        costmap = Costmap(grid.spec, grid.occupied, np.zeros_like(grid.unknown), self.nav)
        spec = grid.spec
        cost = costmap.cost(allow_unknown=True)
        cell = spec.to_cell(np.array([pose[0], pose[1]]))[0]
        if not spec.inside(cell[None, :])[0]:
            return GoalReason.START_BLOCKED
        reach = math.ceil(ESCAPE_M / spec.resolution_m)
        r0, c0 = max(int(cell[0]) - reach, 0), max(int(cell[1]) - reach, 0)
        window = cost[r0 : int(cell[0]) + reach + 1, c0 : int(cell[1]) + reach + 1]
        if not np.isfinite(window).any():
            return GoalReason.START_BLOCKED
        return None

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
            self._apply(command, pose, t_s)
        for status in outcomes:
            self._outcome(status, pose, t_s)
        with self._lock:
            route = self._route
        if route is not None:
            self._drive_route(route, t_s)
            return
        self._explore(grid, pose, t_s)

    def _apply(self, command: Command, pose: Pose, t_s: float) -> None:
        if not self.explorer.command(command, pose, t_s):
            self.counts[f"command_{command.value}_refused"] += 1
            return
        self.counts[f"command_{command.value}"] += 1
        if command is not Command.RESUME:
            self._cancel_goal()
            self._look = []
        if command is Command.START:
            step = 2.0 * math.pi / LOOK_AROUND_TURNS
            self._look = [pose[2] + step * (k + 1) for k in range(LOOK_AROUND_TURNS)]
        if command is Command.CANCEL:
            self._end_explore(GoalState.CANCELLED, GoalReason.NONE)

    def _explore(self, grid: GridMap | None, pose: Pose, t_s: float) -> None:
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
            if t_s - self._t_htm >= TOPOLOGY_EVERY_S or self.explorer.state is not ExploreState.EXPLORING:
                self._copy_htm(t_s)
        if decision.new_target:
            if decision.target is None:
                self._cancel_goal()
            else:
                self._send(decision.target.x_m, decision.target.y_m, decision.target.yaw_rad, t_s)
        if self.explorer.state is ExploreState.COMPLETE:
            self._end_explore(GoalState.REACHED, GoalReason.NONE)
        elif self.explorer.state is ExploreState.FAILED:
            self._end_explore(GoalState.FAILED, GoalReason.EXPLORED)
        elif self.explorer.state is ExploreState.IDLE:
            # Home again before it was finished (return home), or cancelled: the mission is over.
            self._end_explore(GoalState.CANCELLED, GoalReason.NONE)

    def _end_explore(self, state: GoalState, reason: GoalReason) -> None:
        with self._lock:
            mission, self._explore_id = self._explore_id, None
        if mission is not None:
            self._finish(mission, state, reason)

    def _finish(self, mission: int, state: GoalState, reason: GoalReason) -> None:
        status = self.arbiter.mission_status(NO_SEQUENCE, mission, state, reason)
        self.ended[mission] = status
        self.counts[f"missions_{state.name.lower()}"] += 1
        self.answer(status)

    def _drive_route(self, route: _Route, t_s: float) -> None:
        if route.sent or self._goal_id is not None:
            return
        if not route.legs:
            with self._lock:
                self._route = None
            self._finish(route.mission_id, GoalState.REACHED, GoalReason.NONE)
            return
        x, y, yaw = route.legs[0]
        route.sent = self._send(x, y, yaw, t_s, leg=route)

    def _outcome(self, status: GoalStatus, pose: Pose, t_s: float) -> None:
        with self._lock:
            self._goal_id = None
            route = self._route
        if route is not None:
            route.sent = False
            if status.state is GoalState.REACHED:
                self.counts["legs_reached"] += 1
                route.legs.pop(0)
                if self.on_leg is not None:
                    self.on_leg(route.mission_id, route.done)
                route.done += 1
                return
            with self._lock:
                self._route = None
            state = GoalState.CANCELLED if status.state is GoalState.CANCELLED else GoalState.FAILED
            self._finish(route.mission_id, state, status.reason)
            return
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

    def _send(
        self,
        x_m: float,
        y_m: float,
        yaw_rad: float | None,
        t_s: float,
        look: bool = False,
        leg: _Route | None = None,
    ) -> bool:
        """Hand a mission goal to the arbiter; False if it was rejected."""
        self._cancel_goal()
        goal_id = self._next_id
        self._next_id = goal_id + 1 if goal_id + 1 < MISSION_GOAL_IDS.stop else MISSION_GOAL_IDS.start
        # A turn in place may start in cells the map does not know yet; targets and places are known.
        goal = GoalCommand(NO_SEQUENCE, goal_id, x_m, y_m, yaw_rad, allow_unknown=look)
        with self._lock:
            self._goal_id = goal_id
        self._looking = look
        status = self.arbiter.mission_goal(goal)
        what = "look_around" if look else "legs" if leg is not None else "targets"
        self.counts[f"{what}_sent"] += 1
        self.answer(status)  # to the controller too: it sees what the robot is driving to, and why not
        if status.state is not GoalState.REJECTED:
            return True
        with self._lock:
            self._goal_id = None
        self._looking = False
        self.counts[f"{what}_rejected_{status.reason.name.lower()}"] += 1
        if leg is not None:
            if status.reason is not GoalReason.NOT_LOCALIZED:  # a passing lack of pose: tried again
                with self._lock:
                    self._route = None
                self._finish(leg.mission_id, GoalState.FAILED, status.reason)
        elif look and status.reason is not GoalReason.NOT_LOCALIZED:
            self._look = []  # a turn here is refused (not for a passing lack of pose): explore as it is
        elif not look:
            self.explorer.report_failed(f"rejected: {status.reason.name.lower()}", t_s)
        return False

    def _cancel_goal(self) -> None:
        with self._lock:
            goal_id, self._goal_id = self._goal_id, None
        if goal_id is not None:
            status = self.arbiter.cancel_mission(goal_id)
            if status is not None:
                self.answer(status)

    # -- the topological map ------------------------------------------------------------------------

    def _copy_htm(self, t_s: float) -> None:
        make = getattr(self.explorer, "topology", None)
        if make is None:
            return
        data = make()
        with self._lock:
            self._htm_copy, self._t_htm = data, t_s

    def topology(self) -> dict[str, Any] | None:
        """The topological map to save beside the occupancy map (any thread; see the module docstring);
        None when there is neither a graph nor a map nor a named place yet."""
        from agent.exploration.htm import Htm
        from agent.exploration.regions import find_regions
        from agent.exploration.topology import add_named_places, from_geojson, to_geojson

        with self._lock:
            data, grid, places = self._htm_copy, self.last_grid, dict(self.places)
        if data is not None:
            htm = from_geojson(data)
        else:
            htm = Htm()
            if grid is not None:
                cfg = getattr(self.explorer, "config", None)
                door, area = (cfg.door_width_m, cfg.min_region_m2) if cfg is not None else (1.2, 1.0)
                _, regions = find_regions(grid, door, area)
                htm.set_regions([(r.polygon, r.area_m2) for r in regions])
        if not htm.nodes and not places:
            return None
        add_named_places(htm, [(p.name, p.x_m, p.y_m) for p in places.values()])
        return to_geojson(htm, map_name="vlp-agent")

    def load_topology(self, data: dict[str, Any]) -> list[str]:
        """Take the named places (and named rooms, at their centres) of a saved topological map as
        places missions can go to; a place the caller named already keeps the caller's position. The
        names taken."""
        from agent.exploration.topology import from_geojson, named_places

        found = named_places(from_geojson(data))
        taken: list[str] = []
        with self._lock:
            for name, (x, y) in found.items():
                if name not in self.places:
                    self.places[name] = NamedPlace(name, x, y)
                    taken.append(name)
        return taken

    def run(self, beat: Heartbeat, stop: threading.Event) -> None:
        while not stop.is_set():
            beat.beat()
            self.step()
            stop.wait(self.period_s)
        self._cancel_goal()

    # -- what it did --------------------------------------------------------------------------------

    @property
    def exploration_ended(self) -> bool:
        return self.explorer.state in (ExploreState.COMPLETE, ExploreState.FAILED)

    def status(self) -> dict[str, Any]:
        ms = list(self.decision_ms)
        return {
            "state": self.explorer.state.value,
            "reason": self.explorer.reason,
            "complete": self.explorer.state is ExploreState.COMPLETE,
            "decision_ms_median": round(float(np.median(ms)), 2) if ms else None,
            "retries": getattr(self.explorer, "retries", 0),
            "blocked_branches": len(getattr(self.explorer, "blocked_branches", ())),
            **dict(self.counts),
        }
