"""SP2ATM's hierarchical topology map: append, rebind, remove, visit, backtracking, termination."""

from __future__ import annotations

import pytest

from agent.exploration.htm import Htm, NodeKind


def test_append_adds_possible_nodes_with_edges_from_the_place() -> None:
    htm = Htm(merge_m=0.75)
    home = htm.add_place((0.0, 0.0))
    a, b = htm.integrate(home, [(3.0, 0.0), (0.0, 4.0)])
    assert htm.nodes[a].kind is NodeKind.POSSIBLE and htm.nodes[b].kind is NodeKind.POSSIBLE
    assert htm.edges[(home, a)] == pytest.approx(3.0)
    assert htm.edges[(home, b)] == pytest.approx(4.0)
    assert not htm.done


def test_rebind_does_not_duplicate_a_node_seen_again_and_averages_it() -> None:
    htm = Htm(merge_m=0.75)
    home = htm.add_place((0.0, 0.0))
    (a,) = htm.integrate(home, [(3.0, 0.0)])
    htm.visit(a)  # the robot went there; from there it sees a doorway
    (door,) = htm.integrate(a, [(3.0, 3.0)])
    (again,) = htm.integrate(home, [(3.2, 3.0)])  # the same doorway, seen from home: a loop closure
    assert again == door and len(htm.nodes) == 3
    assert htm.nodes[door].x_m == pytest.approx(3.1)
    assert (home, door) in htm.edges and (a, door) in htm.edges


def test_remove_takes_the_node_and_its_edges_and_refuses_places() -> None:
    htm = Htm()
    home = htm.add_place((0.0, 0.0))
    (a,) = htm.integrate(home, [(2.0, 0.0)])
    htm.remove(a)
    assert a not in htm.nodes and htm.edges == {} and htm.done
    with pytest.raises(ValueError):
        htm.remove(home)


def test_backtracking_goes_to_the_nearest_place_with_something_left() -> None:
    #  far(place, 1 possible) -- 5 m -- home(place) -- 2 m -- near(place, 1 possible) -- 1 m -- here(place)
    htm = Htm(merge_m=0.5)
    home = htm.add_place((0.0, 0.0))
    near, far = htm.integrate(home, [(2.0, 0.0), (-5.0, 0.0)])
    htm.visit(near)
    htm.visit(far)
    htm.integrate(near, [(2.0, 3.0)])
    htm.integrate(far, [(-5.0, 3.0)])
    (here,) = htm.integrate(near, [(3.0, 0.0)])
    htm.visit(here)
    way = htm.backtrack(here)
    assert way == [here, near]
    # Once near's branch is explored (removed), the way leads back through home to far.
    (left,) = [n for n in htm.neighbours(near) if htm.nodes[n].kind is NodeKind.POSSIBLE]
    htm.remove(left)
    assert htm.backtrack(here) == [here, near, home, far]


def test_nothing_left_means_done_and_no_backtracking() -> None:
    htm = Htm()
    home = htm.add_place((0.0, 0.0))
    (a,) = htm.integrate(home, [(2.0, 0.0)])
    htm.visit(a)
    assert htm.done and htm.backtrack(a) is None
