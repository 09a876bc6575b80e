"""``vlp-agent eval deliver``: "from room A to room B and back", N times, on the simulated robot with the
navigation stack, faster than real time, and how well each end was met.

The places are the world file's ``[[places]]`` (docs/world.md). The robot starts at the world's start,
drives to A, then N trips A -> B -> A; each leg is a goal at the place (its heading if it has one, any
otherwise), driven exactly as ``eval nav`` drives its goals (``agent.commands.eval_nav.run_eval``: the
same simulated sensors, localization by odometry and VLP fixes, the navigator with scans at 10 Hz and a
control step at 20 Hz), on the map a finished exploration gives: the world's walls rasterized (people and
anything else only through the scans). A trip counts when both its ends were reached (the navigator said
so and the true position is within ``--tolerance-m`` of the place, and within 5 deg of its heading if it
has one) and the robot touched nothing on the way.

With ``--explore EXPLORER`` the map is the one an exploration built instead: ``eval explore``'s run
(``run_exploration``) from an empty map at the world's start, its map (``--explore-map``: ``slam``, the
RBPF's, by default) saved as ``<map-dir>/<world>.yaml`` with its topological map beside it
(``<world>.topology.geojson``: sp2atm's HTM, or for the frontier explorer the rooms found on the final
map, with the world's ``[[places]]`` as named places naming their rooms); the file is read back and the
legs go to the places it names. The trips then start again from the world's start, on that map.
"""

from __future__ import annotations

import argparse
import json
import sys
import textwrap
from pathlib import Path
from typing import Any

import numpy as np

from agent.commands.eval_nav import GoalResult, run_eval
from agent.exploration import ExploreConfig, ExplorerKind, GridMap
from agent.navigation.costmap import BoolArray
from drivers.sim.world import Place, World

DEFAULT_TRIPS = 10
DEFAULT_TOLERANCE_M = 0.10


def add_parser(subparsers: Any) -> None:
    p: argparse.ArgumentParser = subparsers.add_parser(
        "deliver",
        help="drive from place A to place B and back N times with the navigation stack; report the trips "
        "made, the error at each end and collisions",
        description=textwrap.dedent(
            """\
            Drive the simulated robot of --world to place A (the world's [[places]]), then N times from A
            to B and back, with the navigation stack on a simulated clock, faster than real time, on the
            map a finished exploration gives, localized by odometry and VLP fixes (as eval nav). Reports
            how many trips were made with both ends within --tolerance-m of the place and no contact,
            the true error at every end, collisions, and the time."""
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--world", metavar="FILE", default=None, help="the world (default: the shipped office)")
    p.add_argument("--from", dest="place_a", required=True, metavar="A", help="the place the trips start at")
    p.add_argument("--to", dest="place_b", required=True, metavar="B", help="the place they go to")
    p.add_argument(
        "--trips", type=int, default=DEFAULT_TRIPS, metavar="N", help=f"trips (default: {DEFAULT_TRIPS})"
    )
    p.add_argument(
        "--tolerance-m",
        type=float,
        default=DEFAULT_TOLERANCE_M,
        metavar="M",
        help=f"an end is met within this of the place (default: {DEFAULT_TOLERANCE_M:g})",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed: sensor noise, people (default: 0)")
    p.add_argument(
        "--explore",
        choices=[k.value for k in ExplorerKind],
        default=None,
        metavar="EXPLORER",
        help="explore the world first from an empty map with this explorer (sp2atm or frontier), save the "
        "map and its topology under --map-dir, and drive the trips on that map to the places the saved "
        "topology names (default: the world's walls as the map)",
    )
    p.add_argument(
        "--explore-map",
        choices=["slam", "truth-pose"],
        default="slam",
        help="with --explore: the map the exploration builds (default: slam, the RBPF's map and pose)",
    )
    p.add_argument(
        "--map-dir",
        metavar="DIR",
        default="deliver-map",
        help="with --explore: where the map and its topology are saved (default: deliver-map)",
    )
    p.add_argument("--json", action="store_true", help="print the results as one JSON object on stdout")


def place(world: World, name: str, option: str) -> Place:
    from drivers.errors import ConfigError

    for p in world.places:
        if p.name == name:
            return p
    known = ", ".join(p.name for p in world.places) or "none: the world file has no [[places]]"
    raise ConfigError(option, f"no place {name!r} in world {world.name!r} (places: {known})")


def run_delivery(
    world: World,
    a: Place,
    b: Place,
    trips: int,
    seed: int,
    tolerance_m: float = DEFAULT_TOLERANCE_M,
    progress: bool = False,
    static_map: tuple[BoolArray, BoolArray] | None = None,
) -> dict[str, Any]:
    """The evaluation (see the module docstring) as a JSON-ready dict; ``static_map``: the navigator's
    map (occupied, unknown on the walls' grid) instead of the walls."""
    legs = [a] + [p for _ in range(trips) for p in (b, a)]
    results: list[GoalResult] = []

    def ended(r: GoalResult) -> None:
        results.append(r)
        if progress:
            leg = legs[len(results) - 1]
            print(
                f"  leg {len(results):3d}/{len(legs)} to {leg.name}: {r.status}, {100 * r.error_m:.1f} cm, "
                f"{r.time_s:.0f} s, {r.collisions} collisions",
                file=sys.stderr,
                flush=True,
            )

    nav = run_eval(
        world,
        len(legs),
        seed,
        on_goal=ended,
        goal_list=[(p.x_m, p.y_m, p.yaw_rad) for p in legs],
        static_map=static_map,
    )
    ends: list[dict[str, Any]] = []
    for leg, r in zip(legs, results, strict=False):
        met = r.status == "reached" and r.error_m <= tolerance_m and (leg.yaw_rad is None or r.reached)
        ends.append(
            {
                "place": leg.name,
                "met": met,
                "error_m": round(r.error_m, 4),
                "status": r.status,
                "reason": r.reason,
                "collisions": r.collisions,
                "time_s": round(r.time_s, 1),
                "driven_m": round(r.driven_m, 2),
            }
        )
    made = 0
    for k in range(trips):
        trip = ends[1 + 2 * k : 3 + 2 * k]
        if len(trip) == 2 and all(e["met"] and e["collisions"] == 0 for e in trip):
            made += 1
    trip_ends = ends[1:]
    errors = sorted(float(e["error_m"]) for e in trip_ends)
    return {
        "world": world.name,
        "seed": seed,
        "from": a.name,
        "to": b.name,
        "trips": trips,
        "trips_made": made,
        "tolerance_m": tolerance_m,
        "ends_met": sum(1 for e in trip_ends if e["met"]),
        "ends": len(trip_ends),
        "end_error_m_max": max(errors) if errors else None,
        "end_error_m_median": errors[len(errors) // 2] if errors else None,
        "collisions": nav["collisions"],
        "collisions_walls": nav["collisions_walls"],
        "collisions_people": nav["collisions_people"],
        "first_leg": ends[0] if ends else None,
        "legs": trip_ends,
        "sim_s": nav["sim_s"],
        "wall_s": nav["wall_s"],
        "map_source": nav["map_source"] if static_map is None else "the map an exploration built",
        "localization": nav["localization"],
    }


def explore_and_save(
    world: World, explorer: ExplorerKind, seed: int, map_source: str, map_dir: Path, progress: bool = False
) -> tuple[GridMap, dict[str, Any], Path, dict[str, tuple[float, float]]]:
    """Explore ``world`` from an empty map (``eval explore``'s run), save the map and its topological map
    (named places from the world's ``[[places]]``) under ``map_dir``, read the topology back: the map,
    the exploration's summary, the map's YAML and the places the saved topology names."""
    from agent.commands.eval_explore import MapSource, run_exploration
    from agent.exploration.htm import Htm
    from agent.exploration.regions import find_regions
    from agent.exploration.topology import add_named_places, from_geojson, named_places, to_geojson
    from agent.slam import mapio
    from agent.slam.render import FREE_VALUE, OCCUPIED_VALUE, UNKNOWN_VALUE, OccupancyImage

    config = ExploreConfig(explorer=explorer)
    e = run_exploration(world, explorer, seed, MapSource(map_source), progress=progress, config=config)
    grid = e.grid
    pixels = np.full(grid.spec.shape, UNKNOWN_VALUE, np.uint8)
    pixels[grid.free] = FREE_VALUE
    pixels[grid.occupied] = OCCUPIED_VALUE
    image = OccupancyImage(
        np.ascontiguousarray(pixels[::-1]), grid.spec.resolution_m, (*grid.spec.origin_m, 0.0)
    )
    yaml_path = map_dir / f"{world.name}.yaml"
    mapio.save_map(
        image, yaml_path, comment=f"vlp-agent eval deliver --explore {explorer.value}, seed {seed}"
    )
    if e.topology is not None:
        htm = from_geojson(e.topology)
    else:  # the frontier explorer keeps no graph: the rooms of the final map
        htm = Htm(config.merge_m)
        _, regions = find_regions(grid, config.door_width_m, config.min_region_m2)
        htm.set_regions([(r.polygon, r.area_m2) for r in regions])
    add_named_places(htm, [(p.name, p.x_m, p.y_m) for p in world.places])
    where = mapio.save_topology(
        to_geojson(htm, map_name=f"{world.name} (eval deliver --explore {explorer.value}, seed {seed})"),
        mapio.topology_path(yaml_path),
    )
    places = named_places(from_geojson(mapio.load_topology(where)))
    return grid, e.summary, yaml_path, places


def run(args: argparse.Namespace) -> int:
    from agent.commands.worlds import resolve_world
    from drivers.errors import ConfigError
    from drivers.sim.worldfile import load_world

    if args.trips < 1:
        raise ConfigError("--trips", "must be at least 1")
    if not args.tolerance_m > 0:
        raise ConfigError("--tolerance-m", "must be positive")
    path = resolve_world(args.world)
    world = load_world(path)
    a, b = place(world, args.place_a, "--from"), place(world, args.place_b, "--to")
    if a.name == b.name:
        raise ConfigError("--to", "must name another place than --from")
    print(
        f"vlp-agent eval deliver: {path}, {a.name} <-> {b.name}, {args.trips} trips "
        "(each leg's end on stderr)",
        file=sys.stderr,
    )
    static_map: tuple[BoolArray, BoolArray] | None = None
    explored: dict[str, Any] | None = None
    if args.explore is not None:
        print(f"  exploring first ({args.explore}, map from {args.explore_map})", file=sys.stderr)
        grid, explored, yaml_path, places = explore_and_save(
            world, ExplorerKind(args.explore), args.seed, args.explore_map, Path(args.map_dir), progress=True
        )
        for p in (a, b):
            if p.name not in places:
                raise ConfigError("--explore", f"the saved topology names no place {p.name!r}")
        # The legs go where the saved topology says (the heading is the world's: the file keeps none).
        a = Place(a.name, *places[a.name], a.yaw_rad)
        b = Place(b.name, *places[b.name], b.yaw_rad)
        static_map = (grid.occupied, grid.unknown)
        explored = {
            k: explored[k]
            for k in (
                "explorer",
                "map_source",
                "explored_fraction",
                "complete",
                "stopped_reason",
                "ate_m",
                "map_error_m",
                "path_length_m",
                "time_s",
                "collisions",
            )
        }
        explored["map"] = str(yaml_path)
        explored["topology"] = str(yaml_path.with_name(yaml_path.stem + ".topology.geojson"))
    s = run_delivery(
        world, a, b, args.trips, args.seed, args.tolerance_m, progress=True, static_map=static_map
    )
    if explored is not None:
        s["exploration"] = explored
    if args.json:
        print(json.dumps(s, sort_keys=True))
        return 0
    print(f"vlp-agent eval deliver: {s['world']}, {s['from']} -> {s['to']} and back, seed {s['seed']}")
    print(
        f"  trips made         {s['trips_made']}/{s['trips']} "
        f"(both ends within {s['tolerance_m']} m, no contact)"
    )
    print(
        f"  ends met           {s['ends_met']}/{s['ends']}; error median {s['end_error_m_median']} m, max "
        f"{s['end_error_m_max']} m"
    )
    print(
        f"  collisions         {s['collisions']} (walls {s['collisions_walls']}, people "
        f"{s['collisions_people']})"
    )
    print(f"  time               {s['sim_s']} s simulated, {s['wall_s']} s wall")
    return 0
