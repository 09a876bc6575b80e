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
* **done** when no POSSIBLE node is left.

Not written yet: REGION nodes from doorways (the kind exists, nothing makes one), anchoring nodes to SLAM
poses so they move when the map is corrected, and the SP2ATM explorer that drives this behind the
``Explorer`` interface.

Pure: no I/O, no clock.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph


class NodeKind(enum.StrEnum):
    PLACE = "place"
    POSSIBLE = "possible"
    REGION = "region"


@dataclass
class Node:
    id: int
    kind: NodeKind
    x_m: float
    y_m: float
    sightings: int = 1


class Htm:
    def __init__(self, merge_m: float = 0.75) -> None:
        if merge_m <= 0.0:
            raise ValueError("merge_m must be positive")
        self.merge_m = merge_m
        self.nodes: dict[int, Node] = {}
        self.edges: dict[tuple[int, int], float] = {}  # (low id, high id) -> cost, metres
        self._next = 0

    # -- building ---------------------------------------------------------------------------------------
    def add_place(self, xy: tuple[float, float]) -> int:
        """A place the robot stands at (the first node, or one reached off the graph)."""
        return self._new(NodeKind.PLACE, xy)

    def integrate(self, place: int, possible: list[tuple[float, float]]) -> list[int]:
        """Apply append / rebind for each possible node seen from ``place``; the node each was bound to."""
        here = self.nodes[place]
        bound = []
        for xy in possible:
            cost = math.hypot(xy[0] - here.x_m, xy[1] - here.y_m)
            near = self.nearest(xy, exclude=place)
            if near is not None and near[1] <= self.merge_m:
                node = self.nodes[near[0]]
                if node.kind is NodeKind.POSSIBLE:
                    node.x_m = (node.x_m * node.sightings + xy[0]) / (node.sightings + 1)
                    node.y_m = (node.y_m * node.sightings + xy[1]) / (node.sightings + 1)
                    node.sightings += 1
                self._link(place, node.id, cost)
                bound.append(node.id)
            else:
                new = self._new(NodeKind.POSSIBLE, xy)
                self._link(place, new, cost)
                bound.append(new)
        return bound

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
        # A zero-cost edge would vanish from a sparse matrix; the floor keeps it an edge.
        costs = [max(c, 1e-9) for c in self.edges.values()] * 2
        matrix = sparse.csr_matrix((costs, (rows, cols)), shape=(len(ids), len(ids)))
        distances, predecessors = csgraph.bellman_ford(
            matrix, directed=False, indices=index[place], return_predecessors=True
        )
        goals = [
            n
            for n in ids
            if self.nodes[n].kind is NodeKind.PLACE
            and any(self.nodes[m].kind is NodeKind.POSSIBLE for m in self.neighbours(n))
            and np.isfinite(distances[index[n]])
        ]
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

    def _link(self, a: int, b: int, cost: float) -> None:
        key = (min(a, b), max(a, b))
        self.edges[key] = min(cost, self.edges.get(key, math.inf))
