"""SP2ATM's explorer and its parts beyond the AST's first level and the HTM's rules: the scan cast on the
map, regions (rooms) at doorways, nodes anchored to poses, the topological map file, and the explorer's
choices on small synthetic grids."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from agent.exploration import (
    Command,
    ExploreConfig,
    ExplorerKind,
    ExploreState,
    GridMap,
    Sp2atmExplorer,
    make_explorer,
)
from agent.exploration.admissible_tree import grid_scan
from agent.exploration.htm import Htm, NodeKind, point_in_polygon
from agent.exploration.lifecycle import Target
from agent.exploration.regions import find_regions
from agent.exploration.topology import from_geojson, to_geojson
from agent.slam.mapio import load_topology, save_topology, topology_path
from drivers.errors import ConfigError
from tests.unit.exploration_helpers import NAV, SPEC, cells, opened, started, two_rooms


def test_a_grid_scan_is_closed_at_walls_and_open_into_unknown_space() -> None:
    grid = opened(two_rooms(unknown_east=True), 0.5, 1.5, 0.55, 2.5)  # a 1 m gap in the west wall
    angles, ranges, open_ = grid_scan(grid, (2.5, 2.0, 0.0), 360, 5.0)
    north = int(np.argmin(np.abs(angles - math.pi / 2)))
    west = int(np.argmin(np.abs(np.abs(angles) - math.pi)))
    east = int(np.argmin(np.abs(angles)))
    assert not open_[north] and ranges[north] == pytest.approx(1.75, abs=0.1)  # the north wall
    assert open_[west] and ranges[west] == pytest.approx(2.0, abs=0.1)  # out through the gap
    assert open_[east] and ranges[east] == pytest.approx(2.05, abs=0.1)  # the unknown east room


# -- regions -------------------------------------------------------------------------------------------
def test_rooms_are_cut_at_a_door_and_a_wide_opening_joins_them() -> None:
    labels, regions = find_regions(two_rooms(door_m=1.0), door_width_m=1.2)
    assert len(regions) == 2
    assert all(10.0 < r.area_m2 < 15.0 for r in regions)
    west = labels[cells(2.0, 2.0, 2.05, 2.05)][0, 0]
    east = labels[cells(7.0, 2.0, 7.05, 2.05)][0, 0]
    assert west != east and west > 0 and east > 0
    assert point_in_polygon((2.5, 2.0), regions[west - 1].polygon)
    assert not point_in_polygon((6.5, 2.0), regions[west - 1].polygon)
    _, one = find_regions(two_rooms(door_m=2.0), door_width_m=1.2)  # wider than a door: one space
    assert len(one) == 1 and one[0].area_m2 > 25.0


def test_a_map_with_no_free_space_has_no_region() -> None:
    grid = GridMap(SPEC, np.zeros(SPEC.shape, bool), np.ones(SPEC.shape, bool))
    labels, regions = find_regions(grid)
    assert regions == [] and not labels.any()


def test_a_region_keeps_its_id_and_name_as_it_grows() -> None:
    htm = Htm()
    small = ((0.0, 0.0), (2.0, 0.0), (2.0, 2.0), (0.0, 2.0))
    (rid,) = htm.set_regions([(small, 4.0)])
    htm.name_region(rid, "kitchen")
    grown = ((0.0, 0.0), (4.0, 0.0), (4.0, 3.0), (0.0, 3.0))
    other = ((5.0, 0.0), (8.0, 0.0), (8.0, 3.0), (5.0, 3.0))
    ids = htm.set_regions([(grown, 12.0), (other, 9.0)])
    assert ids[0] == rid and htm.nodes[rid].name == "kitchen" and ids[1] != rid
    assert htm.region_named("kitchen") is htm.nodes[rid]
    place = htm.add_place((1.0, 1.0))
    htm.assign_regions()
    assert htm.nodes[place].region == rid
    with pytest.raises(KeyError):
        htm.name_region(place, "not a region")


# -- anchoring to poses ------------------------------------------------------------------------------
def test_nodes_anchored_to_a_pose_move_when_slam_corrects_it() -> None:
    htm = Htm()
    htm.add_pose(0, (1.0, 0.0, 0.0))
    htm.add_pose(1, (3.0, 0.0, math.pi / 2))
    home = htm.add_place((1.0, 0.0))
    htm.anchor(home, 0)
    (seen,) = htm.integrate(home, [(3.0, 1.0)], anchor=1)  # 1 m ahead of pose 1 (it faces +y)
    fixed = htm.add_place((9.0, 9.0))  # not anchored: stays
    assert htm.nodes[seen].offset_m == pytest.approx((1.0, 0.0))
    # Unchanged poses: identity (the eval's perfect map).
    assert htm.reproject({0: (1.0, 0.0, 0.0), 1: (3.0, 0.0, math.pi / 2)}) == 2
    assert (htm.nodes[seen].x_m, htm.nodes[seen].y_m) == pytest.approx((3.0, 1.0))
    # A loop closure shifts pose 1 by (0.5, -0.2) and turns it by 90 degrees more: the node follows.
    htm.reproject({1: (3.5, -0.2, math.pi)})
    assert (htm.nodes[seen].x_m, htm.nodes[seen].y_m) == pytest.approx((2.5, -0.2))
    assert (htm.nodes[home].x_m, htm.nodes[home].y_m) == pytest.approx((1.0, 0.0))
    assert (htm.nodes[fixed].x_m, htm.nodes[fixed].y_m) == (9.0, 9.0)
    assert htm.reproject({7: (0.0, 0.0, 0.0)}) == 0  # a pose no node knows


# -- the topological map file --------------------------------------------------------------------------
def _small_htm() -> Htm:
    htm = Htm(merge_m=0.5)
    htm.add_pose(0, (0.5, 0.5, 0.0))
    home = htm.add_place((0.5, 0.5))
    htm.anchor(home, 0)
    a, _ = htm.integrate(home, [(2.5, 0.5), (0.5, 2.5)], anchor=0)
    htm.visit(a)
    htm.set_regions([(((0.0, 0.0), (3.0, 0.0), (3.0, 3.0), (0.0, 3.0)), 9.0)])
    htm.assign_regions()
    return htm


def test_the_topology_round_trips_in_nav2_route_graph_style() -> None:
    htm = _small_htm()
    data = json.loads(json.dumps(to_geojson(htm, date="2026-01-01T00:00:00Z")))
    assert data["type"] == "FeatureCollection"
    points = [f for f in data["features"] if f["geometry"]["type"] == "Point"]
    lines = [f for f in data["features"] if f["geometry"]["type"] == "MultiLineString"]
    polygons = [f for f in data["features"] if f["geometry"]["type"] == "Polygon"]
    assert len(points) == 3 and len(polygons) == 1
    assert len(lines) == 2 * len(htm.edges)  # nav2's edges are directed: each written both ways
    assert {"id", "startid", "endid", "cost"} <= set(lines[0]["properties"])
    ids = [f["properties"]["id"] for f in data["features"]]
    assert len(ids) == len(set(ids))  # unique across nodes, regions and edges
    back = from_geojson(data)
    assert back.edges == pytest.approx(htm.edges)
    for nid, n in htm.nodes.items():
        m = back.nodes[nid]
        assert (m.kind, m.region, m.anchor) == (n.kind, n.region, n.anchor)
        assert (m.x_m, m.y_m) == pytest.approx((n.x_m, n.y_m), abs=1e-3)
    assert back.poses == htm.poses


def test_a_room_named_in_the_file_keeps_its_name_after_loading_and_mapping_on() -> None:
    data = to_geojson(_small_htm())
    (region,) = [f for f in data["features"] if f["properties"].get("kind") == "region"]
    region["properties"]["name"] = "mail room"  # a robot builder edits the file
    htm = from_geojson(json.loads(json.dumps(data)))
    rid = region["properties"]["id"]
    assert htm.nodes[rid].name == "mail room"
    # The map grows: the room is re-found a little larger; it keeps its id and its name.
    ids = htm.set_regions([(((0.0, 0.0), (3.5, 0.0), (3.5, 3.2), (0.0, 3.2)), 11.0)])
    assert ids == [rid] and htm.nodes[rid].name == "mail room"


def test_an_edge_without_a_cost_costs_its_length_as_in_nav2() -> None:
    data = to_geojson(_small_htm())
    for f in data["features"]:
        f["properties"].pop("cost", None)
    htm = from_geojson(data)
    assert htm.edges[(0, 1)] == pytest.approx(2.0)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d.update(type="Feature"), "FeatureCollection"),
        (lambda d: d["features"][0]["properties"].update(id="zero"), "properties.id"),
        (lambda d: d["features"].append(dict(d["features"][0])), "used twice"),
        (lambda d: d["features"][0]["geometry"].update(type="LineString"), "LineString"),
        (lambda d: d["features"][-1]["properties"].update(endid=99), "not a node"),
        (lambda d: d["features"][-1]["properties"].update(cost=-1), "cost"),
        (lambda d: d.update(version=9), "version"),
    ],
)
def test_a_broken_topology_file_is_refused_naming_what_is_wrong(edit: object, message: str) -> None:
    data = json.loads(json.dumps(to_geojson(_small_htm())))
    edit(data)  # type: ignore[operator]
    with pytest.raises(ValueError, match=message):
        from_geojson(data)


def test_the_topology_is_written_atomically_beside_the_map(tmp_path: Path) -> None:
    where = topology_path(tmp_path / "office.yaml")
    assert where.name == "office.topology.geojson"
    save_topology(to_geojson(_small_htm()), where)
    assert from_geojson(load_topology(where)).edges
    assert [p.name for p in tmp_path.iterdir()] == [where.name]  # no temporary file left
    where.write_text("{not json")
    with pytest.raises(ConfigError, match="not JSON"):
        load_topology(where)


# -- the explorer --------------------------------------------------------------------------------------
def _started(config: ExploreConfig, pose: tuple[float, float, float]) -> Sp2atmExplorer:
    explorer = started(config, pose)
    assert isinstance(explorer, Sp2atmExplorer)
    return explorer


SP2ATM = ExploreConfig(explorer=ExplorerKind.SP2ATM)


def test_it_drives_through_the_gap_and_builds_the_htm() -> None:
    grid = opened(two_rooms(), 0.5, 1.5, 0.55, 2.5)  # a 1 m gap in the west wall
    pose = (2.5, 2.0, 0.0)
    explorer = _started(SP2ATM, pose)
    decision = explorer.update(grid, pose, 0.0)
    assert decision.state is ExploreState.EXPLORING and decision.new_target
    target = decision.target
    assert target is not None and target.x_m < 1.2 and 1.4 < target.y_m < 2.6
    assert target.yaw_rad is not None and abs(abs(target.yaw_rad) - math.pi) < math.radians(45)
    kinds = [n.kind for n in explorer.htm.nodes.values()]
    assert kinds.count(NodeKind.PLACE) == 1 and kinds.count(NodeKind.POSSIBLE) >= 1
    assert kinds.count(NodeKind.REGION) == 2  # the two rooms
    place = explorer.place
    assert place is not None and explorer.htm.nodes[place].region is not None
    # Reached: its node becomes a place, linked to the first.
    explorer.report_reached(5.0)
    assert [n.kind for n in explorer.htm.nodes.values()].count(NodeKind.PLACE) == 2
    assert explorer.place is not None and (place, explorer.place) in explorer.htm.edges


def test_the_current_target_is_kept_while_it_has_gain_though_no_candidate_lies_near_it() -> None:
    """Commitment: the current target is a candidate of its own, costed where it is, its node kept; on a
    map whose candidates shift with each update it is not dropped for want of a candidate within merge_m."""
    grid = two_rooms(unknown_east=True)  # the east room unseen behind its 1 m door at x 4.5, y 2
    pose = (2.5, 2.0, 0.0)
    explorer = _started(SP2ATM, pose)
    first = explorer.update(grid, pose, 0.0).target
    assert first is not None and first.x_m > 4.0
    # A target 1.1 m short of the door (as chosen from elsewhere, or the candidates moved since): no
    # candidate of this map lies within merge_m of it, yet the door's frontier is within gain_radius_m.
    held = Target(3.4, 2.0, 0.0)
    explorer.target = held
    near = [
        math.hypot(c.target.x_m - 3.4, c.target.y_m - 2.0)
        for c in explorer.survey(grid, pose, 1.0).candidates
    ]
    assert min(near) == 0.0 and sorted(near)[1] > SP2ATM.merge_m  # only itself
    decision = explorer.update(grid, pose, 2.5)  # a replan: the door's own target is farther, not cheaper
    assert decision.target == held
    assert explorer.switches == 0
    node = explorer._target_node
    assert node is not None and explorer.htm.nodes[node].kind is NodeKind.POSSIBLE
    # The east room seen: nothing left to gain there, the target goes and exploration is complete.
    seen = two_rooms()
    assert explorer.update(seen, pose, 5.0).state is ExploreState.COMPLETE


def test_a_reached_target_whose_frontier_stayed_unknown_is_not_driven_to_again() -> None:
    """The arrival judged with SP2ATM's gain: the robot stood at the target facing the frontier and the map
    did not change (a shadow): that frontier gains nothing from then on, so no target near it comes back
    (the frontier explorer's own rule blocks only the spot and its 0.5 m)."""
    grid = two_rooms(unknown_east=True)
    pose = (2.5, 2.0, 0.0)
    explorer = _started(SP2ATM, pose)
    target = explorer.update(grid, pose, 0.0).target
    assert target is not None and target.x_m > 4.0
    at = (target.x_m, target.y_m, target.yaw_rad or 0.0)
    explorer.report_reached(1.0)
    for t in (1.6, 4.0, 8.0):  # settled, the same map: nothing was seen from there
        decision = explorer.update(grid, at, t)
        assert decision.target is None, decision.target
    assert decision.state is ExploreState.COMPLETE and "slivers" in decision.reason


def test_a_closed_map_is_complete_and_its_htm_has_nothing_possible() -> None:
    explorer = _started(SP2ATM, (2.5, 2.0, 0.0))
    decision = explorer.update(two_rooms(), (2.5, 2.0, 0.0), 0.0)
    assert decision.state is ExploreState.COMPLETE and decision.target is None
    assert explorer.htm.done


def test_it_finishes_its_own_room_before_a_cheaper_gap_next_door() -> None:
    """SP2ATM's rule: the candidates of the robot's room come first. The frontier explorer takes the
    cheaper gap in the next room and has to come back for this room's later."""
    grid = opened(two_rooms(), 1.0, 3.75, 2.0, 3.8)  # 1 m gap north in the west room, about 3 m away
    grid = opened(grid, 5.0, 0.25, 6.0, 0.3)  # 1 m gap south in the east room, about 2 m away
    pose = (4.0, 2.0, 0.0)
    sp2atm = _started(SP2ATM, pose).update(grid, pose, 0.0).target
    frontier = make_explorer(ExploreConfig(), NAV)
    frontier.command(Command.START, pose, 0.0)
    greedy = frontier.update(grid, pose, 0.0).target
    assert sp2atm is not None and greedy is not None
    assert sp2atm.x_m < 2.5 and sp2atm.y_m > 3.0  # the west room's own gap
    assert greedy.x_m > 4.5 and greedy.y_m < 1.0  # the east room's
    # With no preference for the room (locality 0) SP2ATM picks the cheaper one too.
    flat = _started(ExploreConfig(explorer=SP2ATM.explorer, locality_m=0.0), pose)
    assert flat.update(grid, pose, 0.0).target == greedy or (
        flat.target is not None and flat.target.x_m > 4.5
    )


def test_no_premature_complete_while_a_reachable_gap_is_only_blacklisted_for_now() -> None:
    config = ExploreConfig(
        explorer=SP2ATM.explorer, blacklist_radius_m=1.0, blacklist_expiry_s=10.0, max_failures=2
    )
    grid = opened(two_rooms(), 0.5, 1.5, 0.55, 2.5)
    pose = (2.5, 2.0, 0.0)
    explorer = _started(config, pose)
    assert explorer.update(grid, pose, 0.0).target is not None
    explorer.report_failed("blocked ahead", 1.0)
    waiting = explorer.update(grid, pose, 2.0)
    assert waiting.state is ExploreState.EXPLORING and waiting.target is None
    again = explorer.update(grid, pose, 12.0)
    assert again.target is not None
    explorer.report_failed("blocked ahead", 13.0)
    assert explorer.update(grid, pose, 14.0).state is ExploreState.FAILED


def test_the_explorer_writes_its_topology_and_moves_it_with_corrected_poses() -> None:
    grid = opened(two_rooms(), 0.5, 1.5, 0.55, 2.5)
    pose = (2.5, 2.0, 0.0)
    explorer = _started(SP2ATM, pose)
    explorer.update(grid, pose, 0.0)
    anchors = explorer.anchors
    assert anchors and all(len(p) == 3 for p in anchors.values())
    before = {i: (n.x_m, n.y_m) for i, n in explorer.htm.nodes.items() if n.anchor is not None}
    shifted = {pid: (x + 0.2, y, yaw) for pid, (x, y, yaw) in anchors.items()}
    assert explorer.correct_poses(shifted) == len(before)
    for i, (x, y) in before.items():
        assert (explorer.htm.nodes[i].x_m, explorer.htm.nodes[i].y_m) == pytest.approx((x + 0.2, y))
    back = from_geojson(json.loads(json.dumps(explorer.topology())))
    assert set(back.nodes) == set(explorer.htm.nodes)


def test_only_unknown_worth_a_trip_gives_information() -> None:
    from agent.exploration.sp2atm_explorer import informative_unknown

    grid = two_rooms(unknown_east=True)  # the east room unseen behind its door: worth it
    occupied, unknown = grid.occupied.copy(), grid.unknown.copy()
    unknown[cells(1.0, 1.0, 3.0, 1.1)] = True  # a sliver 2 cells wide between far beams
    box = cells(1.0, 2.5, 2.0, 3.3)  # a box: walls seen, inside never
    occupied[box] = True
    unknown[box[0].start + 1 : box[0].stop - 1, box[1].start + 1 : box[1].stop - 1] = True
    occupied[box[0].start + 1 : box[0].stop - 1, box[1].start + 1 : box[1].stop - 1] = False
    keep = informative_unknown(GridMap(SPEC, occupied, unknown), 0.25)
    assert keep[cells(6.0, 2.0, 6.05, 2.05)].all()  # the east room
    assert not keep[cells(1.0, 1.0, 3.0, 1.1)].any()  # the sliver
    assert not keep[cells(1.2, 2.7, 1.8, 3.1)].any()  # the box's inside


def test_backtracking_survives_a_misfired_negative_cycle_check(monkeypatch: pytest.MonkeyPatch) -> None:
    """scipy's Bellman-Ford once reported a negative cycle on a graph of costs >= 1e-9 (office, seed 2)
    and ended the run; with no negative cost, Dijkstra's way is the same."""
    from scipy.sparse import csgraph

    htm = Htm(merge_m=0.5)
    home = htm.add_place((0.0, 0.0))
    near, _ = htm.integrate(home, [(2.0, 0.0), (-5.0, 0.0)])
    htm.visit(near)
    (here,) = htm.integrate(near, [(3.0, 0.0)])
    htm.visit(here)
    expected = htm.backtrack(here)

    def misfire(*args: object, **kwargs: object) -> None:
        raise csgraph.NegativeCycleError("misfired")

    monkeypatch.setattr(csgraph, "bellman_ford", misfire)
    assert htm.backtrack(here) == expected == [here, near, home]


def test_the_office_is_cut_into_its_eight_rooms_and_the_corridor() -> None:
    from agent.commands.eval_explore import reachable_free
    from agent.commands.eval_nav import rasterize_walls
    from agent.shipped import WORLDS
    from drivers.sim.worldfile import load_world

    world = load_world(WORLDS / "office.toml")
    spec, walls = rasterize_walls(world, 0.05)
    inside = reachable_free(spec, walls, (world.robot.start.x_m, world.robot.start.y_m))
    grid = GridMap(spec, walls, ~inside & ~walls)  # the whole floor mapped
    labels, regions = find_regions(grid, door_width_m=1.2)
    assert len(regions) == 9
    assert 35.0 < regions[0].area_m2 < 42.0  # the corridor, 20 x 2 m less its walls
    assert all(20.0 < r.area_m2 < 26.0 for r in regions[1:])  # the 5 x 5 m rooms
    cell = spec.to_cell(np.array([10.0, 6.0]))[0]
    assert labels[cell[0], cell[1]] == regions[0].label  # the corridor's middle
    centres = [(2.5 + 5.0 * i, y) for i in range(4) for y in (2.5, 9.5)]
    for r in regions[1:]:  # each room's outline holds one room's centre
        assert sum(point_in_polygon(c, r.polygon) for c in centres) == 1
    assert all(sum(point_in_polygon(c, r.polygon) for r in regions) == 1 for c in centres)


def test_frontier_behind_a_wall_is_out_of_sight() -> None:
    """Gain is frontier in sight of the candidate: the frontier of the room behind a wall, within the gain
    radius, is not (office seed 0: a tip in a corner of room N2 drew its gain from room N1 through the
    wall); through the door it is."""
    from agent.exploration.sp2atm_explorer import in_sight

    grid = two_rooms()  # the shared wall at x 4.5-4.55, the door at y 1.5-2.5
    spot = np.array([[4.0, 2.6]])  # west of the wall, by the door
    behind = np.array([[5.0, 3.2], [5.2, 3.4]])  # east of the wall, within 1.5 m
    through = np.array([[5.0, 2.0]])  # seen through the door
    targets = np.concatenate([behind, through])
    pairs = np.ones((1, 3), dtype=bool)
    assert in_sight(grid, spot, targets, pairs).tolist() == [[False, False, True]]
    open_wall = opened(grid, 4.5, 0.3, 4.55, 3.7)  # no wall: all in sight
    assert in_sight(open_wall, spot, targets, pairs).all()
    assert not in_sight(grid, spot, targets, np.zeros((1, 3), dtype=bool)).any()  # only the pairs asked
