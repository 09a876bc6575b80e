"""Simulated people walking their looped paths as pedestrians do: they stop for the robot in their way.

A real pedestrian does not walk through an obstacle standing in their path. A person with ``yields``
(the default) looks ``lookahead_m(speed)`` ahead along their own path; when the robot's body, as they
perceived it ``reaction_s`` ago (a human reaction time), is in the way (closer to the path than the two
bodies' radii plus ``LATERAL_MARGIN_M``), they brake to stop ``STOP_GAP_M`` short of it: at the
deceleration that does it, at most ``HARD_DECEL_MPS2`` (a comfortable one when the robot was seen in
good time). When the way is clear again (again as perceived ``reaction_s`` late) they walk on,
accelerating at ``ACCEL_MPS2`` back to their speed. They never leave their path and never step aside:
the robot still has to keep out of their way, and a robot driving into a standing person, or stepping
into the path of one too close to stop, still touches them.

Pure functions over a person's path and state; :class:`drivers.sim.simulation.Simulation` steps them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from drivers.sim.world import Person

COMFORT_DECEL_MPS2 = 1.0  # a walker's unhurried stop (0.8 m/s to rest in 0.8 s, 0.32 m)
HARD_DECEL_MPS2 = 3.0  # the firmest stop a walker makes
ACCEL_MPS2 = 0.6  # back to walking speed
STOP_GAP_M = 0.3  # the gap a pedestrian leaves between their body and the robot's when they stop
LATERAL_MARGIN_M = 0.1  # the robot counts as in the way within the bodies' radii plus this
FORESIGHT_M = 0.5  # how much further ahead than their stopping distance a walker watches


def lookahead_m(speed_mps: float, reaction_s: float) -> float:
    """How far ahead along the path a walker of this speed watches for the robot."""
    return speed_mps * reaction_s + speed_mps**2 / (2.0 * COMFORT_DECEL_MPS2) + STOP_GAP_M + FORESIGHT_M


Piece = tuple[float, tuple[float, float], float, float, float]


class WalkPath:
    """A person's path, by distance walked: looped (``s_m`` grows without bound; it wraps here), or walked
    once (``loop=False``: past the end the person stands at the last point)."""

    def __init__(self, points: tuple[tuple[float, float], ...], loop: bool = True) -> None:
        self.points = points
        self.loop = loop
        n = len(points)
        if loop:
            self.legs = [(points[i], points[(i + 1) % n]) for i in range(n)] if n > 1 else []
        else:
            self.legs = [(points[i], points[i + 1]) for i in range(n - 1)]
        self.lengths = [math.dist(a, b) for a, b in self.legs]
        self.total_m = sum(self.lengths)

    def _wrap(self, s_m: float) -> float:
        return s_m % self.total_m if self.loop else min(max(s_m, 0.0), self.total_m)

    def point_at(self, s_m: float) -> tuple[float, float]:
        if self.total_m <= 0.0:
            return self.points[0] if self.loop or not self.legs else self.points[-1]
        if not self.loop and s_m >= self.total_m:
            return self.points[-1]
        d = self._wrap(s_m)
        for (a, b), length in zip(self.legs, self.lengths, strict=True):
            if d <= length and length > 0:
                w = d / length
                return (a[0] + w * (b[0] - a[0]), a[1] + w * (b[1] - a[1]))
            d -= length
        return self.points[0]

    def pieces(self, s_m: float, ahead_m: float) -> list[Piece]:
        """The straight pieces of the path from ``s_m`` to ``s_m + ahead_m``: (distance ahead of ``s_m``
        where the piece starts, its start point, its unit direction x, y, its length)."""
        out: list[Piece] = []
        if self.total_m <= 0.0:
            return out
        if not self.loop:
            if s_m >= self.total_m:
                return out
            ahead_m = min(ahead_m, self.total_m - s_m)
        d = self._wrap(s_m)
        done = 0.0
        i = 0
        # The leg holding d.
        while i < len(self.legs) and (d > self.lengths[i] or self.lengths[i] <= 0):
            d -= self.lengths[i]
            i += 1
        i %= len(self.legs)
        while done < ahead_m - 1e-12:
            (a, b), length = self.legs[i], self.lengths[i]
            if length > 0:
                ux, uy = (b[0] - a[0]) / length, (b[1] - a[1]) / length
                start = (a[0] + d * ux, a[1] + d * uy)
                piece = min(length - d, ahead_m - done)
                out.append((done, start, ux, uy, piece))
                done += piece
            d = 0.0
            i = (i + 1) % len(self.legs)
        return out

    def contact_ahead_m(self, s_m: float, ahead_m: float, xy: tuple[float, float], reach_m: float) -> float:
        """Distance along the path from ``s_m`` (within ``ahead_m``) at which a body there would come
        within ``reach_m`` of ``xy``; ``inf`` if it does not. Something behind the walker is not in the
        way (0 is returned only for something within reach and ahead of them)."""
        for k, (offset, (ax, ay), ux, uy, length) in enumerate(self.pieces(s_m, ahead_m)):
            rx, ry = xy[0] - ax, xy[1] - ay
            along = rx * ux + ry * uy
            if k == 0 and along < 0.0:
                if math.hypot(rx, ry) > reach_m:
                    continue
                return math.inf  # beside or behind them, not ahead: they walk on, away from it
            lateral = abs(rx * uy - ry * ux)
            if lateral >= reach_m:
                continue
            first = along - math.sqrt(reach_m**2 - lateral**2)
            if first <= length:
                return offset + max(first, 0.0)
        return math.inf


@dataclass
class Walker:
    """A person's state: distance walked along their path and speed now."""

    s_m: float = 0.0
    v_mps: float = 0.0


def step_walker(
    walker: Walker,
    person: Person,
    path: WalkPath,
    dt_s: float,
    robot_seen_xy: tuple[float, float] | None,
    robot_radius_m: float,
) -> None:
    """Advance ``walker`` by ``dt_s``; ``robot_seen_xy`` is where they perceive the robot (its position
    ``reaction_s`` ago), None when it is too far to matter."""
    speed = person.speed_mps
    contact = math.inf
    if person.yields and robot_seen_xy is not None:
        reach = person.radius_m + robot_radius_m + LATERAL_MARGIN_M
        contact = path.contact_ahead_m(
            walker.s_m, lookahead_m(speed, person.reaction_s), robot_seen_xy, reach
        )
    if math.isfinite(contact):
        room = contact - STOP_GAP_M
        # v^2 = 2 a d: the deceleration that stops them the gap short of the robot.
        decel = HARD_DECEL_MPS2 if room <= 1e-3 else min(walker.v_mps**2 / (2.0 * room), HARD_DECEL_MPS2)
        walker.v_mps = max(walker.v_mps - decel * dt_s, 0.0)
    elif person.yields:
        walker.v_mps = min(walker.v_mps + ACCEL_MPS2 * dt_s, speed)
    else:
        walker.v_mps = speed
    walker.s_m += walker.v_mps * dt_s


__all__ = ["WalkPath", "Walker", "lookahead_m", "step_walker"]
