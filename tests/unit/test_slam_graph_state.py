"""The filter's pose graph as it stands (``RbpfSlam.graph_state``, ``loops.GraphState``), what
``benchmarks/slam_error_budget.py`` optimises again with factors replaced: its nodes are the trajectory's,
its chain's steps compose to them, the optimisation of the state as it is moves nothing, and a filter
without loop closure says it keeps no graph."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from agent.slam.loops import chain_poses, optimize_graph
from agent.slam.pose import between, wrap_angle
from agent.slam.rbpf import RbpfConfig
from agent.slam.replay import ReplayResult, replay
from agent.slam.simlog import simulate_log
from drivers.sim.worldfile import load_world

OFFICE = Path(__file__).resolve().parents[2] / "examples" / "worlds" / "office.toml"


@pytest.fixture(scope="module")
def run() -> ReplayResult:
    drive = simulate_log(load_world(OFFICE), 40.0, seed=1)
    return replay(drive.log, RbpfConfig(particles=8, seed=0))


def test_the_graph_is_the_trajectory_and_its_steps(run: ReplayResult) -> None:
    state = run.slam.graph_state()
    path = run.slam.trajectory()[1]
    assert state.path.shape == path.shape and state.path.shape[0] > 10
    np.testing.assert_array_equal(state.path, path)
    # No loop closure moved anything on a 40 s drive: the chain's steps are the lineage's own.
    assert run.slam.stats.loop_rebuilds == 0
    chained = chain_poses(state.path[0], state.motions)
    np.testing.assert_allclose(chained[:, :2], path[:, :2], atol=1e-9)
    np.testing.assert_allclose(wrap_angle(chained[:, 2] - path[:, 2]), 0.0, atol=1e-9)
    odometry = np.array(run.slam.history_odom)
    np.testing.assert_allclose(state.odometry_motions[1:], between(odometry[:-1], odometry[1:]), atol=1e-12)
    assert state.loops == tuple(run.slam._loops)


def test_the_graph_optimised_as_it_stands_moves_nothing(run: ReplayResult) -> None:
    state = run.slam.graph_state()
    config = run.slam.config.loop_closure
    assert config is not None
    result = optimize_graph(
        state.path, state.motions, list(state.loops), config, state.absolute, state.odometry_motions
    )
    assert float(np.max(np.abs(result.poses - state.path))) < 1e-6


def test_a_filter_without_loop_closure_keeps_no_graph() -> None:
    drive = simulate_log(load_world(OFFICE), 2.0, seed=1)
    result = replay(drive.log, dataclasses.replace(RbpfConfig(particles=4, seed=0), loop_closure=None))
    with pytest.raises(ValueError, match="without loop closure"):
        result.slam.graph_state()
