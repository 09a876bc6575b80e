"""The topological map as GeoJSON, modelled on nav2's route graph (``nav2_route``'s GeoJSON graph files):
a dict in, a dict out (``json.dumps`` / ``json.loads`` it; writing it beside the occupancy map is
``agent.slam.mapio.save_topology``). The format is documented in ``docs/exploration.md`` ("The topological
map file").

As in nav2: one ``FeatureCollection``; every node a ``Point`` feature with ``properties.id`` and
``properties.frame``; every edge a ``MultiLineString`` feature with ``id``, ``startid``, ``endid``,
``cost`` (metres) and ``overridable``; an edge is directed in nav2, so each of the HTM's undirected edges is
written both ways (reading merges them, the cheaper cost kept). What the HTM adds goes where nav2 keeps
extras, in ``properties.metadata``: a node's ``kind`` (``place`` or ``possible``), its ``region`` and its
``anchor`` (the pose id it is kept relative to, and its offset in that pose's frame). Regions (rooms) are
``Polygon`` features with ``properties.kind = "region"``, ``id``, ``name`` (editable: a robot builder
names a room by editing it) and ``metadata.area_m2``; the poses nodes are anchored to are a top-level
``poses`` member. Ids are unique across nodes, regions and edges (nav2's rule).

Pure: no I/O, no clock (the date is passed in).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable
from typing import Any

from agent.exploration.htm import Htm, Node, NodeKind, point_in_polygon, polygon_centre

FORMAT = "vlp-agent-topology"
VERSION = 1


def to_geojson(htm: Htm, frame: str = "map", date: str = "", map_name: str = "") -> dict[str, Any]:
    """``htm`` as a GeoJSON FeatureCollection (see the module docstring)."""
    features: list[dict[str, Any]] = []
    for n in sorted(htm.nodes.values(), key=lambda n: n.id):
        if n.kind is NodeKind.REGION:
            ring = [[x, y] for x, y in n.polygon]
            if ring and ring[0] != ring[-1]:
                ring.append(ring[0])
            features.append(
                {
                    "type": "Feature",
                    "geometry": {"type": "Polygon", "coordinates": [ring]},
                    "properties": {
                        "id": n.id,
                        "kind": "region",
                        "name": n.name,
                        "frame": frame,
                        "metadata": {"area_m2": round(n.area_m2, 3), "centre": [_r(n.x_m), _r(n.y_m)]},
                    },
                }
            )
            continue
        meta: dict[str, Any] = {"kind": n.kind.value, "sightings": n.sightings}
        if n.region is not None:
            meta["region"] = n.region
        if n.anchor is not None:
            meta["anchor"] = {"pose": n.anchor, "dx": _r(n.offset_m[0]), "dy": _r(n.offset_m[1])}
        if n.name:
            meta["name"] = n.name
        features.append(
            {
                "type": "Feature",
                "geometry": {"type": "Point", "coordinates": [_r(n.x_m), _r(n.y_m)]},
                "properties": {"id": n.id, "frame": frame, "metadata": meta},
            }
        )
    next_id = max(htm.nodes, default=-1) + 1
    for (a, b), cost in sorted(htm.edges.items()):
        for start, end in ((a, b), (b, a)):
            s, e = htm.nodes[start], htm.nodes[end]
            features.append(
                {
                    "type": "Feature",
                    "geometry": {
                        "type": "MultiLineString",
                        "coordinates": [[[_r(s.x_m), _r(s.y_m)], [_r(e.x_m), _r(e.y_m)]]],
                    },
                    "properties": {
                        "id": next_id,
                        "startid": start,
                        "endid": end,
                        "cost": _r(cost),
                        "overridable": False,
                    },
                }
            )
            next_id += 1
    out: dict[str, Any] = {
        "type": "FeatureCollection",
        "name": "vlp-agent topology",
        "format": FORMAT,
        "version": VERSION,
        "frame": frame,
        "merge_m": htm.merge_m,
        "poses": [
            {"id": pid, "x": _r(p[0]), "y": _r(p[1]), "yaw": _r(p[2])} for pid, p in sorted(htm.poses.items())
        ],
        "features": features,
    }
    if date:
        out["date_generated"] = date
    if map_name:
        out["map"] = map_name
    return out


def from_geojson(data: Any) -> Htm:
    """An HTM from a dict :func:`to_geojson` made (or a person edited); ``ValueError`` naming what is
    wrong. Features this format does not know (another tool's) are refused, not dropped silently."""
    if not isinstance(data, dict) or data.get("type") != "FeatureCollection":
        raise ValueError("not a GeoJSON FeatureCollection")
    if data.get("format", FORMAT) != FORMAT:
        raise ValueError(f"format {data.get('format')!r}, expected {FORMAT!r}")
    if data.get("version", VERSION) != VERSION:
        raise ValueError(f"version {data.get('version')!r}; this reader knows version {VERSION}")
    merge = data.get("merge_m", 0.75)
    htm = Htm(merge_m=_number(merge, "merge_m"))
    for i, p in enumerate(_list(data.get("poses", []), "poses")):
        where = f"poses[{i}]"
        if not isinstance(p, dict):
            raise ValueError(f"{where}: must be an object")
        htm.add_pose(
            _int(p.get("id"), f"{where}.id"),
            (
                _number(p.get("x"), f"{where}.x"),
                _number(p.get("y"), f"{where}.y"),
                _number(p.get("yaw"), f"{where}.yaw"),
            ),
        )
    edges: list[tuple[int, int, float, str]] = []
    ids: set[int] = set()
    for i, f in enumerate(_list(data.get("features"), "features")):
        where = f"features[{i}]"
        if not isinstance(f, dict) or f.get("type") != "Feature":
            raise ValueError(f"{where}: not a Feature")
        geometry, props = f.get("geometry"), f.get("properties")
        if not isinstance(geometry, dict) or not isinstance(props, dict):
            raise ValueError(f"{where}: needs a geometry and properties")
        fid = _int(props.get("id"), f"{where}.properties.id")
        if fid in ids:
            raise ValueError(f"{where}: id {fid} used twice")
        ids.add(fid)
        kind = geometry.get("type")
        coords = geometry.get("coordinates")
        if kind == "Point":
            x, y = _xy(coords, f"{where}.geometry")
            meta = props.get("metadata", {})
            if not isinstance(meta, dict):
                raise ValueError(f"{where}.properties.metadata: must be an object")
            try:
                node_kind = NodeKind(meta.get("kind", "place"))
            except ValueError:
                raise ValueError(f"{where}: kind {meta.get('kind')!r} is not place or possible") from None
            if node_kind is NodeKind.REGION:
                raise ValueError(f"{where}: a region is a Polygon, not a Point")
            node = Node(fid, node_kind, x, y, _int(meta.get("sightings", 1), f"{where}.sightings"))
            if "region" in meta:
                node.region = _int(meta["region"], f"{where}.metadata.region")
            if "name" in meta:
                if not isinstance(meta["name"], str):
                    raise ValueError(f"{where}.properties.metadata.name: must be a string")
                node.name = meta["name"]
            if "anchor" in meta:
                a = meta["anchor"]
                if not isinstance(a, dict):
                    raise ValueError(f"{where}.metadata.anchor: must be an object")
                node.anchor = _int(a.get("pose"), f"{where}.metadata.anchor.pose")
                node.offset_m = (
                    _number(a.get("dx"), f"{where}.anchor.dx"),
                    _number(a.get("dy"), f"{where}.anchor.dy"),
                )
                if node.anchor not in htm.poses:
                    raise ValueError(f"{where}: anchored to pose {node.anchor}, which is not in poses")
            htm.restore(node)
        elif kind == "Polygon":
            if props.get("kind") != "region":
                raise ValueError(f'{where}: a Polygon must be a region (properties.kind = "region")')
            rings = _list(coords, f"{where}.geometry.coordinates")
            if not rings:
                raise ValueError(f"{where}: a Polygon needs a ring")
            ring = [_xy(p, f"{where}.geometry") for p in _list(rings[0], f"{where}.geometry ring")]
            if len(ring) > 1 and ring[0] == ring[-1]:
                ring = ring[:-1]
            if len(ring) < 3:
                raise ValueError(f"{where}: a region's outline needs at least 3 points")
            name = props.get("name", "")
            if not isinstance(name, str):
                raise ValueError(f"{where}.properties.name: must be a string")
            meta = props.get("metadata", {})
            area = (
                _number(meta.get("area_m2", 0.0), f"{where}.metadata.area_m2")
                if isinstance(meta, dict)
                else 0.0
            )
            cx, cy = polygon_centre(tuple(ring))
            region = Node(fid, NodeKind.REGION, cx, cy, name=name, polygon=tuple(ring), area_m2=area)
            htm.restore(region)
        elif kind == "MultiLineString":
            start = _int(props.get("startid"), f"{where}.properties.startid")
            end = _int(props.get("endid"), f"{where}.properties.endid")
            if "cost" in props:
                cost = _number(props["cost"], f"{where}.properties.cost")
            else:  # nav2's default: the edge's length
                line = _list(_list(coords, f"{where}.geometry.coordinates")[0], f"{where}.geometry")
                pts = [_xy(p, f"{where}.geometry") for p in line]
                cost = sum(math.dist(p, q) for p, q in itertools.pairwise(pts))
            if not (cost >= 0.0 and math.isfinite(cost)):
                raise ValueError(f"{where}: cost must be a finite number >= 0, got {cost}")
            edges.append((start, end, cost, where))
        else:
            raise ValueError(f"{where}: geometry {kind!r} is not a Point, MultiLineString or Polygon")
    for start, end, cost, where in edges:
        for end_id in (start, end):
            if end_id not in htm.nodes or htm.nodes[end_id].kind is NodeKind.REGION:
                raise ValueError(f"{where}: edge end {end_id} is not a node")
        htm.link(start, end, cost)
    for n in htm.nodes.values():
        if n.region is not None and (
            n.region not in htm.nodes or htm.nodes[n.region].kind is not NodeKind.REGION
        ):
            raise ValueError(f"node {n.id}: region {n.region} is not a region")
    return htm


def add_named_places(htm: Htm, places: Iterable[tuple[str, float, float]]) -> None:
    """The user's places (``name, x, y``: a world file's or the config's ``[[places]]``) as named PLACE
    nodes (one per name: a place of that name is moved there), each naming the region (room) it lies in
    when that region has no name yet."""
    for name, x, y in places:
        if not name:
            raise ValueError("a place needs a name")
        old = next((n for n in htm.nodes.values() if n.kind is NodeKind.PLACE and n.name == name), None)
        if old is None:
            old = htm.nodes[htm.add_place((x, y))]
            old.name = name
        old.x_m, old.y_m, old.anchor = x, y, None
        for r in htm.regions():
            if point_in_polygon((x, y), r.polygon):
                old.region = r.id
                if not r.name:
                    r.name = name
                break


def named_places(htm: Htm) -> dict[str, tuple[float, float]]:
    """Where each name leads: named PLACE nodes, and named regions (their centre) no place is named
    after; what a go-to-place mission can go to."""
    out: dict[str, tuple[float, float]] = {}
    for n in sorted(htm.regions(), key=lambda n: n.id):
        if n.name:
            out[n.name] = (n.x_m, n.y_m)
    for n in htm.nodes.values():
        if n.kind is NodeKind.PLACE and n.name:
            out[n.name] = (n.x_m, n.y_m)
    return out


def _r(v: float) -> float:
    return round(float(v), 4)


def _list(v: Any, where: str) -> list[Any]:
    if not isinstance(v, list):
        raise ValueError(f"{where}: must be a list")
    return v


def _number(v: Any, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ValueError(f"{where}: must be a finite number, got {v!r}")
    return float(v)


def _int(v: Any, where: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise ValueError(f"{where}: must be an integer, got {v!r}")
    return v


def _xy(v: Any, where: str) -> tuple[float, float]:
    if not isinstance(v, list) or len(v) < 2:
        raise ValueError(f"{where}: a position is [x, y]")
    return _number(v[0], where), _number(v[1], where)
