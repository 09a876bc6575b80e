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


def test_the_budget_splits_the_steps_disagreement_into_what_every_seed_shares_and_each_seed_s_own() -> None:
    budget = _budget_module()
    rng = np.random.default_rng(3)
    shared = np.zeros((40, 3))
    shared[:, 0] = rng.normal(0.0, 0.05, 40)  # the same forward error in every seed
    odometry = np.zeros((40, 3))
    odometry[:, 0] = 1.5 * shared[:, 0] + rng.normal(0.0, 0.005, 40)  # ... following the wheels' error
    odometry[:, 2] = 0.02
    records = np.stack([np.arange(40), np.arange(1, 41)], axis=1)
    own = [np.zeros((40, 3)), np.zeros((40, 3))]
    own[0][:, 0], own[1][:, 0] = 0.01, -0.01
    own[0][:, 2], own[1][:, 2] = np.radians(0.5), -np.radians(0.5)
    errors = [budget.StepErrors(records, shared + o, odometry) for o in own]
    # A third seed took one more node (step 10 -> 11 split in two): only the steps all three took count.
    extra = budget.StepErrors(
        np.vstack([records[:10], [[10, 100], [100, 11]], records[11:]]),
        np.vstack([shared[:10] - own[0][:10], [[9.0, 9.0, 1.0], [9.0, 9.0, 1.0]], shared[11:] - own[0][11:]]),
        np.vstack([odometry[:10], np.zeros((2, 3)), odometry[11:]]),
    )
    out = budget.shared_and_own([*errors, extra])
    assert out["steps"] == 39 and out["seeds"] == 3
    kept = np.delete(shared[:, 0], 10)
    third = (0.01 - 0.01 - 0.01) / 3.0  # the mean of the three seeds' own parts, in the shared part
    assert out["forward_rms_m"]["shared"] == round(float(np.sqrt(np.mean((kept + third) ** 2))), 4)
    # Own parts: +0.01, -0.01, -0.01 less their mean.
    own_rms = np.sqrt(((0.01 - third) ** 2 + 2 * (0.01 + third) ** 2) / 3)
    assert out["forward_rms_m"]["own"] == pytest.approx(own_rms, abs=1e-4)
    assert out["heading_rms_deg"]["shared"] == pytest.approx(abs(0.5 - 0.5 - 0.5) / 3.0, abs=1e-4)
    assert out["odometry_heading_rms_deg"] == pytest.approx(np.degrees(0.02), abs=1e-4)
    assert out["shared_forward_odometry_correlation"] > 0.95
    # One seed: all of it is shared, none its own.
    alone = budget.shared_and_own(errors[:1])
    assert alone["forward_rms_m"]["own"] == 0.0
    assert alone["forward_rms_m"]["shared"] == alone["forward_rms_m"]["all"]
    with pytest.raises(ValueError, match="no seeds"):
        budget.shared_and_own([])


def test_the_budget_s_steps_are_the_graph_s_less_the_reference_s() -> None:
    budget = _budget_module()
    reference = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, np.pi / 2], [1.0, 1.0, np.pi / 2]])
    motions = np.array([[0.0, 0.0, 0.0], [1.1, 0.0, np.pi / 2], [0.9, 0.05, -0.01]])
    odometry = np.array([[0.0, 0.0, 0.0], [0.8, 0.0, np.pi / 2 + 0.1], [1.0, 0.0, 0.0]])
    state = GraphState(chain_poses(np.zeros(3), motions), motions, odometry, (), None)
    steps = budget.step_errors(state, reference, [0, 5, 9])
    np.testing.assert_array_equal(steps.records, [[0, 5], [5, 9]])
    np.testing.assert_allclose(steps.ours, [[0.1, 0.0, 0.0], [-0.1, 0.05, -0.01]], atol=1e-12)
    np.testing.assert_allclose(steps.odometry, [[-0.2, 0.0, 0.1], [0.0, 0.0, 0.0]], atol=1e-12)
