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
