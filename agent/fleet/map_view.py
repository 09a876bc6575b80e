"""The fleet's merged map: every robot's newest map (``<prefix>/*/map``), pose and topology heard on Zenoh,
merged in the shared map frame (``agent.fleet.maps``), how each pair agrees, and one picture for people.

:class:`FleetMaps` takes samples (its handlers go on any Zenoh session: ``vlp-agent fleet map`` opens its
own, ``vlp-agent sim --robots N`` puts them on its observer's); malformed or oversized messages are counted
(``rejected``), never kept. :func:`report` and :func:`picture` are pure.
"""

from __future__ import annotations

import itertools
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from agent.fleet import payloads
from agent.fleet.local_protocol import PoseMessage
from agent.fleet.maps import FREE, OCCUPIED, Grid, agreement, merge
from firmware_protocol.errors import ProtocolError

__all__ = ["KINDS", "FleetMaps", "picture", "report"]

KINDS = ("map", "pose", "topology")
_LIMITS = {
    "map": payloads.MAX_MAP_PAYLOAD,
    "pose": payloads.MAX_PAYLOAD,
    "topology": payloads.MAX_TOPOLOGY_PAYLOAD,
}


@dataclass
class FleetMaps:
    """The newest map, pose and topology per robot heard under ``key_prefix``."""

    key_prefix: str = "fleet"
    maps: dict[str, payloads.RobotMap] = field(default_factory=dict)
    poses: dict[str, PoseMessage] = field(default_factory=dict)
    topologies: dict[str, dict[str, Any]] = field(default_factory=dict)
    rejected: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def on_sample(self, kind: str, sample: Any) -> None:
        try:
            robot = payloads.robot_of(self.key_prefix, str(sample.key_expr))
            data = bytes(sample.payload.to_bytes())
            if len(data) > _LIMITS[kind]:  # the decoders check it too; before decoding anything
                raise payloads.FleetPayloadError(f"{kind}: {len(data)} bytes, over its cap")
            self.take(kind, robot, data)
        except ProtocolError:
            with self._lock:
                self.rejected += 1

    def take(self, kind: str, robot: str, data: bytes) -> None:
        """One payload of ``kind`` under ``robot``'s key; FleetPayloadError when it is not valid."""
        if kind == "map":
            decoded_map = payloads.decode_map(data, robot)
            with self._lock:
                old = self.maps.get(robot)
                if old is None or decoded_map.t_us >= old.t_us:
                    self.maps[robot] = decoded_map
        elif kind == "pose":
            pose = payloads.decode_pose(data, robot)
            with self._lock:
                self.poses[robot] = pose
        else:
            topology = payloads.decode_topology(data, robot)
            with self._lock:
                self.topologies[robot] = topology

    def handler(self, kind: str) -> Callable[[Any], None]:
        return lambda sample: self.on_sample(kind, sample)

    def subscribe(self, session: Any) -> list[Any]:
        """Subscribers for every kind on ``session`` (undeclare them, or close the session, to stop)."""
        return [
            session.declare_subscriber(f"{self.key_prefix}/*/{kind}", self.handler(kind)) for kind in KINDS
        ]

    def snapshot(
        self,
    ) -> tuple[dict[str, payloads.RobotMap], dict[str, PoseMessage], dict[str, dict[str, Any]]]:
        with self._lock:
            return dict(self.maps), dict(self.poses), dict(self.topologies)


def report(maps: dict[str, payloads.RobotMap], poses: dict[str, PoseMessage]) -> dict[str, Any]:
    """The merged map's extent and, for each pair of robots, how their maps agree where both saw."""
    out: dict[str, Any] = {"robots": [], "pairs": [], "merged": None}
    for name in sorted(set(maps) | set(poses)):
        m, p = maps.get(name), poses.get(name)
        out["robots"].append(
            {
                "robot": name,
                "pose": None if p is None else {"x_m": p.x_m, "y_m": p.y_m, "yaw_rad": p.yaw_rad},
                "map": None
                if m is None
                else {
                    "width": int(m.grid.cells.shape[1]),
                    "height": int(m.grid.cells.shape[0]),
                    "resolution_m": m.grid.resolution_m,
                    "origin_m": [m.grid.origin_x_m, m.grid.origin_y_m],
                    "known_cells": int((m.grid.cells != -1).sum()),
                    "occupied_cells": int((m.grid.cells == OCCUPIED).sum()),
                    "path_points": len(m.path),
                },
            }
        )
    if not maps:
        return out
    merged = merge([maps[n].grid for n in sorted(maps)])
    out["merged"] = {
        "width": int(merged.cells.shape[1]),
        "height": int(merged.cells.shape[0]),
        "resolution_m": merged.resolution_m,
        "origin_m": [merged.origin_x_m, merged.origin_y_m],
        "known_cells": int((merged.cells != -1).sum()),
    }
    for a, b in itertools.combinations(sorted(maps), 2):
        ag = agreement(maps[a].grid, maps[b].grid)
        out["pairs"].append(
            {
                "robots": [a, b],
                "overlap_cells": ag.overlap_cells,
                "overlap_m2": round(ag.overlap_cells * merged.resolution_m**2, 3),
                "agreement": None if ag.agree is None else round(ag.agree, 4),
                "shift_m": None if ag.shift_m is None else list(ag.shift_m),
                "shift_norm_m": None if ag.shift_norm_m is None else round(ag.shift_norm_m, 4),
                "wall_cells": list(ag.walls),
            }
        )
    return out


# Robots' colours (BGR), distinct from the map's black, grey and white.
_COLOURS = [(200, 80, 0), (0, 120, 230), (40, 160, 40), (160, 40, 160), (0, 180, 200), (90, 90, 220)]


def picture(
    maps: dict[str, payloads.RobotMap], poses: dict[str, PoseMessage], title: str = ""
) -> npt.NDArray[np.uint8]:
    """A BGR picture of the merged map (``agent.slam.render.map_picture``: axes in metres, legend, scale
    bar), each robot's recent path in its colour, and each robot as a disc with its heading and its name at
    its newest pose."""
    import cv2

    from agent import figure
    from agent.slam import render

    if not maps:
        raise ValueError("no map heard")
    merged = merge([maps[n].grid for n in sorted(maps)])
    image = _image(merged)
    names = sorted(set(maps) | set(poses))
    colour = {n: _COLOURS[i % len(_COLOURS)] for i, n in enumerate(names)}
    paths = [
        render.MapPath(f"{n}: path", np.asarray(maps[n].path, np.float64).reshape(-1, 2), colour[n])
        for n in names
        if n in maps and maps[n].path
    ]
    img = render.map_picture(image, paths, title or f"fleet map: {', '.join(names)}")
    # The robots at their poses, on the picture's axes (the same layout map_picture draws).
    h, w = merged.cells.shape
    k = max(1, math.ceil(render.MIN_MAP_PX / max(h, w, 1)))
    x0, x1, y0, y1 = merged.bounds
    left, top = render._MARGIN_LEFT, render._MARGIN_TOP
    axes = figure.Axes((left, top, left + w * k, top + h * k), (x0, x1, y0, y1))
    px_per_m = k / merged.resolution_m
    for n in names:
        p = poses.get(n)
        if p is None and n in maps and maps[n].path:
            x, y = maps[n].path[-1]
            p = PoseMessage(0, x, y, math.nan, math.nan, math.nan, 0)
        if p is None:
            continue
        u, v = axes.to_px(p.x_m, p.y_m)
        r = max(4, round(0.105 * px_per_m))
        cv2.circle(img, (u, v), r, colour[n], -1, cv2.LINE_AA)
        if math.isfinite(p.yaw_rad):
            tip = (round(u + 2 * r * math.cos(p.yaw_rad)), round(v - 2 * r * math.sin(p.yaw_rad)))
            cv2.line(img, (u, v), tip, colour[n], 2, cv2.LINE_AA)
        cv2.putText(img, n, (u + r + 4, v - r - 2), figure.FONT, 0.6, (255, 255, 255), 4, cv2.LINE_AA)
        cv2.putText(img, n, (u + r + 4, v - r - 2), figure.FONT, 0.6, colour[n], 2, cv2.LINE_AA)
    figure.text(img, "disc + name: each robot's last pose", (16, img.shape[0] - 16), 0.45)
    return img


def _image(grid: Grid) -> Any:
    from agent.slam import render

    pixels = np.full(grid.cells.shape, render.UNKNOWN_VALUE, np.uint8)
    pixels[grid.cells == FREE] = render.FREE_VALUE
    pixels[grid.cells == OCCUPIED] = render.OCCUPIED_VALUE
    return render.OccupancyImage(
        np.ascontiguousarray(pixels[::-1]), grid.resolution_m, (grid.origin_x_m, grid.origin_y_m, 0.0)
    )
