"""The global planner: cost-aware Dijkstra on the costmap (scipy's csgraph), then any-angle smoothing.

* **Graph**: one node per cell whose cost is finite, 8-connected (a diagonal step needs both cells beside
  it free: no cutting corners). An edge between cells a and b costs ``length (1 + w (c_a + c_b) / 2)``,
  length 1 or sqrt(2) cells, c the costmap's clearance cost in [0, 1], w ``clearance_weight``: paths keep
  off walls where there is room and still squeeze through a door when that is the way.
* **Search**: ``scipy.sparse.csgraph.dijkstra`` from the *goal* (C, not Python: a Python heap A* costs
  ~700 ms on such a grid, reference/eco.md §1.4; on the whole 420 x 260 office grid the graph costs
  17-25 ms and the search ~19 ms of CPU, so the search is coarse to fine, see :class:`GlobalPlanner`).
  The tree is a navigation function: while the costmap and the goal stay the same, a plan from
  anywhere is a walk up the predecessors, no search (replanning as the robot moves costs microseconds).
* **Smoothing** (any-angle, a Theta*-style post-pass): from each anchor the farthest later path cell
  that a straight line reaches over free cells at no more cost, by the search's own measure
  (length (1 + w mean c)), than the grid path between them (within ``smooth_tolerance``): the corners of
  the 8-connected staircase go, the clearance the search paid for stays.

Plans report why they failed (:class:`PlanStatus`): a start inside an obstacle's footprint is escaped
to the nearest free cell within ``escape_m``; a goal in a forbidden cell or one not connected to the start
is reported, never searched for forever.
"""

from __future__ import annotations

import enum
import itertools
import math
import time
from dataclasses import dataclass, field

import cv2
import numpy as np
import numpy.typing as npt
from scipy import sparse
from scipy.sparse import csgraph

from agent.navigation.costmap import (
    BoolArray,
    Costmap,
    Float32Array,
    FloatArray,
    GridSpec,
    IntArray,
    segment_cells,
)

SQRT2 = math.sqrt(2.0)


class PlanStatus(enum.StrEnum):
    OK = "ok"
    START_BLOCKED = "start_blocked"  # the robot is inside an obstacle's footprint, no free cell nearby
    GOAL_BLOCKED = "goal_blocked"  # the goal is in a forbidden cell (an obstacle, unknown, off the map)
    UNREACHABLE = "unreachable"  # no free way from the start to the goal


@dataclass(frozen=True)
class Plan:
    status: PlanStatus
    path_m: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))  # (N, 2) waypoints, start first
    length_m: float = math.inf
    cost: float = math.inf  # the grid path's cost (cells x (1 + w c))
    grid_cells: int = 0  # cells on the grid path before smoothing
    searched: bool = False  # a new search was run (False: the cached tree was walked)
    plan_ms: float = 0.0  # wall time
    cpu_ms: float = 0.0  # this thread's CPU time (what one core spent, however loaded the machine)
    reason: str = ""

    @property
    def ok(self) -> bool:
        return self.status is PlanStatus.OK


@dataclass(frozen=True)
class Graph:
    """The grid graph of some cells: ``matrix`` (K x K CSR, 8 slots per node, ``inf`` where a slot has
    no edge), ``cells`` the flat cell index of each node, ``node_of`` each cell's node or -1."""

    matrix: sparse.csr_matrix
    cells: npt.NDArray[np.intp]
    node_of: npt.NDArray[np.int32]


# (d_row, d_col, length in cells)
_STEPS = (
    (0, 1, 1.0),
    (1, 0, 1.0),
    (0, -1, 1.0),
    (-1, 0, 1.0),
    (1, 1, SQRT2),
    (1, -1, SQRT2),
    (-1, 1, SQRT2),
    (-1, -1, SQRT2),
)


def build_graph(cost: Float32Array, clearance_weight: float, mask: BoolArray | None = None) -> Graph:
    """The 8-connected graph of the finite cells of ``cost`` (within ``mask``). Built straight into CSR
    with eight slots per node (absent edges weigh ``inf``, which Dijkstra never relaxes) and a node per
    finite cell only, so a band's graph costs in proportion to the band."""
    rows, cols = cost.shape
    free = np.isfinite(cost)
    if mask is not None:
        free &= mask
    # Node numbers on a grid padded with one cell of "no node" all round: neighbours need no bounds checks.
    width = cols + 2
    padded = np.full((rows + 2, width), -1, dtype=np.int32)
    inner = padded[1:-1, 1:-1]
    k = int(np.count_nonzero(free))
    inner[free] = np.arange(k, dtype=np.int32)
    flat_nodes = padded.ravel()
    cells = np.flatnonzero(free)
    r, c = np.divmod(cells, cols)
    at = (r + 1) * width + (c + 1)  # each node's place in the padded grid
    padded_cost = np.zeros((rows + 2, width))
    padded_cost[1:-1, 1:-1] = np.where(free, cost, 0.0)  # edges to other cells are masked out below
    flat_cost = padded_cost.ravel()
    own = flat_cost[at]
    indices = np.empty((k, 8), dtype=np.int32)
    weights = np.empty((k, 8), dtype=np.float64)
    self_nodes = np.arange(k, dtype=np.int32)
    for slot, (dr, dc, length) in enumerate(_STEPS):
        there = at + (dr * width + dc)
        other = flat_nodes[there]
        ok = other >= 0
        if dr and dc:  # no cutting corners: both cells beside the diagonal free
            ok &= (flat_nodes[at + dr * width] >= 0) & (flat_nodes[at + dc] >= 0)
        indices[:, slot] = np.where(ok, other, self_nodes)
        weight = length * (1.0 + clearance_weight * 0.5 * (own + flat_cost[there]))
        weights[:, slot] = np.where(ok, weight, np.inf)
    node_of = np.full(rows * cols, -1, dtype=np.int32)
    node_of[cells] = self_nodes
    indptr = np.arange(0, 8 * k + 1, 8, dtype=np.int32)
    matrix = sparse.csr_matrix((weights.ravel(), indices.ravel(), indptr), shape=(k, k))
    return Graph(matrix, cells, node_of)


def coarse_cost(cost: Float32Array, factor: int) -> Float32Array:
    """``cost`` pooled over factor x factor blocks by their maximum (a block with a forbidden cell is
    forbidden): a conservative, smaller grid for the first search."""
    rows, cols = cost.shape
    pr, pc = -rows % factor, -cols % factor
    padded = np.pad(cost, ((0, pr), (0, pc)), constant_values=np.inf)
    blocks = padded.reshape(padded.shape[0] // factor, factor, padded.shape[1] // factor, factor)
    out: Float32Array = blocks.max(axis=(1, 3))
    return out


@dataclass
class _Tree:
    """A Dijkstra tree rooted at the goal over some graph: cost-to-goal and predecessor per node."""

    graph: Graph
    distances: FloatArray
    predecessors: npt.NDArray[np.int32]
    root: int


class GlobalPlanner:
    """Plans on a :class:`Costmap`, keeping the search tree of the last goal while the costmap stays.

    Coarse to fine: a first search on the costmap pooled ``coarse_factor`` x ``coarse_factor`` finds the
    way; the full-resolution search then runs in a band ``corridor_m`` wide either side of it (a
    conservative pooling can only lose narrow passages, never invent one: when the coarse search finds
    nothing, or the band does not hold the way, the whole grid is searched)."""

    def __init__(
        self,
        clearance_weight: float = 2.0,
        escape_m: float = 0.3,
        smooth_tolerance: float = 0.02,
        coarse_factor: int = 2,
        corridor_m: float = 0.5,
    ) -> None:
        self.clearance_weight = clearance_weight
        self.escape_m = escape_m
        self.smooth_tolerance = smooth_tolerance
        self.coarse_factor = coarse_factor
        self.corridor_m = corridor_m
        self._key: tuple[int, int, bool, int] | None = None  # costmap id, version, allow_unknown, goal
        self._tree: _Tree | None = None
        self.searches = 0

    def invalidate(self) -> None:
        self._key = None
        self._tree = None

    def plan(
        self,
        costmap: Costmap,
        start_xy: tuple[float, float],
        goal_xy: tuple[float, float],
        allow_unknown: bool | None = None,
    ) -> Plan:
        t0, c0 = time.perf_counter(), time.thread_time()
        allow = costmap.config.allow_unknown if allow_unknown is None else allow_unknown
        cost = costmap.cost(allow)
        spec = costmap.spec
        cols = spec.shape[1]
        goal_cell = spec.to_cell(np.array(goal_xy))[0]
        if not spec.inside(goal_cell[None, :])[0] or not np.isfinite(cost[goal_cell[0], goal_cell[1]]):
            return Plan(PlanStatus.GOAL_BLOCKED, reason=_blocked_reason(costmap, goal_cell, allow, "goal"))
        goal_index = int(goal_cell[0] * cols + goal_cell[1])
        start_cell = spec.to_cell(np.array(start_xy))[0]
        key = (id(costmap), costmap.version, allow, goal_index)
        searched = False
        start_index: int | None = None
        if key == self._key and self._tree is not None:
            start_index = self._escape(cost, spec, start_cell, self._tree)
        if start_index is None:
            # A new search: coarse first, then the band around its way; the whole grid if that fails.
            searched = True
            self._key = key
            mask = self._corridor(cost, spec, start_cell, goal_cell)
            self._tree = self._search(cost, goal_index, mask) if mask is not None else None
            if self._tree is not None:
                start_index = self._escape(cost, spec, start_cell, self._tree)
            if start_index is None:
                self._tree = self._search(cost, goal_index, None)
                start_index = self._escape(cost, spec, start_cell, self._tree)
        tree = self._tree
        assert tree is not None
        if start_index is None:
            ms, cpu = (time.perf_counter() - t0) * 1e3, (time.thread_time() - c0) * 1e3
            status, reason = self._why_not(cost, spec, start_cell, tree)
            return Plan(status, searched=searched, plan_ms=ms, cpu_ms=cpu, reason=reason)
        graph = tree.graph
        node = int(graph.node_of[start_index])
        chain = [node]
        while node != tree.root:
            node = int(tree.predecessors[node])
            chain.append(node)
        flat = graph.cells[np.array(chain, dtype=np.intp)]
        cells = np.stack(np.divmod(flat, cols), axis=1)
        to_goal = tree.distances[np.array(chain, dtype=np.intp)]
        total = float(to_goal[0])
        path = self._smooth(cells, to_goal, cost, spec)
        start = np.array(start_xy, dtype=np.float64)
        if start_index == int(start_cell[0] * cols + start_cell[1]):
            path[0] = start
        else:  # escaped from a forbidden cell: first back to the free cell
            path = np.vstack([start[None, :], path])
        path[-1] = goal_xy
        length = float(np.sum(np.hypot(*np.diff(path, axis=0).T))) if len(path) > 1 else 0.0
        ms, cpu = (time.perf_counter() - t0) * 1e3, (time.thread_time() - c0) * 1e3
        return Plan(PlanStatus.OK, path, length, total, len(chain), searched, ms, cpu)

    def _search(self, cost: Float32Array, goal_index: int, mask: BoolArray | None) -> _Tree:
        graph = build_graph(cost, self.clearance_weight, mask)
        root = int(graph.node_of[goal_index])
        distances, predecessors = csgraph.dijkstra(
            graph.matrix, directed=True, indices=root, return_predecessors=True
        )
        self.searches += 1
        return _Tree(graph, distances, predecessors.astype(np.int32), root)

    def _corridor(
        self, cost: Float32Array, spec: GridSpec, start_cell: IntArray, goal_cell: IntArray
    ) -> BoolArray | None:
        """The fine cells within ``corridor_m`` of the coarse grid's way from start to goal, or None."""
        f = self.coarse_factor
        if f <= 1 or not spec.inside(start_cell[None, :])[0]:
            return None
        coarse = coarse_cost(cost, f)
        crows, ccols = coarse.shape
        cs, cg = start_cell // f, goal_cell // f
        if not (np.isfinite(coarse[cs[0], cs[1]]) and np.isfinite(coarse[cg[0], cg[1]])):
            return None
        goal = int(cg[0] * ccols + cg[1])
        tree = self._search(coarse, goal, None)
        node = int(tree.graph.node_of[int(cs[0] * ccols + cs[1])])
        if not np.isfinite(tree.distances[node]):
            return None
        chain = [node]
        while node != tree.root:
            node = int(tree.predecessors[node])
            chain.append(node)
        band = np.zeros((crows, ccols), dtype=np.uint8)
        flat = tree.graph.cells[np.array(chain, dtype=np.intp)]
        band.flat[flat] = 1
        fine = np.kron(band, np.ones((f, f), dtype=np.uint8))[: spec.shape[0], : spec.shape[1]]
        reach = max(math.ceil(self.corridor_m / spec.resolution_m), 1)
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * reach + 1, 2 * reach + 1))
        grown: BoolArray = cv2.dilate(np.ascontiguousarray(fine), kernel).astype(bool)
        return grown

    def _escape(self, cost: Float32Array, spec: GridSpec, cell: IntArray, tree: _Tree) -> int | None:
        """The start's flat cell index, or, when the start cell is forbidden, the nearest cell within
        ``escape_m`` that reaches the goal; None when there is none (or the tree does not reach it)."""
        rows, cols = spec.shape
        node_of = tree.graph.node_of
        if spec.inside(cell[None, :])[0]:
            index = int(cell[0] * cols + cell[1])
            node = int(node_of[index])
            if node >= 0 and np.isfinite(tree.distances[node]):
                return index
            if np.isfinite(cost[cell[0], cell[1]]):
                return None  # free, but not reached by this tree
        reach = math.ceil(self.escape_m / spec.resolution_m)
        r0, r1 = max(int(cell[0]) - reach, 0), min(int(cell[0]) + reach + 1, rows)
        c0, c1 = max(int(cell[1]) - reach, 0), min(int(cell[1]) + reach + 1, cols)
        if r0 >= r1 or c0 >= c1:
            return None
        rr, cc = np.mgrid[r0:r1, c0:c1]
        flat = (rr * cols + cc).ravel()
        nodes = node_of[flat]
        reached = np.zeros(flat.shape, dtype=bool)
        reached[nodes >= 0] = np.isfinite(tree.distances[nodes[nodes >= 0]])
        d2 = ((rr - cell[0]) ** 2 + (cc - cell[1]) ** 2).ravel()
        reached &= d2 <= reach * reach
        if not reached.any():
            return None
        return int(flat[np.argmin(np.where(reached, d2, np.iinfo(np.int64).max))])

    def _why_not(
        self, cost: Float32Array, spec: GridSpec, cell: IntArray, tree: _Tree
    ) -> tuple[PlanStatus, str]:
        if not spec.inside(cell[None, :])[0]:
            return PlanStatus.START_BLOCKED, "the robot is off the map"
        if np.isfinite(cost[cell[0], cell[1]]):
            return PlanStatus.UNREACHABLE, "no free way from the robot to the goal"
        return (
            PlanStatus.START_BLOCKED,
            f"the robot is inside an obstacle's footprint and no free cell within {self.escape_m} m "
            "leads to the goal",
        )

    def _smooth(self, cells: IntArray, to_goal: FloatArray, cost: Float32Array, spec: GridSpec) -> FloatArray:
        """Any-angle shortcuts over the grid path (see the module docstring); world points.
        ``to_goal``: each path cell's cost to the goal in the search (cells x (1 + w c))."""
        world = spec.to_world(cells)
        n = len(cells)
        keep = [0]
        i = 0
        while i < n - 1:
            if self._shortcut(world, to_goal, cost, spec, i, n - 1):
                j = n - 1
            else:
                lo, hi = i + 1, n - 1
                while hi - lo > 1:
                    mid = (lo + hi) // 2
                    if self._shortcut(world, to_goal, cost, spec, i, mid):
                        lo = mid
                    else:
                        hi = mid
                j = lo
            keep.append(j)
            i = j
        out: FloatArray = world[keep].copy()
        return out

    def _shortcut(
        self, world: FloatArray, to_goal: FloatArray, cost: Float32Array, spec: GridSpec, i: int, j: int
    ) -> bool:
        """Whether the straight line from path cell i to j is free and costs no more, by the search's own
        measure (length x (1 + w mean cost)), than the grid path between them (plus
        ``smooth_tolerance`` of it)."""
        if j == i + 1:
            return True
        seg = segment_cells(spec, world[i], world[j])
        rows, cols = spec.shape
        if seg.min() < 0 or seg[:, 0].max() >= rows or seg[:, 1].max() >= cols:
            return False
        on_line = cost[seg[:, 0], seg[:, 1]].astype(np.float64)
        if not np.all(np.isfinite(on_line)):
            return False
        length = math.dist(world[i], world[j]) / spec.resolution_m
        line_cost = length * (1.0 + self.clearance_weight * float(on_line.mean()))
        grid_cost = float(to_goal[i] - to_goal[j])
        return line_cost <= grid_cost * (1.0 + self.smooth_tolerance) + 1e-9


def reachable(
    costmap: Costmap, start_xy: tuple[float, float], allow_unknown: bool | None = None
) -> BoolArray:
    """The cells a robot at ``start_xy`` can reach on the costmap (one search from there)."""
    allow = costmap.config.allow_unknown if allow_unknown is None else allow_unknown
    cost = costmap.cost(allow)
    spec = costmap.spec
    out = np.zeros(spec.shape, dtype=bool)
    cell = spec.to_cell(np.array(start_xy))[0]
    if not spec.inside(cell[None, :])[0] or not np.isfinite(cost[cell[0], cell[1]]):
        return out
    graph = build_graph(cost, 0.0)
    root = int(graph.node_of[int(cell[0] * spec.shape[1] + cell[1])])
    distances = csgraph.dijkstra(graph.matrix, directed=True, indices=root)
    out.reshape(-1)[graph.cells[np.isfinite(distances)]] = True
    return out


def path_is_free(costmap: Costmap, path_m: FloatArray, allow_unknown: bool | None = None) -> bool:
    """Whether every cell along the polyline is still allowed."""
    if len(path_m) < 2:
        return len(path_m) == 1 and bool(np.isfinite(costmap.cost_at(path_m, allow_unknown)[0]))
    cost = costmap.cost(allow_unknown)
    spec = costmap.spec
    for a, b in itertools.pairwise(path_m):
        seg = segment_cells(spec, a, b)
        if not np.all(spec.inside(seg)) or not np.all(np.isfinite(cost[seg[:, 0], seg[:, 1]])):
            return False
    return True


def _blocked_reason(costmap: Costmap, cell: IntArray, allow_unknown: bool, what: str) -> str:
    spec = costmap.spec
    if not spec.inside(cell[None, :])[0]:
        return f"the {what} is off the map"
    r, c = int(cell[0]), int(cell[1])
    if costmap.unknown[r, c] and not allow_unknown:
        return f"the {what} is in unknown space (allow_unknown is off)"
    if costmap.static_occupied[r, c] or costmap.obstacles[r, c]:
        return f"the {what} is on an obstacle"
    return f"the {what} is closer than the robot's radius to an obstacle"
