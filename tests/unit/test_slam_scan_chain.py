"""The final optimisation's chain (``agent.slam.scan_chain``): a scan registered on the one before it
recovers their relative pose, a registration that cannot be trusted is not kept, and the chain keeps the
front end's step there; ``RbpfSlam.finish`` runs only with a loop factor to hold the chain."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from agent.slam.pose import between, compose, inverse, transform_points
from agent.slam.rbpf import RbpfConfig
from agent.slam.replay import replay
from agent.slam.scan_chain import ScanChainConfig, register_pair, scan_chain
from agent.slam.simlog import simulate_log
from drivers.sim.worldfile import load_world

OFFICE = Path(__file__).resolve().parents[2] / "examples" / "worlds" / "office.toml"


def _room(rng: np.random.Generator) -> np.ndarray:
    """World endpoints of an L-shaped room with a pillar: walls sampled every 5 cm, 1 cm range noise."""
    segments = [
        ((0.0, 0.0), (8.0, 0.0)),
        ((8.0, 0.0), (8.0, 3.0)),
        ((8.0, 3.0), (4.0, 3.0)),
        ((4.0, 3.0), (4.0, 6.0)),
        ((4.0, 6.0), (0.0, 6.0)),
        ((0.0, 6.0), (0.0, 0.0)),
        ((2.0, 2.0), (2.5, 2.0)),
        ((2.5, 2.0), (2.5, 2.5)),
    ]
    points = []
    for (x0, y0), (x1, y1) in segments:
        n = max(2, int(math.hypot(x1 - x0, y1 - y0) / 0.05))
        t = np.linspace(0.0, 1.0, n)
        points.append(np.stack([x0 + t * (x1 - x0), y0 + t * (y1 - y0)], axis=1))
    world = np.vstack(points)
    return world + rng.normal(0.0, 0.01, world.shape)


def _seen_from(world: np.ndarray, pose: np.ndarray, reach_m: float = 6.0) -> np.ndarray:
    local = transform_points(inverse(pose), world)
    return local[np.hypot(local[:, 0], local[:, 1]) < reach_m]


def test_a_scan_registered_on_the_one_before_recovers_their_relative_pose() -> None:
    rng = np.random.default_rng(0)
    world = _room(rng)
    a, b = np.array([1.0, 1.0, 0.1]), np.array([1.9, 1.3, 0.25])
    truth = between(a, b)
    guess = compose(truth, np.array([0.08, -0.06, math.radians(3.0)]))
    found = register_pair(_seen_from(world, a), _seen_from(_room(rng), b), guess, ScanChainConfig())
    assert found is not None
    pose, inliers = found
    assert math.hypot(*(pose[:2] - truth[:2])) < 0.01
    assert abs(pose[2] - truth[2]) < math.radians(0.3)
    assert inliers > 0.9


def test_a_registration_that_cannot_be_trusted_is_not_kept() -> None:
    rng = np.random.default_rng(1)
    world = _room(rng)
    a, b = np.array([1.0, 1.0, 0.0]), np.array([1.5, 1.2, 0.1])
    truth = between(a, b)
    older, newer = _seen_from(world, a), _seen_from(world, b)
    config = ScanChainConfig()
    # Too few endpoints to pair.
    assert register_pair(older[:10], newer, truth, config) is None
    # A scan of another place: few of its endpoints land on the older scan's walls.
    elsewhere = rng.uniform(-20.0, 20.0, (300, 2))
    assert register_pair(older, elsewhere, truth, config) is None
    # Found, but further from the front end's step than a registration may move it: a wrong minimum.
    strict = dataclasses.replace(config, max_shift_m=0.02)
    assert register_pair(older, newer, compose(truth, np.array([0.1, 0.0, 0.0])), strict) is None
    assert register_pair(older, newer, compose(truth, np.array([0.1, 0.0, 0.0])), config) is not None


def test_the_chain_keeps_the_front_end_s_step_where_no_registration_is_kept() -> None:
    rng = np.random.default_rng(2)
    world = _room(rng)
    poses = np.array([[1.0, 1.0, 0.0], [1.6, 1.1, 0.1], [2.3, 1.0, 0.2], [3.0, 1.2, 0.1]])
    hits = [_seen_from(world, p) for p in poses]
    hits[2] = hits[2][:5]  # a scan with almost nothing in it
    truth = np.zeros_like(poses)
    truth[1:] = between(poses[:-1], poses[1:])
    steps = truth + np.array([0.05, -0.03, 0.02])  # the front end's steps, a few cm off
    steps[0] = 0.0
    chain, measured = scan_chain(hits, steps, ScanChainConfig())
    np.testing.assert_array_equal(measured, [False, True, False, False])
    np.testing.assert_array_equal(chain[0], steps[0])
    np.testing.assert_array_equal(chain[2:], steps[2:])
    assert math.hypot(*(chain[1, :2] - truth[1, :2])) < 0.01
    with pytest.raises(ValueError, match="3 scans for a chain of 4 nodes"):
        scan_chain(hits[:3], steps, ScanChainConfig())


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"stages": ()}, "stages"),
        ({"stages": ((0.0, 3),)}, "stages"),
        ({"stages": ((0.1, 0),)}, "stages"),
        ({"min_pairs": 2}, "min_pairs"),
        ({"min_inlier_fraction": 1.5}, "min_inlier_fraction"),
        ({"max_shift_m": 0.0}, "max_shift_m"),
    ],
)
def test_a_bad_chain_configuration_is_refused(changes: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        ScanChainConfig(**changes)  # type: ignore[arg-type]


def test_the_final_optimisation_needs_a_loop_factor_and_can_be_turned_off() -> None:
    drive = simulate_log(load_world(OFFICE), 8.0, seed=1)
    result = replay(drive.log, RbpfConfig(particles=4, seed=0))
    # Eight seconds hold no loop: nothing holds a chain measured scan to scan, so it does not run.
    assert not result.slam._loops and not result.slam._near_loops
    assert result.slam.stats.final_scan_edges == -1
    assert not result.slam.finish()
    base = RbpfConfig(particles=4, seed=0)
    assert base.loop_closure is not None
    loop_off = dataclasses.replace(base.loop_closure, final_scan_chain=None)
    off = dataclasses.replace(base, loop_closure=loop_off)
    assert not replay(drive.log, off).slam.finish()
