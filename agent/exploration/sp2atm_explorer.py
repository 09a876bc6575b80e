"""The SP2ATM explorer (reference/eco.md §1.1, with the improvements of its "recipe"): the admissible space
tree's gaps and the grid's frontiers together as candidates, the hierarchical topology map (HTM) as memory,
REGION nodes (rooms) at doorways, target choice by path cost with clearance minus information gain, and
Bellman-Ford backtracking over the HTM.

Each decision (when the last target ended, and every ``replan_period_s`` while driving; the lifecycle,
progress watch, blacklist and the end are the frontier explorer's, which this one extends):

1. the frontier explorer's search: the map with the robot's footprint known free, the frontiers, one
   Dijkstra from the robot over the navigation costmap (clearance-weighted, unknown cells forbidden) and
   each frontier's cheapest reachable target;
2. the **current place**: the PLACE node within ``place_spacing_m`` of the robot, or a new one there
   (anchored to a new pose id, linked to the last place by the distance driven);
3. the **AST**: a 360° scan cast on the map from the robot (``admissible_tree.grid_scan``: a beam is open
   where unknown space begins) and its gaps' branches (``scan_branches``); each tip is a possible node;
4. the **possible-node filter** (step 3 of §1.1): a tip is kept only if the robot can reach its cell
   with room to spare (the Dijkstra's cost is finite, the cell clear of the footprint by
   ``target_clearance_m``), no blacklist entry covers it, and it has information to gain: at least
   ``min_frontier_size_m`` of frontier within ``gain_radius_m`` (a tip in the explored interior has none),
   counting only frontier cells beside unknown space that survives a 3 x 3 opening (a sliver of unknown
   one or two cells wide between a far scan's beams has frontier on both sides and nothing behind it),
   and only frontier in sight of the candidate (``in_sight``: no wall between; the frontier of the room
   behind a wall is no gain for a spot on this side);
   the frontiers' targets pass the same gain test;
5. the **HTM** (``htm.Htm``): tips are appended / rebound from the current place (an edge as long as the
   branch); each frontier's target is bound to the nearest place that sees it in a straight line (an
   edge that long), else to the current place (an edge costing the path); POSSIBLE nodes no candidate
   was bound to this time are **removed** (their gap explored, or blocked, or blacklisted);
6. **regions** (``regions.find_regions``): rooms cut at doorways narrower than ``door_width_m``, their ids
   and names kept as the map grows (``Htm.set_regions``); every node knows its room;
7. the **choice**: every candidate costs ``potential_scale`` x path cost (m) - ``gain_scale`` x gain (m
   of frontier within ``gain_radius_m``): both metres, as the frontier explorer's. SP2ATM's rule, with
   the room level first: the cheapest candidate in the robot's room (finish a room before leaving it;
   one elsewhere wins only when it is cheaper by ``locality_m``; a region touching more than
   ``ROOM_MAX_DOORS`` others is a hub, a corridor, not a room to finish); none there: the cheapest
   POSSIBLE child of the current place; none: **backtrack**: Bellman-Ford over the HTM from the current
   place to the nearest place that still has POSSIBLE children, and the cheapest of those (the navigator
   drives there on the grid); none connected: the cheapest of all;
8. hysteresis as the frontier explorer's: the current target is kept unless the new one is cheaper by
   ``switch_margin``.

A target reached makes its POSSIBLE node a PLACE (the robot stood there). Nodes are anchored to pose ids
(``anchors`` / ``correct_poses``): when SLAM corrects the poses, the HTM moves with them.

The end is the frontier explorer's: complete only when no candidate of either kind is left and no
reachable frontier is waiting out a blacklist entry.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from agent.exploration.admissible_tree import grid_scan, scan_branches, to_world
from agent.exploration.blacklist import EntryKind
from agent.exploration.config import ExploreConfig
from agent.exploration.frontier_explorer import Candidate, FrontierExplorer, Pose, Survey
from agent.exploration.frontiers import GridMap, dilate
from agent.exploration.htm import Htm, NodeKind
from agent.exploration.lifecycle import Command, Decision, ExploreState, Target
from agent.exploration.regions import find_regions
from agent.exploration.topology import to_geojson
from agent.navigation.config import NavConfig
from agent.navigation.costmap import BoolArray, FloatArray, IntArray, segment_cells

log = logging.getLogger(__name__)

LOOKED_HALF_ANGLE = math.radians(100.0)  # a reached target's heading +- this is what the laser showed there
REGIONS_EVERY_S = 4.0  # the rooms are re-found this often (and whenever a target has ended)
ROOM_MAX_DOORS = 2  # a region touching more regions than this is a hub (a corridor), not a room to finish


@dataclass(frozen=True)
class NodeCandidate(Candidate):
    """A candidate with where it came from (``ast`` or ``frontier``), its gain (m of frontier near it)
    and the HTM node it was bound to."""

    source: str = "frontier"
    gain_m: float = 0.0
    node: int = -1


class Sp2atmExplorer(FrontierExplorer):
    def __init__(self, config: ExploreConfig, nav: NavConfig) -> None:
        super().__init__(config, nav)
        self.htm = Htm(config.merge_m)
        self.place: int | None = None  # the current place
        self.labels: IntArray | None = None  # the last region label image (0: none, k: region_ids[k-1])
        self.region_ids: list[int] = []
        self.neighbours_of_region: dict[int, int] = {}  # region id -> how many regions it touches
        self.backtracks = 0
        self._slivers_now = 0  # frontier targets passed over as slivers in the last search
        self._next_pose = 0
        self._driven_m = 0.0  # since the current place
        self._last_xy: tuple[float, float] | None = None
        self._target_node: int | None = None
        self._t_regions = -math.inf
        self._wanted_regions = True
        # Frontier a reached target was to show and did not: (spot x, y, heading or None), and the
        # informative frontier points of the last search (for the arrival's judgement).
        self._looked: list[tuple[float, float, float | None]] = []
        self._gain_points: FloatArray = np.zeros((0, 2))

    # -- SLAM coupling ---------------------------------------------------------------------------------
    @property
    def anchors(self) -> dict[int, tuple[float, float, float]]:
        """The pose ids the HTM's nodes are kept relative to, and those poses as last known."""
        return dict(self.htm.poses)

    def correct_poses(self, poses: dict[int, tuple[float, float, float]]) -> int:
        """SLAM corrected these poses: move the nodes anchored to them; the number moved."""
        return self.htm.reproject(poses)

    def topology(self, frame: str = "map", date: str = "", map_name: str = "") -> dict[str, object]:
        """The HTM as the topological map file's GeoJSON (``agent.exploration.topology``)."""
        return to_geojson(self.htm, frame, date, map_name)

    # -- the cycle ---------------------------------------------------------------------------------------
    def command(self, command: Command, pose: Pose, t_s: float) -> bool:
        ok = super().command(command, pose, t_s)
        if ok:
            self._target_node = None
        return ok

    def update(self, grid: GridMap, pose: Pose, t_s: float) -> Decision:
        if self._last_xy is not None:
            self._driven_m += math.hypot(pose[0] - self._last_xy[0], pose[1] - self._last_xy[1])
        self._last_xy = (pose[0], pose[1])
        return super().update(grid, pose, t_s)

    def report_reached(self, t_s: float) -> None:
        self._wanted_regions = True
        node = self._target_node
        target = self.target
        super().report_reached(t_s)
        if target is None or node is None or node not in self.htm.nodes:
            return
        if self.htm.nodes[node].kind is not NodeKind.POSSIBLE:
            return
        # The robot stands there: the POSSIBLE node becomes a PLACE, at the robot's own pose.
        n = self.htm.nodes[node]
        n.x_m, n.y_m = target.x_m, target.y_m
        self.htm.visit(node)
        pid = self._new_pose((target.x_m, target.y_m, target.yaw_rad or 0.0))
        self.htm.anchor(node, pid)
        self._enter(node)
        self._target_node = None

    def _on_pruned(self) -> None:
        """A branch shut with evidence is cut from the HTM at once: the target's POSSIBLE node and every
        POSSIBLE node the robot cannot reach with the closure over the map
        (``blocked_branches[-1]["htm_nodes_pruned"]``)."""
        node = self._target_node
        pruned: list[int] = []
        path_m, field = self.shut_path_m, self.field
        for n in self.htm.possible():
            if n == node:
                pruned.append(n)
                continue
            if path_m is None or field is None:
                continue
            x = self.htm.nodes[n]
            cell = field.seen.spec.to_cell(np.array([x.x_m, x.y_m]))[0]
            if field.seen.spec.inside(cell[None, :])[0] and not np.isfinite(path_m[cell[0], cell[1]]):
                pruned.append(n)
        for n in pruned:
            self.htm.remove(n)
        self.blocked_branches[-1]["htm_nodes_pruned"] = len(pruned)
        self._target_node = None

    def _choose(self, survey: Survey, pose: Pose, t_s: float) -> None:
        super()._choose(survey, pose, t_s)
        if self.state is ExploreState.COMPLETE and self._slivers_now:
            self._set(
                ExploreState.COMPLETE,
                f"{self.reason}; {self._slivers_now} slivers (frontier, nothing behind it) passed over",
            )
        best = survey.best
        if best is not None and self.target == best.target and isinstance(best, NodeCandidate):
            self._target_node = best.node
        elif self.target is None:
            self._target_node = None

    def _current_cost(self, survey: Survey) -> float | None:
        """The cost of the candidate the current target belongs to: the same HTM node, or a candidate
        within ``merge_m`` of it."""
        if self.target is None:
            return None
        best: float | None = None
        for c in survey.candidates:
            same = isinstance(c, NodeCandidate) and c.node == self._target_node
            near = math.hypot(c.target.x_m - self.target.x_m, c.target.y_m - self.target.y_m)
            if same or near <= self.config.merge_m:
                best = c.cost if best is None else min(best, c.cost)
        return best

    # -- the search --------------------------------------------------------------------------------------
    def survey(self, grid: GridMap, pose: Pose, t_s: float) -> Survey:
        base = super().survey(grid, pose, t_s)
        field = self.field
        if not base.placed or field is None:
            return base
        cfg, nav = self.config, self.nav
        spec = field.seen.spec
        place = self._place_at(pose)
        self._slivers_now = 0
        # Information gain: metres of frontier near a point, counting only frontier cells that border
        # unknown space worth a look (``informative_unknown``).
        informative = dilate(informative_unknown(field.seen, cfg.min_gain_m2), 2)
        fpoints_list, owner_list = [], []
        for i, f in enumerate(base.frontiers):
            keep = informative[f.cells[:, 0], f.cells[:, 1]]
            fpoints_list.append(f.points_m[keep])
            owner_list.append(np.full(int(keep.sum()), i, dtype=np.intp))
        fpoints = np.concatenate(fpoints_list) if fpoints_list else np.zeros((0, 2))
        owner = np.concatenate(owner_list) if owner_list else np.zeros(0, dtype=np.intp)
        if self._looked and len(fpoints):
            keep = ~self._looked_at(fpoints)
            fpoints, owner = fpoints[keep], owner[keep]
        self._gain_points = fpoints

        def gain(points: FloatArray) -> tuple[FloatArray, IntArray]:
            if len(fpoints) == 0 or len(points) == 0:
                return np.zeros(len(points)), np.full(len(points), -1, dtype=np.intp)
            d = np.hypot(points[:, None, 0] - fpoints[None, :, 0], points[:, None, 1] - fpoints[None, :, 1])
            near = in_sight(field.seen, points, fpoints, d <= cfg.gain_radius_m)
            metres = near.sum(axis=1) * spec.resolution_m
            nearest = owner[d.argmin(axis=1)]
            return metres.astype(np.float64), np.where(near.any(axis=1), nearest, -1).astype(np.intp)

        # 3-4: the AST's tips, filtered against the map.
        angles, ranges, opened = grid_scan(field.seen, pose, cfg.ast_beams, cfg.ast_range_m)
        branches = scan_branches(angles, ranges, cfg.ast_range_m, nav.radius_m, opened=opened)
        tips = np.array([to_world(pose, b.tip_m) for b in branches]).reshape(-1, 2)
        cells = spec.to_cell(tips)
        inside = spec.inside(cells)
        tip_list: list[tuple[FloatArray, float]] = []
        for xy, cell, ok in zip(tips, cells, inside, strict=True):
            if not ok:
                continue
            path = float(field.path_m[cell[0], cell[1]])
            if not math.isfinite(path) or not field.roomy[cell[0], cell[1]]:
                continue
            tip_list.append((xy, path))
        tip_pts = np.array([t[0] for t in tip_list]).reshape(-1, 2)
        if len(tip_pts):
            blocked = self.blacklist.blocked(tip_pts, t_s)
            keep = ~blocked
            tip_pts = tip_pts[keep]
            tip_paths = np.array([t[1] for t in tip_list])[keep]
        else:
            tip_paths = np.zeros(0)
        tip_gain, tip_owner = gain(tip_pts)
        useful = tip_gain >= cfg.min_frontier_size_m
        tip_pts, tip_paths, tip_gain, tip_owner = (
            tip_pts[useful],
            tip_paths[useful],
            tip_gain[useful],
            tip_owner[useful],
        )
        # 5: the HTM. Tips from the current place (the branch's straight line).
        tip_nodes = self.htm.integrate(
            place, [(float(x), float(y)) for x, y in tip_pts], anchor=self._place_pose(place)
        )
        candidates: list[NodeCandidate] = []
        for xy, path, g, k, node in zip(tip_pts, tip_paths, tip_gain, tip_owner, tip_nodes, strict=True):
            frontier = base.frontiers[int(k)]
            target = Target(float(xy[0]), float(xy[1]), self._facing(field.seen, (xy[0], xy[1]), frontier))
            cost = cfg.potential_scale * float(path) - cfg.gain_scale * float(g)
            candidates.append(NodeCandidate(frontier, target, float(path), cost, "ast", float(g), node))
        # The frontiers' targets: each bound from the nearest place that sees it.
        fr_pts = np.array([[c.target.x_m, c.target.y_m] for c in base.candidates]).reshape(-1, 2)
        fr_gain, _ = gain(fr_pts)
        for c, g in zip(base.candidates, fr_gain, strict=True):
            if g < cfg.min_frontier_size_m:
                self._slivers_now += 1  # nothing behind it worth the trip (the filter above)
                continue
            spot = (c.target.x_m, c.target.y_m)
            src, cost_edge = self._seen_from(field.seen, spot, place, c.path_m)
            (node,) = self.htm.integrate(src, [spot], costs=[cost_edge], anchor=self._place_pose(src))
            g_m = float(g)
            cost = cfg.potential_scale * c.path_m - cfg.gain_scale * g_m
            candidates.append(NodeCandidate(c.frontier, c.target, c.path_m, cost, "frontier", g_m, node))
        # The current target, judged on its own (commitment): kept as a candidate, and its node bound, while
        # it is still reachable with room and has information to gain, whether or not this scan's AST or
        # frontiers found a candidate within ``merge_m`` of it (on a map SLAM builds the tips and frontier
        # targets shift with each update, and a target that vanished for one decision was replaced at
        # once: the robot turned between two goals, each switch resetting the progress watch).
        current = self._current_candidate(base, place, gain, t_s)
        if current is not None:
            candidates.append(current)
            self._target_node = current.node
        bound = {c.node for c in candidates}
        for n in self.htm.possible():
            if n not in bound:
                self.htm.remove(n)
        # 6: regions (rooms change slowly: at most every REGIONS_EVERY_S, and at once when a target ended).
        if self._wanted_regions or t_s - self._t_regions >= REGIONS_EVERY_S:
            self._update_regions(field.seen)
            self._t_regions, self._wanted_regions = t_s, False
        else:
            self.htm.assign_regions_from(self._region_at)
        # 7: the choice.
        best = self._pick(candidates, place, pose)
        candidates.sort(key=lambda c: c.cost)
        return Survey(
            base.frontiers,
            best,
            tuple(candidates),
            base.waiting,
            base.given_up,
            base.unreachable,
            True,
        )

    def _looked_at(self, points: FloatArray) -> BoolArray:
        """The points a reached target faced, within ``gain_radius_m`` of it and ``LOOKED_HALF_ANGLE`` of
        its heading (any bearing for a target without one), and did not make known."""
        out = np.zeros(len(points), dtype=bool)
        for x, y, yaw in self._looked:
            dx, dy = points[:, 0] - x, points[:, 1] - y
            near = np.hypot(dx, dy) <= self.config.gain_radius_m
            if yaw is not None:
                off = np.abs(np.remainder(np.arctan2(dy, dx) - yaw + math.pi, math.tau) - math.pi)
                near &= off <= LOOKED_HALF_ANGLE
            out |= near
        return out

    def _judge_arrival(self, survey: Survey, t_s: float) -> bool:
        """The frontier explorer's judgement (frontier left within reach of the spot: unobservable), and
        SP2ATM's own, with its measure of gain: a reached target facing at least ``min_frontier_size_m``
        of informative frontier within ``gain_radius_m`` after the map settled could not show it (a
        laser shadow, or a wall the map drew with free cells beside it: an AST tip's gain is counted that
        far away). The spot is blacklisted as unobservable and that frontier counts no gain from then on:
        without it the robot, leaving, saw the same tip again from a door and drove back to it, 10 m a
        time (office seed 2 on the SLAM map, with the commitment: 16 times in 900 s)."""
        arrived = self._arrived
        judged = super()._judge_arrival(survey, t_s)
        if arrived is None:
            return judged
        spot = arrived[0]
        pts = self._gain_points
        if len(pts) == 0:
            return judged
        self._looked.append((spot.x_m, spot.y_m, spot.yaw_rad))
        left = float(np.count_nonzero(self._looked_at(pts))) * self.nav.resolution_m
        if left < self.config.min_frontier_size_m:
            self._looked.pop()
            return judged
        if not judged:
            self.blacklist.add(
                (spot.x_m, spot.y_m), t_s, "reached, its gain still unseen", EntryKind.UNOBSERVABLE
            )
        return True

    def _current_candidate(
        self,
        base: Survey,
        place: int,
        gain: Callable[[FloatArray], tuple[FloatArray, IntArray]],
        t_s: float,
    ) -> NodeCandidate | None:
        """The current target as a candidate, its cost measured where it is now (path cost from the
        robot, gain at its spot), bound to the HTM like a frontier's target; None when there is no target,
        or it is no longer reachable with room, is blacklisted, or has nothing left to gain."""
        field, target, cfg = self.field, self.target, self.config
        if target is None or field is None or self._state is not ExploreState.EXPLORING:
            return None
        spec = field.seen.spec
        spot = np.array([[target.x_m, target.y_m]])
        cell = spec.to_cell(spot)
        if not spec.inside(cell)[0]:
            return None
        r, c = int(cell[0, 0]), int(cell[0, 1])
        path = float(field.path_m[r, c])
        if not math.isfinite(path) or not field.roomy[r, c] or self.blacklist.blocked(spot, t_s)[0]:
            return None
        g, k = gain(spot)
        if g[0] < cfg.min_frontier_size_m or k[0] < 0:
            return None
        xy = (target.x_m, target.y_m)
        src, cost_edge = self._seen_from(field.seen, xy, place, path)
        (node,) = self.htm.integrate(src, [xy], costs=[cost_edge], anchor=self._place_pose(src))
        cost = cfg.potential_scale * path - cfg.gain_scale * float(g[0])
        return NodeCandidate(base.frontiers[int(k[0])], target, path, cost, "current", float(g[0]), node)

    def _pick(self, candidates: list[NodeCandidate], place: int, pose: Pose) -> NodeCandidate | None:
        if not candidates:
            return None
        overall = min(candidates, key=lambda c: c.cost)
        room = self._region_at((pose[0], pose[1]))
        if room is not None and self.neighbours_of_region.get(room, 0) > ROOM_MAX_DOORS:
            room = None  # a hub (a corridor with many doors) is no room to finish first
        mine = [c for c in candidates if room is not None and self.htm.nodes[c.node].region == room]
        if mine:  # the robot's room first: finish it before leaving
            best = min(mine, key=lambda c: c.cost)
            return overall if overall.cost < best.cost - self.config.locality_m else best
        children = set(self.htm.neighbours(place))
        local = [c for c in candidates if c.node in children]
        if local:  # SP2ATM step 5: the current place's POSSIBLE children
            return min(local, key=lambda c: c.cost)
        # Backtracking: the nearest place (over the HTM) that still has POSSIBLE children.
        way = self.htm.backtrack(place)
        self.backtracks += 1
        if way is not None:
            goal = way[-1]
            theirs = set(self.htm.neighbours(goal))
            there = [c for c in candidates if c.node in theirs]
            if there:
                log.debug("sp2atm: backtracking over %d places to place %d", len(way) - 1, goal)
                return min(there, key=lambda c: c.cost)
        return overall

    # -- places, poses, regions ----------------------------------------------------------------------
    def _new_pose(self, pose: tuple[float, float, float]) -> int:
        pid = self._next_pose
        self._next_pose += 1
        self.htm.add_pose(pid, pose)
        return pid

    def _place_pose(self, place: int) -> int | None:
        return self.htm.nodes[place].anchor

    def _place_at(self, pose: Pose) -> int:
        """The current place: the nearest PLACE within ``place_spacing_m`` of the robot, or a new one."""
        best: tuple[int, float] | None = None
        for n in self.htm.nodes.values():
            if n.kind is NodeKind.PLACE:
                d = math.hypot(n.x_m - pose[0], n.y_m - pose[1])
                if d <= self.config.place_spacing_m and (best is None or d < best[1]):
                    best = (n.id, d)
        if best is not None:
            if best[0] != self.place:
                self._enter(best[0])
            assert self.place is not None
            return self.place
        node = self.htm.add_place((pose[0], pose[1]))
        self.htm.anchor(node, self._new_pose(pose))
        self._enter(node)
        return node

    def _enter(self, node: int) -> None:
        """The robot is at place ``node`` now; an edge from the last place, as long as it drove."""
        if self.place is not None and self.place in self.htm.nodes and self.place != node:
            a, b = self.htm.nodes[self.place], self.htm.nodes[node]
            self.htm.link(self.place, node, max(self._driven_m, math.hypot(a.x_m - b.x_m, a.y_m - b.y_m)))
        self.place = node
        self._driven_m = 0.0

    def _seen_from(
        self, grid: GridMap, xy: tuple[float, float], place: int, path_m: float
    ) -> tuple[int, float]:
        """The place nearest ``xy`` with a clear straight line to it (and that line's length), else the
        current place and ``path_m``."""
        places = [
            (math.hypot(n.x_m - xy[0], n.y_m - xy[1]), n.id)
            for n in self.htm.nodes.values()
            if n.kind is NodeKind.PLACE
        ]
        for d, pid in sorted(places)[:3]:
            n = self.htm.nodes[pid]
            cells = segment_cells(grid.spec, np.array([n.x_m, n.y_m]), np.array(xy))
            ok = grid.spec.inside(cells)
            if ok.all() and not (grid.occupied | grid.unknown)[cells[:, 0], cells[:, 1]].any():
                return pid, d
        return place, path_m

    def _update_regions(self, grid: GridMap) -> None:
        labels, regions = find_regions(grid, self.config.door_width_m, self.config.min_region_m2)
        self.region_ids = self.htm.set_regions([(r.polygon, r.area_m2) for r in regions])
        self.labels = labels
        self.htm.assign_regions_from(self._region_at)
        # Which regions touch which (a door's cells go to one side, so the two sides touch there).
        pairs = np.concatenate(
            [
                np.stack([labels[:, :-1].ravel(), labels[:, 1:].ravel()], axis=1),
                np.stack([labels[:-1, :].ravel(), labels[1:, :].ravel()], axis=1),
            ]
        )
        pairs = pairs[(pairs[:, 0] > 0) & (pairs[:, 1] > 0) & (pairs[:, 0] != pairs[:, 1])]
        pairs = np.unique(np.sort(pairs, axis=1), axis=0)
        degree: dict[int, int] = {}
        for a, b in pairs:
            for k in (int(a), int(b)):
                rid = self.region_ids[k - 1]
                degree[rid] = degree.get(rid, 0) + 1
        self.neighbours_of_region = degree

    def _region_at(self, xy: tuple[float, float]) -> int | None:
        if self.labels is None or self.field is None:
            return None
        spec = self.field.seen.spec
        cell = spec.to_cell(np.array(xy))[0]
        if not spec.inside(cell[None, :])[0]:
            return None
        k = int(self.labels[cell[0], cell[1]])
        return self.region_ids[k - 1] if 0 < k <= len(self.region_ids) else None


ENCLOSED = 0.8  # a small unknown pocket with this share of its border occupied is the inside of an obstacle
ENCLOSED_MAX_M2 = 2.0  # ... up to this size (an unexplored room seen through its door is bordered by walls
# seen from its neighbours too: it must never count as enclosed)


def informative_unknown(grid: GridMap, min_area_m2: float) -> BoolArray:
    """The unknown cells worth a trip: the unknown space after a 3 x 3 opening (a sliver one or two cells
    wide between the beams of a far scan has frontier on both sides and nothing behind it), in pockets of
    at least ``min_area_m2``, leaving out small pockets (``ENCLOSED_MAX_M2``) whose border is mostly
    occupied (``ENCLOSED``: the inside of a cupboard or a box, which no position of the robot shows)."""
    unknown = np.asarray(
        cv2.morphologyEx(grid.unknown.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    )
    if not unknown.any():
        return unknown.astype(bool)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(unknown, connectivity=4, ltype=cv2.CV_32S)
    # Each pocket's border: the cells one step outside it, labelled by the pocket next to them.
    grown = np.asarray(cv2.dilate(labels.astype(np.float32), np.ones((3, 3), np.uint8))).astype(np.int32)
    border = (grown > 0) & (unknown == 0)
    total = np.bincount(grown[border], minlength=count)
    walls = np.bincount(grown[border & grid.occupied], minlength=count)
    area = stats[:, cv2.CC_STAT_AREA] * grid.spec.resolution_m**2
    enclosed = (walls >= ENCLOSED * np.maximum(total, 1)) & (area < ENCLOSED_MAX_M2)
    keep = (area >= min_area_m2) & ~enclosed
    keep[0] = False
    out: BoolArray = keep[labels]
    return out


def in_sight(grid: GridMap, points: FloatArray, targets: FloatArray, pairs: BoolArray) -> BoolArray:
    """``pairs`` (points x targets) kept where the straight line from the point to the target crosses no
    occupied cell (sampled every half cell; the target's own cell not looked at). Gain counted within a
    radius alone counts the frontier of the room behind a wall: a tip in a corner of office room N2 drew
    its gain from room N1's frontier 1.4 m away through the wall, and the robot drove to it (seed 0)."""
    out = pairs.copy()
    i, j = np.nonzero(pairs)
    if len(i) == 0:
        return out
    a, b = points[i], targets[j]
    length = np.hypot(*(b - a).T)
    steps = max(2, int(np.ceil(float(length.max()) / (grid.spec.resolution_m / 2))) + 1)
    t = np.linspace(0.0, 1.0, steps)[None, :, None]
    samples = a[:, None, :] + t * (b - a)[:, None, :]
    cells = grid.spec.to_cell(samples.reshape(-1, 2)).reshape(len(i), steps, 2)
    end = grid.spec.to_cell(b)
    rows = np.clip(cells[..., 0], 0, grid.spec.shape[0] - 1)
    cols = np.clip(cells[..., 1], 0, grid.spec.shape[1] - 1)
    own = (cells[..., 0] == end[:, None, 0]) & (cells[..., 1] == end[:, None, 1])
    blocked = (grid.occupied[rows, cols] & ~own).any(axis=1)
    out[i[blocked], j[blocked]] = False
    return out
