"""The exploration's settings: one frozen dataclass, read from the config file's ``[exploration]`` table by
``agent.config`` (keys and meanings: ``docs/exploration.md``).

The frontier defaults follow explore_lite's ``params.yaml`` (potential_scale 3.0, gain_scale 1.0,
progress_timeout 30 s) except where its choices hurt here: ``min_frontier_size_m`` is 0.3 m, not 0.75 m (a
door seen at a slant shows a frontier shorter than 0.75 m, and dropping it ends exploration with a room
unseen: the users' "stops with unknown space visible", reference/eco.md §1.3).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass


class ExplorerKind(enum.StrEnum):
    FRONTIER = "frontier"
    SP2ATM = "sp2atm"


@dataclass(frozen=True)
class NamedPoint:
    """A place the user names (``[[exploration.places]]``): a room's name for the topological map and a
    goal for go-to-place missions."""

    name: str
    x_m: float
    y_m: float
    yaw_rad: float | None = None  # the heading to stop at (None: any)


@dataclass(frozen=True)
class ExploreConfig:
    explorer: ExplorerKind = ExplorerKind.FRONTIER
    # frontiers
    min_frontier_size_m: float = 0.3  # clusters shorter than this (cells x resolution) are noise
    min_unknown_m2: float = 0.1  # unknown pockets smaller than this (inside walls, between hits) are noise
    target_reach_m: float = 0.35  # a frontier's targets: free cells this close to it the robot can stand on
    target_clearance_m: float = 0.1  # ... with this much room beyond the footprint (scans add noise marks)
    # choice: cost = potential_scale x path cost (m) - gain_scale x frontier length (m)
    potential_scale: float = 3.0
    gain_scale: float = 1.0
    switch_margin: float = 1.0  # a new best frontier must be this much cheaper to replace the current one
    replan_period_s: float = 2.0  # how often frontiers are re-detected while driving to a target
    # progress and the blacklist
    target_reached_m: float = 0.25  # the robot is at its target within this
    progress_m: float = 0.1  # what counts as getting closer to the target
    progress_timeout_s: float = 30.0  # no progress for this long: the target is blacklisted
    blacklist_radius_m: float = 0.5  # around a blacklisted target no target is chosen ...
    blacklist_expiry_s: float = 60.0  # ... for this long (doubling with each failure there)
    max_failures: int = 3  # failures at one place before it is given up for good
    # the end
    return_home: bool = False  # drive back to where exploration started once it is complete
    # SP2ATM (explorer = "sp2atm"; docs/exploration.md)
    merge_m: float = 0.75  # a possible node this close to an HTM node is bound to it (rebind), not added
    place_spacing_m: float = 1.0  # the robot farther than this from every place: a new PLACE node
    gain_radius_m: float = 1.5  # information gain: metres of frontier within this of a candidate
    min_gain_m2: float = (
        0.25  # unknown pockets smaller than this (after a 3 x 3 opening) are not worth a trip
    )
    ast_beams: int = 180  # beams of the scan cast on the map the AST is grown from
    ast_range_m: float = 5.0  # their range
    locality_m: float = 3.0  # a candidate outside the current place and room wins only if this much cheaper
    door_width_m: float = 1.2  # passages narrower than this separate regions (rooms)
    min_region_m2: float = 1.0  # a region's core (the part wider than a door) at least this large
    # the user's named places ([[exploration.places]]): saved in the topological map, missions' goals
    places: tuple[NamedPoint, ...] = ()
