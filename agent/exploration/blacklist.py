"""Places the explorer will not send the robot to: a radius around each, an expiry, and a count of
failures there.

Why expiry: a target fails for reasons that pass (a person in the door, a map not yet corrected); a
blacklist that never forgets ends exploration with reachable space unseen (m-explore's "Done exploring
with N goals left", reference/eco.md §1.3). Why a count: a target that fails again and again is not retried
forever (frontier_exploration #2, #11): each failure at the same place doubles the time it stays
blacklisted, and after ``max_failures`` it stays for good.

Two kinds of entry are permanent from the start: a spot the robot reached, facing the frontier, that
stayed unknown (a gap under furniture, a corner the laser cannot see): there is nothing more to see there;
and a target whose way was shut with evidence (a door the laser now sees closed across a passage the map
had open, ``frontier_explorer.closure``): retrying it would only fail again.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from agent.navigation.costmap import BoolArray, FloatArray


class EntryKind(enum.StrEnum):
    UNREACHED = "unreached"  # the robot could not get there (may pass: expires)
    UNOBSERVABLE = "unobservable"  # the robot got there and still saw nothing (permanent)
    BLOCKED = "blocked"  # its way is shut: a door seen closed across the passage (permanent)


@dataclass
class Entry:
    x_m: float
    y_m: float
    kind: EntryKind
    reason: str
    failures: int
    until_s: float  # math.inf: for good


class Blacklist:
    def __init__(self, radius_m: float, expiry_s: float, max_failures: int) -> None:
        if radius_m <= 0.0 or expiry_s <= 0.0 or max_failures < 1:
            raise ValueError("radius_m and expiry_s must be positive, max_failures at least 1")
        self.radius_m = radius_m
        self.expiry_s = expiry_s
        self.max_failures = max_failures
        self.entries: list[Entry] = []

    def add(
        self, xy: tuple[float, float], t_s: float, reason: str, kind: EntryKind = EntryKind.UNREACHED
    ) -> Entry:
        """Blacklist ``xy``; a failure within the radius of an entry (expired or not: an expired entry
        keeps its count, so a place that keeps failing is given up in the end) counts against it."""
        for e in self.entries:
            if math.hypot(e.x_m - xy[0], e.y_m - xy[1]) <= self.radius_m:
                e.failures += 1
                e.reason = reason
                if kind is not EntryKind.UNREACHED:
                    e.kind = kind
                e.until_s = self._until(t_s, e.failures, e.kind)
                return e
        entry = Entry(float(xy[0]), float(xy[1]), kind, reason, 1, self._until(t_s, 1, kind))
        self.entries.append(entry)
        return entry

    def _until(self, t_s: float, failures: int, kind: EntryKind) -> float:
        if kind is not EntryKind.UNREACHED or failures >= self.max_failures:
            return math.inf
        return t_s + self.expiry_s * 2.0 ** (failures - 1)

    def active(self, t_s: float) -> list[Entry]:
        return [e for e in self.entries if e.until_s > t_s]

    def blocked(
        self, points_m: FloatArray, t_s: float, permanent_only: bool = False, kind: EntryKind | None = None
    ) -> BoolArray:
        """Which of the (N, 2) points lie within the radius of an active entry (only permanent ones, only
        of ``kind``, if asked)."""
        pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 2)
        out = np.zeros(len(pts), dtype=bool)
        for e in self.entries:
            if e.until_s <= t_s or (permanent_only and math.isfinite(e.until_s)):
                continue
            if kind is not None and e.kind is not kind:
                continue
            out |= np.hypot(pts[:, 0] - e.x_m, pts[:, 1] - e.y_m) <= self.radius_m
        return out

    def failed_near(self, xy: tuple[float, float]) -> bool:
        """Whether a target failed within the radius of ``xy`` before (an entry of the UNREACHED kind,
        expired or not): choosing ``xy`` now is a retry."""
        return any(
            e.kind is EntryKind.UNREACHED and math.hypot(e.x_m - xy[0], e.y_m - xy[1]) <= self.radius_m
            for e in self.entries
        )

    def permanent(self, kind: EntryKind | None = None) -> list[Entry]:
        return [e for e in self.entries if math.isinf(e.until_s) and (kind is None or e.kind is kind)]
