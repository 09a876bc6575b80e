"""SP2ATM's hierarchical topology map (HTM): PLACE nodes (visited), POSSIBLE nodes (seen, not visited) and
REGION nodes (rooms), with the update rules and the backtracking search (reference/eco.md §1.1, steps 4,
6, 7; the thresholds are that page's proposals).

* **append**: a possible node with no node within ``merge_m`` becomes a POSSIBLE node, with an edge from
  the current place costing the branch's length;
* **rebind**: a possible node within ``merge_m`` of an existing node is not duplicated: the edge from the
  current place to that node is added (or made cheaper): a topological loop closure. A POSSIBLE node's
  position becomes the mean of every sighting bound to it;
* **remove**: a POSSIBLE node goes with its edges (its gap explored, or blocked);
* **visit**: the POSSIBLE node the robot reached becomes a PLACE;
* **backtrack**: single-source shortest paths (Bellman-Ford, scipy's; the weights are non-negative so it
  equals Dijkstra, kept for the seed's sake and for negative preferences later) from the current place
  to the nearest PLACE that still has a POSSIBLE neighbour; the way there as node ids;
* **done** when no POSSIBLE node is left;
* **regions**: REGION nodes (rooms) replace each other as the map grows (``set_regions``, from
  ``agent.exploration.regions``); a new region keeps the id and the user's name of the old region whose
  centre lies inside it (or that holds its centre), so a room named once stays named while it is mapped
  further (and after a load); every PLACE and POSSIBLE node records the region it lies in;
* **anchors** (reference/eco.md §1.1 step 9): a node can be anchored to a pose id (a SLAM keyframe: the
  pose the robot had when it made the node) with its offset in that pose's frame; ``reproject`` moves every
  anchored node when poses are corrected (a loop closure, a resampling), so the HTM stays on the map.

Pure: no I/O, no clock.
"""

from __future__ import annotations

import enum
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

log = logging.getLogger(__name__)


class NodeKind(enum.StrEnum):
    PLACE = "place"
    POSSIBLE = "possible"
    REGION = "region"


Pose = tuple[float, float, float]
Polygon = tuple[tuple[float, float], ...]


@dataclass
class Node:
    id: int
    kind: NodeKind
    x_m: float
    y_m: float
    sightings: int = 1
    anchor: int | None = None  # the pose id the position is kept relative to (None: a fixed position)
    offset_m: tuple[float, float] = (0.0, 0.0)  # the position in that pose's frame
    region: int | None = None  # PLACE / POSSIBLE: the REGION node it lies in
    name: str = ""  # REGION: the user's name for the room ("" until named)
    polygon: Polygon = ()  # REGION: its outline, world metres
    area_m2: float = 0.0  # REGION: its free area


class Htm:
    def __init__(self, merge_m: float = 0.75) -> None:
        if merge_m <= 0.0:
            raise ValueError("merge_m must be positive")
        self.merge_m = merge_m
        self.nodes: dict[int, Node] = {}
        self.edges: dict[tuple[int, int], float] = {}  # (low id, high id) -> cost, metres
        self.poses: dict[int, Pose] = {}  # pose id -> the pose nodes are anchored to
        self._next = 0

    # -- building ---------------------------------------------------------------------------------------
    def add_place(self, xy: tuple[float, float]) -> int:
        """A place the robot stands at (the first node, or one reached off the graph)."""
        return self._new(NodeKind.PLACE, xy)

    def integrate(
        self,
        place: int,
        possible: list[tuple[float, float]],
        costs: list[float] | None = None,
        anchor: int | None = None,
    ) -> list[int]:
        """Apply append / rebind for each possible node seen from ``place``; the node each was bound to.
        An edge costs the straight line from the place (the AST's branch) unless ``costs`` gives each
        its own (a path's); a new node is anchored to pose ``anchor`` if given."""
        here = self.nodes[place]
        if costs is not None and len(costs) != len(possible):
            raise ValueError(f"{len(costs)} costs for {len(possible)} possible nodes")
        bound = []
        for i, xy in enumerate(possible):
            cost = math.hypot(xy[0] - here.x_m, xy[1] - here.y_m) if costs is None else costs[i]
            near = self.nearest(xy, exclude=place)
            if near is not None and near[1] <= self.merge_m:
                node = self.nodes[near[0]]
                if node.kind is NodeKind.POSSIBLE:
                    node.x_m = (node.x_m * node.sightings + xy[0]) / (node.sightings + 1)
                    node.y_m = (node.y_m * node.sightings + xy[1]) / (node.sightings + 1)
                    node.sightings += 1
                    if node.anchor is not None:
                        self.anchor(node.id, node.anchor)
                self._link(place, node.id, cost)
                bound.append(node.id)
            else:
                new = self._new(NodeKind.POSSIBLE, xy)
                if anchor is not None:
                    self.anchor(new, anchor)
                self._link(place, new, cost)
                bound.append(new)
        return bound

    def link(self, a: int, b: int, cost: float) -> None:
        """An edge between two nodes (the robot drove from one place to the other), or a cheaper one."""
        if a == b:
            return
        if cost < 0.0 or not math.isfinite(cost):
            raise ValueError(f"an edge's cost must be finite and >= 0, got {cost}")
        self._link(a, b, cost)

    # -- anchoring to poses -----------------------------------------------------------------------------
    def add_pose(self, pose_id: int, pose: Pose) -> None:
        self.poses[pose_id] = (float(pose[0]), float(pose[1]), float(pose[2]))

    def anchor(self, node: int, pose_id: int) -> None:
        """Keep ``node`` where it is now, relative to pose ``pose_id``."""
        x, y, yaw = self.poses[pose_id]
        n = self.nodes[node]
        dx, dy = n.x_m - x, n.y_m - y
        c, s = math.cos(yaw), math.sin(yaw)
        n.anchor, n.offset_m = pose_id, (c * dx + s * dy, -s * dx + c * dy)

    def reproject(self, poses: dict[int, Pose]) -> int:
        """The poses as corrected (by SLAM): every node anchored to one of them moves with it. Poses not
        known are ignored. The number of nodes moved."""
        moved = 0
        for pid, pose in poses.items():
            if pid in self.poses:
                self.add_pose(pid, pose)
        for n in self.nodes.values():
            if n.anchor is None or n.anchor not in poses or n.anchor not in self.poses:
                continue
            x, y, yaw = self.poses[n.anchor]
            c, s = math.cos(yaw), math.sin(yaw)
            n.x_m = x + c * n.offset_m[0] - s * n.offset_m[1]
            n.y_m = y + s * n.offset_m[0] + c * n.offset_m[1]
            moved += 1
        return moved

    # -- regions ------------------------------------------------------------------------------------------
    def set_regions(self, regions: list[tuple[Polygon, float]]) -> list[int]:
        """Replace the REGION nodes by ``regions`` (outline, free area; largest first is best); each keeps
        the id and name of an old region whose centre it contains or that contains its centre (a named one
        first; the first, largest, new region wins),
        otherwise it gets a new id. The REGION ids, in order. Nodes' ``region`` are not touched: call
        ``assign_regions`` (by outline) or set them from a label image."""
        old = [n for n in self.nodes.values() if n.kind is NodeKind.REGION]
        taken: set[int] = set()
        ids: list[int] = []
        for polygon, area in regions:
            if len(polygon) < 3:
                raise ValueError("a region's outline needs at least 3 points")
            heir = None
            cx, cy = polygon_centre(polygon)
            for o in sorted(old, key=lambda o: (o.name == "", -o.area_m2)):
                if o.id in taken:
                    continue
                if point_in_polygon((o.x_m, o.y_m), polygon) or point_in_polygon((cx, cy), o.polygon):
                    heir = o
                    break
            if heir is not None:
                taken.add(heir.id)
                heir.x_m, heir.y_m, heir.polygon, heir.area_m2 = cx, cy, tuple(polygon), area
                ids.append(heir.id)
            else:
                rid = self._new(NodeKind.REGION, (cx, cy))
                self.nodes[rid].polygon, self.nodes[rid].area_m2 = tuple(polygon), area
                ids.append(rid)
        for o in old:
            if o.id not in taken:
                del self.nodes[o.id]
        return ids

    def assign_regions(self) -> None:
        """Every PLACE / POSSIBLE node's ``region``: the REGION whose outline holds it (None: none)."""
        regions = [n for n in self.nodes.values() if n.kind is NodeKind.REGION]
        for n in self.nodes.values():
            if n.kind is NodeKind.REGION:
                continue
            n.region = next((r.id for r in regions if point_in_polygon((n.x_m, n.y_m), r.polygon)), None)

    def assign_regions_from(self, region_at: Callable[[tuple[float, float]], int | None]) -> None:
        """Every PLACE / POSSIBLE node's ``region`` from a lookup (a label image's)."""
        for n in self.nodes.values():
            if n.kind is not NodeKind.REGION:
                n.region = region_at((n.x_m, n.y_m))

    def name_region(self, region: int, name: str) -> None:
        if region not in self.nodes or self.nodes[region].kind is not NodeKind.REGION:
            raise KeyError(f"no region {region}")
        self.nodes[region].name = name

    def regions(self) -> list[Node]:
        return [n for n in self.nodes.values() if n.kind is NodeKind.REGION]

    def region_named(self, name: str) -> Node | None:
        return next((n for n in self.regions() if n.name == name), None)

    def remove(self, node: int) -> None:
        if self.nodes[node].kind is not NodeKind.POSSIBLE:
            raise ValueError(
                f"node {node} is a {self.nodes[node].kind.value}; only POSSIBLE nodes are removed"
            )
        del self.nodes[node]
        self.edges = {k: v for k, v in self.edges.items() if node not in k}

    def visit(self, node: int) -> None:
        self.nodes[node].kind = NodeKind.PLACE

    # -- reading ----------------------------------------------------------------------------------------
    def nearest(self, xy: tuple[float, float], exclude: int | None = None) -> tuple[int, float] | None:
        best: tuple[int, float] | None = None
        for n in self.nodes.values():
            if n.id == exclude or n.kind is NodeKind.REGION:
                continue
            d = math.hypot(n.x_m - xy[0], n.y_m - xy[1])
            if best is None or d < best[1]:
                best = (n.id, d)
        return best

    def neighbours(self, node: int) -> list[int]:
        return [b if a == node else a for a, b in self.edges if node in (a, b)]

    def possible(self) -> list[int]:
        return [n.id for n in self.nodes.values() if n.kind is NodeKind.POSSIBLE]

    @property
    def done(self) -> bool:
        return not self.possible()

    def backtrack(self, place: int) -> list[int] | None:
        """The way (node ids, ``place`` first) to the nearest PLACE with a POSSIBLE neighbour; None if
        no such place is connected (or none is left)."""
        ids = sorted(self.nodes)
        index = {n: i for i, n in enumerate(ids)}
        rows = [index[a] for a, b in self.edges] + [index[b] for a, b in self.edges]
        cols = [index[b] for a, b in self.edges] + [index[a] for a, b in self.edges]
        # A zero-cost edge would vanish from a sparse matrix; the floor (a millimetre) keeps it an edge,
        # large enough that adding it to a distance is never lost to rounding.
        costs = [max(c, 1e-3) for c in self.edges.values()] * 2
        matrix = sparse.csr_matrix((costs, (rows, cols)), shape=(len(ids), len(ids)))
        try:
            distances, predecessors = csgraph.bellman_ford(
                matrix, directed=False, indices=index[place], return_predecessors=True
            )
        except csgraph.NegativeCycleError:
            # Seen on the office (seed 2) with a 1e-9 floor on the costs, none negative: scipy's check
            # misfired (rounding, most likely).
            # With no negative cost Dijkstra's answer is the same (reference/eco.md §1.1 step 6).
            log.warning(
                "htm: Bellman-Ford reported a negative cycle on %d nodes, %d edges, smallest cost %.3g; "
                "using Dijkstra",
                len(ids),
                len(self.edges),
                min(costs, default=0.0),
            )
            distances, predecessors = csgraph.dijkstra(
                matrix, directed=False, indices=index[place], return_predecessors=True
            )
        open_places = set()
        for a, b in self.edges:
            ka, kb = self.nodes[a].kind, self.nodes[b].kind
            if ka is NodeKind.PLACE and kb is NodeKind.POSSIBLE:
                open_places.add(a)
            elif kb is NodeKind.PLACE and ka is NodeKind.POSSIBLE:
                open_places.add(b)
        goals = [n for n in sorted(open_places) if np.isfinite(distances[index[n]])]
        if not goals:
            return None
        goal = min(goals, key=lambda n: distances[index[n]])
        way = [goal]
        while way[-1] != place:
            way.append(ids[int(predecessors[index[way[-1]]])])
        return way[::-1]

    # -- internals --------------------------------------------------------------------------------------
    def _new(self, kind: NodeKind, xy: tuple[float, float]) -> int:
        node = Node(self._next, kind, float(xy[0]), float(xy[1]))
        self.nodes[node.id] = node
        self._next += 1
        return node.id

    def restore(self, node: Node) -> None:
        """Put back a node read from a file (``agent.exploration.topology``), its id kept."""
        if node.id in self.nodes:
            raise ValueError(f"node id {node.id} twice")
        self.nodes[node.id] = node
        self._next = max(self._next, node.id + 1)

    def _link(self, a: int, b: int, cost: float) -> None:
        key = (min(a, b), max(a, b))
        self.edges[key] = min(cost, self.edges.get(key, math.inf))


def point_in_polygon(xy: tuple[float, float], polygon: Polygon) -> bool:
    """Even-odd rule."""
    x, y = xy
    inside = False
    n = len(polygon)
    for i in range(n):
        (x1, y1), (x2, y2) = polygon[i], polygon[(i + 1) % n]
        if (y1 > y) != (y2 > y) and x < x1 + (y - y1) * (x2 - x1) / (y2 - y1):
            inside = not inside
    return inside


def polygon_centre(polygon: Polygon) -> tuple[float, float]:
    """The area centroid (the vertices' mean for a degenerate outline)."""
    pts = np.asarray(polygon, dtype=np.float64)
    x, y = pts[:, 0], pts[:, 1]
    x2, y2 = np.roll(x, -1), np.roll(y, -1)
    cross = x * y2 - x2 * y
    area = cross.sum() / 2.0
    if abs(area) < 1e-12:
        return float(x.mean()), float(y.mean())
    return float(((x + x2) * cross).sum() / (6 * area)), float(((y + y2) * cross).sum() / (6 * area))
