"""Exploration: from an empty map to a complete one (``docs/exploration.md``). Pure algorithms, as
``agent.navigation``: numpy arrays and small dataclasses in, targets and states out, time passed in; no
threads, files or ports.

Every explorer offers one interface (:class:`~agent.exploration.lifecycle.Explorer`); the config's
``[exploration] explorer`` picks one by name (:func:`make_explorer`). Implemented: ``frontier``
(explore_lite's algorithm, its cost defect fixed) and ``sp2atm`` (``sp2atm_explorer``: the AST's gaps and
the grid's frontiers as candidates, the HTM of ``htm`` with REGION nodes from ``regions``, Bellman-Ford
backtracking); ``topology`` reads and writes the HTM as nav2-route-style GeoJSON.
"""

from __future__ import annotations

from agent.exploration.blacklist import Blacklist, EntryKind
from agent.exploration.config import ExploreConfig, ExplorerKind
from agent.exploration.frontier_explorer import FrontierExplorer
from agent.exploration.frontiers import Frontier, GridMap, detect_frontiers, frontier_mask
from agent.exploration.lifecycle import Command, Decision, Explorer, ExploreState, Target
from agent.exploration.sp2atm_explorer import Sp2atmExplorer
from agent.navigation.config import NavConfig


def make_explorer(config: ExploreConfig, nav: NavConfig) -> Explorer:
    """The explorer ``config.explorer`` names."""
    if config.explorer is ExplorerKind.FRONTIER:
        return FrontierExplorer(config, nav)
    if config.explorer is ExplorerKind.SP2ATM:
        return Sp2atmExplorer(config, nav)
    raise ValueError(f"no explorer {config.explorer!r}")


__all__ = [
    "Blacklist",
    "Command",
    "Decision",
    "EntryKind",
    "ExploreConfig",
    "ExploreState",
    "Explorer",
    "ExplorerKind",
    "Frontier",
    "FrontierExplorer",
    "GridMap",
    "Sp2atmExplorer",
    "Target",
    "detect_frontiers",
    "frontier_mask",
    "make_explorer",
]
