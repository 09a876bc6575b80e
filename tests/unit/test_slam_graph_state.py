"""The filter's pose graph as it stands (``RbpfSlam.graph_state``, ``loops.GraphState``), what
``benchmarks/slam_error_budget.py`` optimises again with factors replaced: its nodes are the trajectory's,
its chain's steps compose to them, the optimisation of the state as it is moves nothing, and a filter
without loop closure says it keeps no graph."""

from __future__ import annotations

import dataclasses
import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from agent.slam.loops import GraphState, chain_poses, optimize_graph
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


def _budget_module() -> ModuleType:
    spec = importlib.util.spec_from_file_location(
        "slam_error_budget", Path(__file__).resolve().parents[2] / "benchmarks" / "slam_error_budget.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_the_budget_s_odometry_snaps_take_the_wheels_forward_step_only_where_the_match_departs() -> None:
    budget = _budget_module()
    motions = np.array([[0.0, 0.0, 0.0], [1.0, 0.02, 0.01], [0.49, -0.01, 0.0], [1.3, 0.0, 0.2]])
    odometry = np.array([[0.0, 0.0, 0.0], [1.05, 0.0, 0.0], [1.01, 0.0, 0.05], [1.0, 0.1, 0.0]])
    state = GraphState(chain_poses(np.zeros(3), motions), motions, odometry, (), None)
    out = budget.odometry_snaps(state, 0.2)
    # Steps 2 (0.52 m short) and 3 (0.3 m long) departed by more than 0.2 m: their forward step is the
    # wheels'; their sideways step and heading, and step 1 (5 cm), are the match's.
    np.testing.assert_array_equal(out[:, 0], [0.0, 1.0, 1.01, 1.0])
    np.testing.assert_array_equal(out[:, 1:], motions[:, 1:])
    np.testing.assert_array_equal(state.motions[2], [0.49, -0.01, 0.0])  # a copy: the state is kept
    assert budget.odometry_snaps(state, 0.6)[2, 0] == 0.49
