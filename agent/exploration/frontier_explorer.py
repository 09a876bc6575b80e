"""The frontier explorer: explore_lite's algorithm (reference/eco.md §1.2) with its cost defect fixed.

Each decision (when there is no target, when the last one ended, and every ``replan_period_s`` while
driving):

1. the map, with the robot's own footprint known free (it stands there; behind a 240° laser it is
   otherwise unknown at the start);
2. frontiers (``agent.exploration.frontiers``): free cells next to unknown, 8-connected clusters, short
   ones dropped;
3. one Dijkstra from the robot over the navigation costmap of that map (``agent.navigation``: unknown
   cells forbidden, the footprint inflated, edges cost length (1 + w c)): the path cost to every cell at
   once, with clearance, never through unknown space (eco.md §1.3: scoring through unknown cells lets
   routes shortcut through unmapped space);
4. a frontier's targets are the cells within ``target_reach_m`` of it the robot can reach and that no
   blacklist entry covers; its target is the cheapest of them;
5. cost = ``potential_scale`` x path cost (m) - ``gain_scale`` x frontier length (m), lowest first.

   explore_lite computes ``potential_scale * min_distance * resolution - gain_scale * size * resolution``
   with ``min_distance`` already in metres: the distance term is scaled down again by the resolution
   (20x at 5 cm), so frontier size dominates and the robot criss-crosses the building towards the
   largest frontier. Here both terms are in metres, and the distance is the path's, not a straight line;
6. hysteresis: the current target is kept unless its frontier is gone or another is cheaper by
   ``switch_margin``.

The target's heading faces the unknown cells near it, so that on arrival the laser looks at what the
frontier hid. A target the robot reached (heading included) that still borders unknown space is
blacklisted for good as unobservable (that spot's cells are no target again; the rest of the frontier
still is); a target the navigator failed, or with no ``progress_m`` of
approach for ``progress_timeout_s``, is blacklisted with an expiry (``agent.exploration.blacklist``),
unless the driver hands over the sensors' evidence with the failure (``report_failed``'s ``obstacles_m``)
and it shows the way shut wall to wall since the map saw it open (``agent.exploration.closure``: a door
that closed) and the target unreachable behind it: then the branch is pruned at this first failure, the
closure kept over the map from then on (everything behind it unreachable, not waiting), a permanent
BLOCKED entry at the target, and it is never retried (``blocked_branches``, ``retries``).

The end: no reachable frontier outside the blacklist. If reachable frontiers remain only under expiring
entries, the explorer waits (EXPLORING, no target); only under entries given up for good: FAILED with the
reason; none at all: COMPLETE (or RETURNING first, with ``return_home``). A robot whose own cell cannot be
placed on the costmap never concludes anything.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csgraph

from agent.exploration.blacklist import Blacklist, EntryKind
from agent.exploration.closure import wall_to_wall
from agent.exploration.config import ExploreConfig
from agent.exploration.frontiers import Frontier, GridMap, detect_frontiers, dilate, disk
from agent.exploration.lifecycle import STOPPED, TRANSITIONS, Command, Decision, ExploreState, Target
from agent.navigation.config import NavConfig
from agent.navigation.costmap import BoolArray, Costmap, FloatArray, GridSpec
from agent.navigation.planner import build_graph

log = logging.getLogger(__name__)

Pose = tuple[float, float, float]
ESCAPE_M = 0.3  # a robot standing in an inflated cell is searched from the nearest free cell this close
SEE_M = 1.5  # a target faces the unknown cells within this of it
SETTLE_S = 0.5  # after arriving, the map gets this long (a few scans) before the spot is judged


@dataclass(frozen=True)
class Candidate:
    frontier: Frontier
    target: Target
    path_m: float
    cost: float


@dataclass(frozen=True)
class Field:
    """What one decision's search computed on the map, for an explorer built on this one (SP2ATM): the
    map with the robot's footprint known free, the path cost (m) from the robot to every cell (inf:
    unreachable) and the cells with room for a target."""

    seen: GridMap
    path_m: FloatArray
    roomy: BoolArray


@dataclass(frozen=True)
class Survey:
    """One decision's look at the map."""

    frontiers: tuple[Frontier, ...]
    best: Candidate | None
    candidates: tuple[Candidate, ...]
    waiting: int  # reachable frontiers whose every target is blacklisted for now
    given_up: int  # ... blacklisted for good as unreachable
    unreachable: int  # frontiers with no reachable target at all
    placed: bool  # the robot's cell could be put on the costmap


class FrontierExplorer:
    def __init__(self, config: ExploreConfig, nav: NavConfig) -> None:
        self.config = config
        self.nav = nav
        self.blacklist = Blacklist(config.blacklist_radius_m, config.blacklist_expiry_s, config.max_failures)
        self._state = ExploreState.IDLE
        self._reason = "not started"
        self.home: tuple[float, float, float] | None = None
        self.target: Target | None = None
        self._sent: Target | None = None
        self._t_decided = -math.inf
        self._best_distance = math.inf
        self._t_progress = 0.0
        self._arrived: tuple[Target, float] | None = None
        self._finished = False  # exploration ended complete (returning home afterwards)
        self._wanted = True  # a decision is due now, not at the next replan period
        self.decisions = 0
        self.field: Field | None = None  # the last search's map, path costs and roomy cells
        self.retries = 0  # targets chosen again where one had failed before
        self.switches = 0  # targets replaced by another before they were reached or failed
        self.blocked_branches: list[dict[str, object]] = []  # branches pruned for a passage shut
        self.closed_m: FloatArray = np.zeros((0, 2))  # cells (centres, metres) of passages seen shut
        self._pose: Pose | None = None
        self._target_frontier: Frontier | None = None  # the frontier the current target is to see
        self.shut_path_m: FloatArray | None = None  # path costs with the last closure found over the map
        # Where the evidence comes from when a failure is reported without it (the explorer's own progress
        # timeout, or a driver that passes none): the driver sets it, e.g. to the navigator's obstacle layer.
        self.evidence: Callable[[], FloatArray | None] | None = None

    @property
    def state(self) -> ExploreState:
        return self._state

    @property
    def reason(self) -> str:
        return self._reason

    # -- lifecycle ---------------------------------------------------------------------------------------
    def command(self, command: Command, pose: Pose, t_s: float) -> bool:
        after = TRANSITIONS.get((self._state, command))
        if after is None:
            log.info("exploration: %s refused in state %s", command.value, self._state.value)
            return False
        if command is Command.START:
            self.home = pose
            self._finished = False
        if command is Command.RETURN_HOME and self.home is None:
            self.home = pose
        self._set(after, f"{command.value} at t={t_s:.1f} s")
        self.target = None
        self._arrived = None
        self._wanted = True
        if after is ExploreState.RETURNING:
            assert self.home is not None
            self._aim(Target(self.home[0], self.home[1], self.home[2]), pose, t_s)
        return True

    def _set(self, state: ExploreState, reason: str) -> None:
        if state is not self._state or reason != self._reason:
            log.info("exploration: %s (%s)", state.value, reason)
        self._state, self._reason = state, reason

    # -- reports from the driver -----------------------------------------------------------------------
    def report_reached(self, t_s: float) -> None:
        if self.target is None:
            return
        if self._state is ExploreState.RETURNING:
            self._arrive_home()
            return
        self._arrived = (self.target, t_s)
        self.target = None
        self._wanted = True

    def report_failed(self, reason: str, t_s: float, obstacles_m: FloatArray | None = None) -> None:
        """The navigator gave up on the target. ``obstacles_m``: (N, 2) points, metres, the robot's
        sensors see occupied now (the navigator's obstacle layer), the evidence a passage was shut."""
        if self.target is None:
            return
        if self._state is ExploreState.RETURNING:
            self._set(ExploreState.FAILED, f"could not return home: {reason}")
            self.target = None
            return
        if obstacles_m is None and self.evidence is not None:
            obstacles_m = self.evidence()
        shut = self._shut(obstacles_m) if obstacles_m is not None else None
        if shut is not None:
            self._prune(shut, reason, t_s)
            self.target = None
            self._wanted = True
            return
        entry = self.blacklist.add((self.target.x_m, self.target.y_m), t_s, reason)
        self._wanted = True
        log.info(
            "exploration: target (%.2f, %.2f) blacklisted (%s, %d failures)",
            entry.x_m,
            entry.y_m,
            reason,
            entry.failures,
        )
        self.target = None

    def _shut(self, obstacles_m: FloatArray) -> BoolArray | None:
        """The cells of a passage the evidence shows shut wall to wall that cut the way to the current
        target (None: no such evidence; an ordinary failure)."""
        field, pose, target = self.field, self._pose, self.target
        if field is None or pose is None or target is None:
            return None
        seen = field.seen
        closure = wall_to_wall(
            seen, obstacles_m, [(target.x_m, target.y_m), (pose[0], pose[1])], self.nav.radius_m
        )
        if not closure.any():
            return None
        occupied = seen.occupied | closure | self._closed_cells(seen.spec)
        costmap = Costmap(seen.spec, occupied, seen.unknown, self.nav)
        path_m = self._path_costs(costmap, pose)
        if path_m is None:
            return None  # the robot itself cannot be placed: no conclusion
        cell = seen.spec.to_cell(np.array([target.x_m, target.y_m]))[0]
        if not seen.spec.inside(cell[None, :])[0]:
            return None
        distance = costmap.distance_m()
        if np.isfinite(path_m[cell[0], cell[1]]) and distance[cell[0], cell[1]] >= self.nav.inscribed_m:
            return None  # shut there, but the target is still reachable another way
        frontier = self._target_frontier
        if frontier is not None:
            # A target that only stood too close to a wall the map had missed is no branch shut: the
            # frontier it served still has targets the robot reaches with room.
            reach = max(round(self.config.target_reach_m / seen.spec.resolution_m), 0)
            near = np.zeros(seen.spec.shape, dtype=bool)
            near[frontier.cells[:, 0], frontier.cells[:, 1]] = True
            near = dilate(near, reach)
            roomy = distance >= self.nav.inscribed_m + self.config.target_clearance_m
            if np.any(near & np.isfinite(path_m) & roomy):
                return None
        self.shut_path_m = path_m
        return closure

    def _prune(self, closure: BoolArray, reason: str, t_s: float) -> None:
        """Keep the closure over the map from now on, blacklist the target for good as BLOCKED."""
        assert self.target is not None and self.field is not None
        spec = self.field.seen.spec
        points = spec.to_world(np.argwhere(closure))
        self.closed_m = np.concatenate([self.closed_m, points])
        why = f"blocked: a passage seen shut wall to wall ({len(points)} cells) after {reason}"
        entry = self.blacklist.add((self.target.x_m, self.target.y_m), t_s, why, EntryKind.BLOCKED)
        centre = points.mean(axis=0)
        self.blocked_branches.append(
            {
                "t_s": round(t_s, 1),
                "target": [round(self.target.x_m, 2), round(self.target.y_m, 2)],
                "closure_centre": [round(float(centre[0]), 2), round(float(centre[1]), 2)],
                "closure_cells": len(points),
                "failure": reason,
                "failures_before": entry.failures - 1,
            }
        )
        log.info(
            "exploration: target (%.2f, %.2f) pruned at its first failure with evidence (%s): a passage "
            "seen shut at (%.2f, %.2f), %d cells; blacklisted for good",
            self.target.x_m,
            self.target.y_m,
            reason,
            centre[0],
            centre[1],
            len(points),
        )
        self._on_pruned()

    def _on_pruned(self) -> None:
        """Called after a branch was pruned (``blocked_branches[-1]``), before the target is dropped."""

    def _closed_cells(self, spec: GridSpec) -> BoolArray:
        out = np.zeros(spec.shape, dtype=bool)
        if len(self.closed_m):
            cells = spec.to_cell(self.closed_m)
            cells = cells[spec.inside(cells)]
            out[cells[:, 0], cells[:, 1]] = True
        return out

    def _arrive_home(self) -> None:
        self.target = None
        if self._finished:
            self._set(ExploreState.COMPLETE, "explored, and back where it started")
        else:
            self._set(ExploreState.IDLE, "back where it started; exploration not finished")

    # -- the cycle ---------------------------------------------------------------------------------------
    def update(self, grid: GridMap, pose: Pose, t_s: float) -> Decision:
        if self._state in STOPPED:
            self.target = None
            return self._decision()
        if self._state is ExploreState.RETURNING:
            if self.target is not None:
                if (
                    math.hypot(self.target.x_m - pose[0], self.target.y_m - pose[1])
                    <= self.config.target_reached_m
                ):
                    self._arrive_home()
                else:
                    self._watch_progress(pose, t_s)
            return self._decision()
        self._pose = pose
        self._watch_progress(pose, t_s)
        # Decide at once when a target has ended (or none was ever given); otherwise every replan period,
        # also while waiting with no target (a blacklist entry to expire, a robot to be placed).
        due = self._wanted or t_s - self._t_decided >= self.config.replan_period_s
        if self._arrived is not None and t_s - self._arrived[1] < SETTLE_S:
            return self._decision()  # let the scans at the arrival heading into the map first
        if not due:
            return self._decision()
        started, started_cpu = time.perf_counter(), time.thread_time()
        survey = self.survey(grid, pose, t_s)
        self.decisions += 1
        self._t_decided = t_s
        self._wanted = False
        if self._judge_arrival(survey, t_s):
            survey = self.survey(grid, pose, t_s)
        self._choose(survey, pose, t_s)
        if self.target is not None and self.evidence is not None and self._state is ExploreState.EXPLORING:
            # Seen shut on the way (a door that closed since the map saw it open): pruned now, not after
            # a failure and a retry.
            hits = self.evidence()
            shut = self._shut(hits) if hits is not None else None
            if shut is not None:
                self._prune(shut, "seen shut on the way", t_s)
                self.target = None
                self._wanted = True
        ms = (time.perf_counter() - started) * 1000.0
        cpu_ms = (time.thread_time() - started_cpu) * 1000.0
        return self._decision(True, ms, cpu_ms, survey.frontiers)

    def _decision(
        self,
        decided: bool = False,
        decision_ms: float = 0.0,
        decision_cpu_ms: float = 0.0,
        frontiers: tuple[Frontier, ...] = (),
    ) -> Decision:
        new = self.target != self._sent
        self._sent = self.target
        return Decision(
            self._state, self.target, self._reason, new, decided, decision_ms, decision_cpu_ms, frontiers
        )

    def _watch_progress(self, pose: Pose, t_s: float) -> None:
        if self.target is None:
            return
        distance = math.hypot(self.target.x_m - pose[0], self.target.y_m - pose[1])
        if distance < self._best_distance - self.config.progress_m:
            self._best_distance = distance
            self._t_progress = t_s
        elif t_s - self._t_progress > self.config.progress_timeout_s:
            self.report_failed(f"no progress for {self.config.progress_timeout_s:g} s", t_s)

    def _aim(self, target: Target, pose: Pose, t_s: float) -> None:
        if self._state is not ExploreState.RETURNING and self.blacklist.failed_near((target.x_m, target.y_m)):
            self.retries += 1
            log.info(
                "exploration: retrying at (%.2f, %.2f), a target failed there before", target.x_m, target.y_m
            )
        self.target = target
        self._best_distance = math.hypot(target.x_m - pose[0], target.y_m - pose[1])
        self._t_progress = t_s

    def _judge_arrival(self, survey: Survey, t_s: float) -> bool:
        """A spot reached facing its frontier that still borders unknown space is not worth a return;
        True if it was blacklisted."""
        if self._arrived is None:
            return False
        spot, _ = self._arrived
        self._arrived = None
        reach = self.config.target_reach_m + self.config.target_reached_m
        for f in survey.frontiers:
            if np.any(np.hypot(f.points_m[:, 0] - spot.x_m, f.points_m[:, 1] - spot.y_m) <= reach):
                self.blacklist.add(
                    (spot.x_m, spot.y_m), t_s, "reached, still unknown", EntryKind.UNOBSERVABLE
                )
                return True
        return False

    def _choose(self, survey: Survey, pose: Pose, t_s: float) -> None:
        cfg = self.config
        if not survey.placed:
            self._set(ExploreState.EXPLORING, "the robot's own cell is blocked on the map; waiting")
            return
        best = survey.best
        if best is None:
            self.target = None
            if survey.waiting:
                self._set(
                    ExploreState.EXPLORING,
                    f"{survey.waiting} reachable frontiers blacklisted for now; waiting",
                )
                return
            if survey.given_up:
                self._set(
                    ExploreState.FAILED,
                    f"{survey.given_up} reachable frontiers could not be reached after "
                    f"{cfg.max_failures} tries",
                )
                return
            unobservable = len(self.blacklist.permanent(EntryKind.UNOBSERVABLE))
            why = (
                f"no reachable frontier left ({survey.unreachable} unreachable frontiers, "
                f"{unobservable} unobservable spots)"
            )
            self._finished = True
            if cfg.return_home and self.home is not None:
                self._set(ExploreState.RETURNING, why + "; returning home")
                self._aim(Target(*self.home), pose, t_s)
            else:
                self._set(ExploreState.COMPLETE, why)
            return
        current = self._current_cost(survey)
        switch = current is None or best.cost < current - cfg.switch_margin
        here = None if self.target is None else (self.target.x_m, self.target.y_m)
        if switch and (best.target.x_m, best.target.y_m) != here:
            if self.target is not None:
                self.switches += 1
            self._aim(best.target, pose, t_s)
            self._target_frontier = best.frontier
        self._set(ExploreState.EXPLORING, f"{len(survey.candidates)} reachable frontiers")

    def _current_cost(self, survey: Survey) -> float | None:
        """The cost of the frontier the current target belongs to, if it is still there."""
        if self.target is None:
            return None
        reach = self.config.target_reach_m + self.nav.resolution_m
        for c in survey.candidates:
            d = np.hypot(
                c.frontier.points_m[:, 0] - self.target.x_m, c.frontier.points_m[:, 1] - self.target.y_m
            )
            if np.any(d <= reach):
                return c.cost
        return None

    # -- the search --------------------------------------------------------------------------------------
    def survey(self, grid: GridMap, pose: Pose, t_s: float) -> Survey:
        """Frontiers, their reachable targets and costs (steps 1-5 of the module docstring)."""
        cfg, nav = self.config, self.nav
        spec = grid.spec
        body = disk(spec, (pose[0], pose[1]), nav.radius_m)
        occupied = (grid.occupied | self._closed_cells(spec)) & ~body
        unknown = grid.unknown & ~body
        seen = GridMap(spec, occupied, unknown)
        frontiers = tuple(detect_frontiers(seen, cfg.min_frontier_size_m, cfg.min_unknown_m2))
        costmap = Costmap(spec, occupied, unknown, nav)
        path_m = self._path_costs(costmap, pose)
        if path_m is None:
            self.field = None
            return Survey(frontiers, None, (), 0, 0, len(frontiers), False)
        reach_cells = max(round(cfg.target_reach_m / spec.resolution_m), 0)
        # A target with room round it: the navigator's costmap adds the scans' marks (noise on walls, a
        # person), and a target right at the forbidden edge would fail there at once.
        roomy = costmap.distance_m() >= nav.inscribed_m + cfg.target_clearance_m
        self.field = Field(seen, path_m, roomy)
        rows, cols = spec.shape
        candidates: list[Candidate] = []
        waiting = given_up = unreachable = 0
        for f in frontiers:
            r0, c0 = f.cells.min(axis=0) - reach_cells
            r1, c1 = f.cells.max(axis=0) + reach_cells + 1
            r0, c0, r1, c1 = max(int(r0), 0), max(int(c0), 0), min(int(r1), rows), min(int(c1), cols)
            mask = np.zeros((r1 - r0, c1 - c0), dtype=bool)
            mask[f.cells[:, 0] - r0, f.cells[:, 1] - c0] = True
            near = dilate(mask, reach_cells)
            window = path_m[r0:r1, c0:c1]
            ok = near & np.isfinite(window) & roomy[r0:r1, c0:c1]
            if not ok.any():
                unreachable += 1
                continue
            cells = np.argwhere(ok) + np.array([r0, c0])
            points = spec.to_world(cells)
            costs = window[ok]
            # Spots the robot stood at, facing this frontier, and saw nothing more from: their cells are
            # no targets, the rest of the frontier still is (a long frontier is not done because one
            # end of it could not be seen past). Every target looked at already: nothing left here.
            fresh = ~(
                self.blacklist.blocked(points, t_s, kind=EntryKind.UNOBSERVABLE)
                | self.blacklist.blocked(points, t_s, kind=EntryKind.BLOCKED)
            )
            if not fresh.any():
                continue
            points, costs = points[fresh], costs[fresh]
            # explore_lite's rule for failures: a frontier is passed over while its cheapest target lies
            # within an entry's radius (from elsewhere its cheapest target moves, and is tried from there).
            i = int(np.argmin(costs))
            spot = points[i : i + 1]
            if self.blacklist.blocked(spot, t_s, kind=EntryKind.UNREACHED)[0]:
                if self.blacklist.blocked(spot, t_s, permanent_only=True, kind=EntryKind.UNREACHED)[0]:
                    given_up += 1
                else:
                    waiting += 1
                continue
            tx, ty = float(points[i, 0]), float(points[i, 1])
            target = Target(tx, ty, self._facing(seen, (tx, ty), f))
            cost = cfg.potential_scale * float(costs[i]) - cfg.gain_scale * f.length_m
            candidates.append(Candidate(f, target, float(costs[i]), cost))
        candidates.sort(key=lambda c: c.cost)
        best = candidates[0] if candidates else None
        return Survey(frontiers, best, tuple(candidates), waiting, given_up, unreachable, True)

    def _path_costs(self, costmap: Costmap, pose: Pose) -> FloatArray | None:
        """Path cost in metres (length (1 + w c)) from the robot to every cell; None if the robot cannot be
        placed (its cell and every cell within ``ESCAPE_M`` forbidden)."""
        spec = costmap.spec
        cost = costmap.cost(allow_unknown=False)
        cell = spec.to_cell(np.array([pose[0], pose[1]]))[0]
        if not spec.inside(cell[None, :])[0]:
            return None
        if not np.isfinite(cost[cell[0], cell[1]]):
            around = disk(spec, (pose[0], pose[1]), ESCAPE_M) & np.isfinite(cost)
            if not around.any():
                return None
            options = np.argwhere(around)
            cell = options[np.argmin(np.hypot(*(options - cell).T))]
        graph = build_graph(cost, self.nav.clearance_weight)
        root = int(graph.node_of[int(cell[0]) * spec.shape[1] + int(cell[1])])
        distances = csgraph.dijkstra(graph.matrix, directed=True, indices=root)
        out = np.full(spec.shape, np.inf)
        out.reshape(-1)[graph.cells] = distances * spec.resolution_m
        return out

    @staticmethod
    def _facing(grid: GridMap, xy: tuple[float, float], frontier: Frontier) -> float | None:
        """The heading from ``xy`` to the unknown cells within ``SEE_M`` of it (to the frontier's centroid
        if none are that close)."""
        spec = grid.spec
        res = spec.resolution_m
        k = math.ceil(SEE_M / res)
        cell = spec.to_cell(np.array(xy))[0]
        r0, c0 = max(int(cell[0]) - k, 0), max(int(cell[1]) - k, 0)
        r1, c1 = min(int(cell[0]) + k + 1, spec.shape[0]), min(int(cell[1]) + k + 1, spec.shape[1])
        unknown = np.argwhere(grid.unknown[r0:r1, c0:c1]) + np.array([r0, c0])
        if len(unknown):
            pts = spec.to_world(unknown)
            close = np.hypot(pts[:, 0] - xy[0], pts[:, 1] - xy[1]) <= SEE_M
            if close.any():
                aim = pts[close].mean(axis=0)
                if math.hypot(aim[0] - xy[0], aim[1] - xy[1]) > res:
                    return math.atan2(aim[1] - xy[1], aim[0] - xy[0])
        cx, cy = frontier.centroid_m
        if math.hypot(cx - xy[0], cy - xy[1]) > res:
            return math.atan2(cy - xy[1], cx - xy[0])
        return None
