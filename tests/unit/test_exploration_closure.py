"""A door that closes during exploration: the branch behind it is pruned at the first failure that comes
with evidence (the door seen shut wall to wall), blacklisted for good and never retried; a person in the
door, or a failure without evidence, is an ordinary failure that expires."""

from __future__ import annotations

import math

import numpy as np

from agent.exploration import (
    EntryKind,
    ExploreConfig,
    ExplorerKind,
    ExploreState,
    GridMap,
    Sp2atmExplorer,
)
from agent.exploration.closure import wall_to_wall
from agent.exploration.htm import NodeKind
from agent.exploration.lifecycle import Explorer
from agent.navigation.costmap import FloatArray
from tests.unit.exploration_helpers import NAV, SPEC, started, two_rooms

POSE = (2.5, 2.0, 0.0)


def _rooms() -> GridMap:
    """The two rooms with the west room and the east room's first 1.5 m seen, the rest unknown."""
    return two_rooms(known_to_x_m=6.0)


def _door_hits() -> FloatArray:
    """The laser's hits on the closed door: every 2.5 cm along x 4.52, y 1.5-2.5."""
    y = np.arange(1.5, 2.5, 0.025)
    return np.stack([np.full_like(y, 4.52), y], axis=1)


def _person_hits() -> FloatArray:
    """A person (0.2 m radius) standing in the door, seen from the west: the front half of a circle."""
    a = np.linspace(math.pi / 2, 3 * math.pi / 2, 24)
    return np.stack([4.6 + 0.2 * np.cos(a), 2.0 + 0.2 * np.sin(a)], axis=1)


def _started(kind: ExplorerKind) -> Explorer:
    explorer = started(ExploreConfig(explorer=kind), POSE)
    decision = explorer.update(_rooms(), POSE, 0.0)
    target = decision.target
    assert decision.state is ExploreState.EXPLORING and target is not None
    assert target.x_m > 4.5  # into the east room, through the door
    return explorer


def test_wall_to_wall_finds_a_door_shut_and_not_a_person_or_a_known_wall() -> None:
    grid = _rooms()
    near = [(5.0, 2.0), POSE[:2]]
    door = wall_to_wall(grid, _door_hits(), near, NAV.radius_m)
    assert door.any()
    xs = SPEC.to_world(np.argwhere(door))
    assert np.all(np.abs(xs[:, 0] - 4.52) < 0.1) and np.ptp(xs[:, 1]) > 0.8
    assert not wall_to_wall(grid, _person_hits(), near, NAV.radius_m).any()
    y = np.arange(0.4, 1.4, 0.025)  # the wall beside the door, which the map has already
    assert not wall_to_wall(grid, np.stack([np.full_like(y, 4.52), y], 1), near, NAV.radius_m).any()
    assert not wall_to_wall(grid, _door_hits(), [(8.0, 3.5)], NAV.radius_m, near_within_m=1.0).any()


def test_the_branch_behind_a_closed_door_is_pruned_at_the_first_failure_and_not_retried() -> None:
    for kind in (ExplorerKind.FRONTIER, ExplorerKind.SP2ATM):
        explorer = _started(kind)
        explorer.report_failed("no progress for 30 s", 10.0, _door_hits())
        assert explorer.target is None
        pruned = explorer.blocked_branches  # type: ignore[attr-defined]
        assert len(pruned) == 1 and pruned[0]["failures_before"] == 0
        (entry,) = explorer.blacklist.entries  # type: ignore[attr-defined]
        assert entry.kind is EntryKind.BLOCKED and math.isinf(entry.until_s)
        if isinstance(explorer, Sp2atmExplorer):
            assert pruned[0]["htm_nodes_pruned"] >= 1
        # The map still shows the door open (it was seen open many times): the closure is kept over it.
        for t in (11.0, 200.0, 1000.0):
            decision = explorer.update(_rooms(), POSE, t)
        assert decision.state is ExploreState.COMPLETE, (kind, decision.reason)
        assert "unreachable frontiers" in decision.reason
        assert explorer.retries == 0  # type: ignore[attr-defined]
        if isinstance(explorer, Sp2atmExplorer):
            assert not [n for n in explorer.htm.nodes.values() if n.kind is NodeKind.POSSIBLE]


def test_a_person_in_the_door_or_no_evidence_is_an_ordinary_failure_tried_again_later() -> None:
    for evidence in (_person_hits(), None):
        explorer = _started(ExplorerKind.SP2ATM)
        explorer.report_failed("no progress for 30 s", 10.0, evidence)
        assert explorer.blocked_branches == []  # type: ignore[attr-defined]
        (entry,) = explorer.blacklist.entries  # type: ignore[attr-defined]
        assert entry.kind is EntryKind.UNREACHED and math.isfinite(entry.until_s)
        decision = explorer.update(_rooms(), POSE, 11.0)
        assert decision.state is ExploreState.EXPLORING  # waiting, or another way in: never complete
        later = explorer.update(_rooms(), POSE, 10.0 + 61.0)  # the entry expired: tried again
        assert later.target is not None and later.target.x_m > 4.5
        assert explorer.retries == 1  # type: ignore[attr-defined]


def test_a_door_seen_shut_on_the_way_prunes_the_branch_before_any_failure() -> None:
    explorer = _started(ExplorerKind.FRONTIER)
    hits = _door_hits()
    explorer.evidence = lambda: hits
    decision = explorer.update(_rooms(), POSE, 2.5)  # the next decision sees the door shut
    assert decision.target is None and len(explorer.blocked_branches) == 1  # type: ignore[attr-defined]
    assert explorer.blocked_branches[0]["failure"] == "seen shut on the way"  # type: ignore[attr-defined]
    assert explorer.update(_rooms(), POSE, 3.0).state is ExploreState.COMPLETE
